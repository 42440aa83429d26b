"""On-disk cache of computed priors, keyed by their inputs, their settings and the tool version.

Layout under the cache root (``<scene>/priors/`` by default)::

    <component>-<key16>/meta.json        what the entry holds: component, full key, settings, inputs, version
    <component>-<key16>/<item>.npz       one file per frame (depth) or frame pair (flow), or one ``all.npz``
    <component>-<key16>/COMPLETE         written last: every item is present

Every file is written to a temporary name and renamed, so an interrupted run leaves only whole items; the next
run with the same inputs finds them and computes only the missing ones (resumable per frame). A change in the
images, cameras, settings or ``worldtree.__version__`` changes the key, hence the folder.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np

import worldtree
from worldtree.infra.atomic import atomic_write_bytes, atomic_write_json, atomic_write_text


def _canonical(obj: Any) -> Any:
    if is_dataclass(obj) and not isinstance(obj, type):
        return {"__type__": type(obj).__name__, **{k: _canonical(v) for k, v in asdict(obj).items()}}
    if isinstance(obj, dict):
        return {str(k): _canonical(v) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
    if isinstance(obj, (list, tuple)):
        return [_canonical(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return obj


def hash_key(*parts: Any) -> str:
    """Hex sha256 of the canonical JSON of ``parts`` plus the tool version."""
    payload = json.dumps([_canonical(p) for p in parts] + [worldtree.__version__], sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()


def inputs_fingerprint(images_u8: np.ndarray, Ks: np.ndarray, w2cs: np.ndarray) -> str:
    """Hex sha256 over the frames' bytes ``[T,H,W,3]`` uint8 and their cameras (rounded to 1e-9)."""
    h = hashlib.sha256()
    h.update(repr(images_u8.shape).encode())
    h.update(np.ascontiguousarray(images_u8).tobytes())
    for a in (Ks, w2cs):
        h.update(np.round(np.asarray(a, np.float64), 9).tobytes())
    return h.hexdigest()


class CacheEntry:
    """One cached prior: a folder of ``.npz`` items plus its meta record."""

    def __init__(self, folder: Path, meta: dict) -> None:
        self.folder = folder
        self.meta = meta

    def _path(self, item: str) -> Path:
        return self.folder / f"{item}.npz"

    def has(self, item: str) -> bool:
        return self._path(item).is_file()

    def save(self, item: str, **arrays: np.ndarray) -> None:
        """Write arrays as one item atomically (compressed npz)."""
        self._ensure_meta()
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)
        atomic_write_bytes(self._path(item), buf.getvalue())

    def load(self, item: str) -> dict[str, np.ndarray] | None:
        """The arrays of an item, or None when it is missing or unreadable (then it is recomputed)."""
        p = self._path(item)
        if not p.is_file():
            return None
        try:
            with np.load(p, allow_pickle=False) as z:
                return {k: z[k] for k in z.keys()}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile):
            p.unlink(missing_ok=True)
            return None

    @property
    def complete(self) -> bool:
        return (self.folder / "COMPLETE").is_file()

    def mark_complete(self) -> None:
        self._ensure_meta()
        atomic_write_text(self.folder / "COMPLETE", "ok\n")

    def _ensure_meta(self) -> None:
        if not (self.folder / "meta.json").is_file():
            self.folder.mkdir(parents=True, exist_ok=True)
            atomic_write_json(self.folder / "meta.json", self.meta)


class PriorCache:
    """Cache root; ``None`` as root gives a cache that stores nothing (every prior is computed)."""

    def __init__(self, root: str | Path | None) -> None:
        self.root = Path(root) if root is not None else None

    def entry(self, component: str, key: str, meta: dict) -> CacheEntry | None:
        """The entry of ``component`` under ``key`` (None when caching is off)."""
        if self.root is None:
            return None
        record = {"component": component, "key": key, "version": worldtree.__version__, **meta}
        return CacheEntry(self.root / f"{component}-{key[:16]}", _canonical(record))
