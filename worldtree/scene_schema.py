"""The scene contract on disk: the typed ``cameras.json`` document and the path-confinement rule.

Every reader and writer of a scene folder goes through this module (docs/scene_format.md): ``nvls build``
writes :meth:`CamerasDoc.to_json`, and the loader, the runner, the video command, gt-priors and
``nvls verify`` read :func:`read_cameras`. A file named inside a scene document is resolved with
:func:`resolve_inside`, so a document can never point outside its scene folder.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from worldtree.infra.errors import UserError

SCHEMA_VERSION = 1
CAMERAS_JSON = "cameras.json"
MANIFEST_JSON = "manifest.json"
CONVENTION = "opencv: x right, y down, z forward; w2c maps world to camera"
# Depth bounds of a document without "near"/"far" (hand-written scenes; `nvls build` always writes them).
DEFAULT_NEAR, DEFAULT_FAR = 0.01, 100.0


def resolve_inside(root: str | Path, rel: str | Path, what: str | Path | None = None) -> Path:
    """``root / rel`` resolved (symbolic links followed), refused unless it lies inside ``root``.

    ``rel`` must be a relative path; an absolute one, a ``..`` that climbs out of ``root``, or a link that
    leads elsewhere is a :class:`UserError` naming ``what`` (the document that named the path; default
    ``root``). The file need not exist.
    """
    root_r = Path(root).resolve()
    where = what if what is not None else root
    p = Path(rel)
    if p.is_absolute() or p.drive:
        raise UserError(f"{where}: path {str(rel)!r} is absolute; scene files are named relative to {root}")
    full = (root_r / p).resolve()
    if full != root_r and root_r not in full.parents:
        raise UserError(f"{where}: path {str(rel)!r} leads outside {root}; fix or rebuild the scene")
    return full


def _bad(path: Path, msg: str) -> UserError:
    return UserError(f"{path}: {msg}; fix it or rebuild the scene with `nvls build`")


def _int(d: dict, key: str, path: Path, where: str, minimum: int | None = None) -> int:
    v = d.get(key)
    if isinstance(v, bool) or not isinstance(v, int | float) or float(v) != int(v):
        raise _bad(path, f"{where}{key!r} must be an integer (got {v!r})")
    if minimum is not None and int(v) < minimum:
        raise _bad(path, f"{where}{key!r} must be at least {minimum} (got {v})")
    return int(v)


def _matrix(v: Any, rows: int, cols: int, path: Path, where: str) -> list[list[float]]:
    ok = isinstance(v, list) and len(v) == rows and all(isinstance(r, list) and len(r) == cols for r in v)
    if ok:
        try:
            m = [[float(x) for x in r] for r in v]
        except (TypeError, ValueError):
            ok = False
    if not ok or not all(math.isfinite(x) for r in m for x in r):
        raise _bad(path, f"{where} must be a {rows}x{cols} matrix of finite numbers")
    return m


@dataclass(frozen=True)
class CameraEntry:
    """One rig camera: intrinsics for the stored image size and its OpenCV world-to-camera pose."""

    id: int
    K: list[list[float]]
    """[3, 3] pixels."""
    w2c: list[list[float]]
    """[4, 4] world-to-camera."""
    dist: list[float] = field(default_factory=lambda: [0.0] * 5)
    """OpenCV distortion of the stored images (zeros: they are undistorted)."""
    near: float | None = None
    far: float | None = None

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {"id": self.id, "K": self.K, "dist": self.dist, "w2c": self.w2c}
        if self.near is not None:
            d["near"], d["far"] = self.near, self.far
        return d


@dataclass(frozen=True)
class FrameEntry:
    """One training or test image: its file (relative to the scene), camera, kept time and raw time."""

    index: int
    file: str
    camera: int
    time: int
    source_time: int | None = None
    mask: str | None = None
    """Test frames only: the dynamic-region mask file (None: no mask)."""

    def to_json(self, with_mask: bool) -> dict[str, Any]:
        d: dict[str, Any] = {"index": self.index, "file": self.file}
        if with_mask:
            d["mask"] = self.mask
        d.update({"camera": self.camera, "time": self.time})
        if self.source_time is not None:
            d["source_time"] = self.source_time
        return d


@dataclass(frozen=True)
class CamerasDoc:
    """``cameras.json`` of a scene (schema 1, docs/scene_format.md)."""

    width: int
    height: int
    test_camera: int
    cameras: list[CameraEntry]
    frames: list[FrameEntry]
    test_frames: list[FrameEntry]
    near: float = DEFAULT_NEAR
    far: float = DEFAULT_FAR
    world_transform: dict[str, Any] | None = None
    convention: str = CONVENTION

    def camera(self, cid: int, path: str | Path = CAMERAS_JSON) -> CameraEntry:
        """The camera with id ``cid``; an unlisted one is a :class:`UserError` naming ``path``."""
        for c in self.cameras:
            if c.id == cid:
                return c
        raise UserError(f"{path}: camera {cid} is not listed under 'cameras'; fix it or rebuild the scene")

    def to_json(self) -> dict[str, Any]:
        """The document as written to ``cameras.json``."""
        out: dict[str, Any] = {
            "schema": SCHEMA_VERSION,
            "width": self.width,
            "height": self.height,
            "convention": self.convention,
            "test_camera": self.test_camera,
            "cameras": [c.to_json() for c in self.cameras],
            "frames": [f.to_json(with_mask=False) for f in self.frames],
            "test_frames": [f.to_json(with_mask=True) for f in self.test_frames],
            "near": self.near,
            "far": self.far,
        }
        if self.world_transform is not None:
            out["world_transform"] = self.world_transform
        return out

    @classmethod
    def from_json(cls, meta: Any, path: str | Path, root: str | Path | None = None) -> CamerasDoc:
        """Check ``meta`` (parsed JSON) against schema 1; with ``root``, every file must lie inside it.

        Every problem is a :class:`UserError` naming ``path`` and the key.
        """
        path = Path(path)
        if not isinstance(meta, dict):
            raise _bad(path, "not a JSON object")
        if meta.get("schema") != SCHEMA_VERSION:
            raise UserError(f"{path}: schema {meta.get('schema')!r}, this tool reads {SCHEMA_VERSION}; rebuild it")
        width = _int(meta, "width", path, "", 1)
        height = _int(meta, "height", path, "", 1)
        cams_raw = meta.get("cameras")
        if not isinstance(cams_raw, list) or not cams_raw:
            raise _bad(path, "'cameras' must be a non-empty list")
        cameras = [_camera(c, path, i) for i, c in enumerate(cams_raw)]
        ids = [c.id for c in cameras]
        if len(set(ids)) != len(ids):
            raise _bad(path, f"camera ids repeat ({ids})")
        frames = _frames(meta.get("frames"), "frames", path, root, ids)
        test_frames = _frames(meta.get("test_frames", []), "test_frames", path, root, ids)
        test_camera = _int(meta, "test_camera", path, "") if "test_camera" in meta else 1
        near = _bound(meta, "near", DEFAULT_NEAR, path)
        far = _bound(meta, "far", DEFAULT_FAR, path)
        wt = meta.get("world_transform")
        return cls(
            width=width, height=height, test_camera=test_camera, cameras=cameras, frames=frames,
            test_frames=test_frames, near=near, far=far, world_transform=wt if isinstance(wt, dict) else None,
            convention=str(meta.get("convention", CONVENTION)),
        )  # fmt: skip


def _bound(meta: dict, key: str, default: float, path: Path) -> float:
    v = meta.get(key, default)
    try:
        f = float(v)
    except (TypeError, ValueError):
        f = math.nan
    if not math.isfinite(f):
        raise _bad(path, f"{key!r} must be a finite number (got {v!r})")
    return f


def _camera(c: Any, path: Path, i: int) -> CameraEntry:
    where = f"cameras[{i}]."
    if not isinstance(c, dict):
        raise _bad(path, f"cameras[{i}] must be an object")
    dist = c.get("dist", [0.0] * 5)
    if not isinstance(dist, list) or not all(isinstance(x, int | float) for x in dist):
        raise _bad(path, f"{where}dist must be a list of numbers")
    near, far = c.get("near"), c.get("far")
    return CameraEntry(
        id=_int(c, "id", path, where),
        K=_matrix(c.get("K"), 3, 3, path, f"{where}K"),
        w2c=_matrix(c.get("w2c"), 4, 4, path, f"{where}w2c"),
        dist=[float(x) for x in dist],
        near=float(near) if isinstance(near, int | float) else None,
        far=float(far) if isinstance(far, int | float) else None,
    )


def _frames(raw: Any, key: str, path: Path, root: str | Path | None, ids: list[int]) -> list[FrameEntry]:
    if not isinstance(raw, list):
        raise _bad(path, f"{key!r} must be a list")
    out = []
    for i, f in enumerate(raw):
        where = f"{key}[{i}]."
        if not isinstance(f, dict) or not isinstance(f.get("file"), str):
            raise _bad(path, f"{key}[{i}] must be an object with a 'file' string")
        mask = f.get("mask")
        if mask is not None and not isinstance(mask, str):
            raise _bad(path, f"{where}mask must be a file name or null")
        if root is not None:
            resolve_inside(root, f["file"], path)
            if mask:
                resolve_inside(root, mask, path)
        cam = _int(f, "camera", path, where)
        if cam not in ids:
            raise UserError(f"{path}: frame refers to camera {cam}, which is not listed")
        st = f.get("source_time")
        out.append(
            FrameEntry(
                index=_int(f, "index", path, where) if "index" in f else i,
                file=f["file"],
                camera=cam,
                time=_int(f, "time", path, where, 0),
                source_time=int(st) if isinstance(st, int | float) and not isinstance(st, bool) else None,
                mask=mask,
            )
        )
    return out


def read_cameras(root: str | Path) -> CamerasDoc:
    """``root/cameras.json`` parsed and checked (files confined to ``root``); :class:`UserError` otherwise."""
    path = Path(root) / CAMERAS_JSON
    meta = _read_scene_json(path, f"missing; is {root} a scene written by `nvls build`?")
    return CamerasDoc.from_json(meta, path, root)


def _read_scene_json(path: Path, missing: str) -> Any:
    """The parsed JSON of a scene document; :class:`UserError` ``"{path}: {missing}"`` when absent, and one
    naming the line when it is not JSON."""
    if not path.is_file():
        raise UserError(f"{path}: {missing}")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        msg = f"{e.msg} at line {e.lineno}" if isinstance(e, json.JSONDecodeError) else str(e)
        raise UserError(f"{path}: not valid JSON ({msg}); rebuild the scene") from e


_HEX = frozenset("0123456789abcdef")


def _checked_manifest(man: Any, path: Path, root: Path) -> dict[str, Any]:
    if not isinstance(man, dict):
        raise _bad(path, "not a JSON object")
    files = man.get("files", {})
    if not isinstance(files, dict):
        raise _bad(path, "'files' must be an object {relative path: sha256}")
    for rel, digest in files.items():
        if not (isinstance(digest, str) and len(digest) == 64 and set(digest) <= _HEX):
            raise _bad(path, f"files[{rel!r}] must be a 64-digit hex sha256")
        resolve_inside(root, rel, f"{path}: files[{rel!r}]")
    counts = man.get("counts", {})
    if not isinstance(counts, dict):
        raise _bad(path, "'counts' must be an object")
    for key in ("frames", "test_frames", "masks", "cameras"):
        v = counts.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 0):
            raise _bad(path, f"counts.{key} must be a whole number >= 0 (got {v!r})")
    train = man.get("train_cameras")
    if train is not None and not (
        isinstance(train, list) and all(isinstance(c, int) and not isinstance(c, bool) for c in train)
    ):
        raise _bad(path, "'train_cameras' must be a list of camera ids")
    return man


def read_manifest(root: str | Path) -> dict[str, Any]:
    """``root/manifest.json`` parsed and checked: an object whose ``files`` map relative paths (each
    resolving inside ``root``, links followed) to sha256 hex digests, with whole-number ``counts`` and a
    ``train_cameras`` id list when present. Any problem is a one-line :class:`UserError` naming the entry;
    nothing outside ``root`` is opened."""
    root = Path(root)
    path = root / MANIFEST_JSON
    man = _read_scene_json(path, "missing (not a scene built by `nvls build`?)")
    return _checked_manifest(man, path, root)
