"""Runs of registered methods sharing their first stages: which may (``root_differences``), what one holds
(``lendable``), and linking its checkpoints into another's checkpoint folder (``lend_root``).

Rule: a method that declares a :class:`methods.plugin.SharedRoot` may take the checkpoints of its first stages
from a run of one of the methods it names, on the same scene, with the same imported priors, whose config
agrees on every field both configs have except the declared free ones (a tree's depth, its children's
settings) and on the ablations that change those stages. CPU runs are deterministic, so the run goes on
exactly as if it had trained them itself.

Each checkpoint is a hard link where the file system allows, a copy otherwise, made under a temporary name and
renamed: an interruption leaves the whole item or none, and since every checkpoint is written by renaming a
new file over the old one, neither run's later writes reach the other's. ``root_from.json`` in the
borrower's checkpoint folder records the lender and the seconds its lent stages took there (with its own
lender's, where it was itself grown on a root). Callers: ``wtbench run --root-from`` and ``wtbench sweep
--share-root`` (:mod:`benchmarks.runner.shared_root`), the leave-one-out tool.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from worldtree.infra.atomic import atomic_write_json
from worldtree.infra.errors import UserError

__all__ = [
    "ROOT_FROM_FILE", "LentRoot", "held", "lend_root", "lendable", "plan_lenders", "read_run_json",
    "root_differences", "root_from_record",
]

ROOT_FROM_FILE = "root_from.json"
"""Under the run's ``checkpoints/``: where its root came from and what that root cost."""


@dataclass(frozen=True)
class LentRoot:
    """What a run takes from another one: checked by :func:`check_root_from`, linked by :func:`lend_root`."""

    source: Path
    """The lending run folder (absolute)."""
    method: str
    """The lending run's method."""
    items: tuple[str, ...]
    """Checkpoint names (files or folders under ``checkpoints/``) the lending run holds, in stage order."""
    stages_s: dict[str, float] = field(default_factory=dict)
    """Wall seconds of the lent stages in the lending run (its lender's included), by stage."""
    stages_cpu_s: dict[str, float] = field(default_factory=dict)
    """CPU seconds of the same."""

    def record(self) -> dict[str, Any]:
        return {
            "run": str(self.source),
            "method": self.method,
            "items": list(self.items),
            "stages_s": self.stages_s,
            "stages_cpu_s": self.stages_cpu_s,
        }


def read_run_json(path: Path, what: str) -> dict[str, Any]:
    """The JSON object of a run's file ``path`` (``what`` names it in the one-line error)."""
    try:
        out = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise UserError(f"--root-from: {path}: unreadable {what} ({e}); give a run folder written by wtbench run") from e
    if not isinstance(out, dict):
        raise UserError(f"--root-from: {path}: not a {what}; give a run folder written by wtbench run")
    return out


def _config_differences(src: dict[str, Any], dst: dict[str, Any], free: tuple[str, ...]) -> list[str]:
    """Top-level config fields both have, outside ``free`` and ``ablate``, whose recorded values differ."""
    keys = (set(src) & set(dst)) - set(free) - {"ablate"}
    return sorted(k for k in keys if src[k] != dst[k])


def _stage_seconds(source: Path, ledger: str, stages: tuple[str, ...]) -> tuple[dict[str, float], dict[str, float]]:
    """The lending run's seconds of ``stages`` (its ledger, plus its own lender's record)."""
    wall: dict[str, float] = {}
    cpu: dict[str, float] = {}
    docs = [root_from_record(source / "checkpoints")]
    if ledger and (source / "checkpoints" / ledger).is_file():
        docs.append(read_run_json(source / "checkpoints" / ledger, "stage ledger"))
    for doc in filter(None, docs):
        for out, key in ((wall, "stages_s"), (cpu, "stages_cpu_s")):
            vals = doc.get(key)
            for st in stages:
                v = vals.get(st) if isinstance(vals, dict) else None
                if isinstance(v, int | float):
                    out[st] = out.get(st, 0.0) + float(v)
    return wall, cpu


def root_differences(shared: Any, src: dict[str, Any], dst: dict[str, Any]) -> str | None:
    """Why a run recorded as ``src`` (its config.json) may not lend its first stages to one recorded as ``dst``
    under ``shared`` (:class:`methods.plugin.SharedRoot`), in a few words; None when it may."""
    if src.get("method") not in shared.methods:
        return f"a {src.get('method')!r} run; this method takes a root from {', '.join(shared.methods)} runs"
    if src.get("scene") != dst.get("scene"):
        return f"trained on {src.get('scene')}, not on {dst.get('scene')}; give a run of this scene"
    if (src.get("imported_priors") or {}) != (dst.get("imported_priors") or {}):
        return (f"imported other priors ({src.get('imported_priors') or 'none'}); give a run with the same "
                "--masks/--tracks/--depth-maps/--flow")  # fmt: skip
    # Through JSON, so that a record made here (tuples) compares with one read from config.json (lists).
    src_cfg, dst_cfg = (json.loads(json.dumps(r.get("config"), default=str)) for r in (src, dst))
    if not isinstance(src_cfg, dict) or not isinstance(dst_cfg, dict):
        return "its config.json has no config; give a run folder written by wtbench run"
    diff = _config_differences(src_cfg, dst_cfg, shared.free_fields)
    if diff:
        shown = ", ".join(diff[:4]) + (f" and {len(diff) - 4} more" if len(diff) > 4 else "")
        free = f" (only {', '.join(shared.free_fields)} may)" if shared.free_fields else ""
        return f"its config differs in {shown}{free}; give a run of the same preset and settings"
    ablated = [set(c.get("ablate") or ()) & set(shared.root_ablations) for c in (src_cfg, dst_cfg)]
    if ablated[0] != ablated[1]:
        return (f"ablates {sorted(ablated[0]) or 'nothing'} of {', '.join(shared.root_ablations)} where this run "
                f"ablates {sorted(ablated[1]) or 'nothing'}; give a run with the same")  # fmt: skip
    return None


def lendable(source: Path, method: str, shared: Any) -> LentRoot:
    """What the folder ``source`` (a run folder, or any folder with the run's ``checkpoints/``) of a
    ``method`` run holds of ``shared``'s checkpoints, and their seconds there; unchecked (the caller has
    compared the configs: :func:`root_differences`)."""
    source = Path(source).resolve()
    items = held(source / "checkpoints", shared.checkpoints)
    wall, cpu = _stage_seconds(source, shared.ledger, shared.stages)
    return LentRoot(source, method, items, wall, cpu)


def held(checkpoints: Path, names: tuple[str, ...]) -> tuple[str, ...]:
    """Those of ``names`` (checkpoint files or folders) present in the checkpoint folder ``checkpoints``."""
    return tuple(n for n in names if (Path(checkpoints) / n).exists())


def plan_lenders(shared: Any, records: list[dict[str, Any]]) -> list[int | None]:
    """For runs recorded as ``records`` (in the order a sweep lists them), the index of the run each one takes
    its first stages from: the first earlier run that trains its own and may lend them (None: it trains its
    own). A run that borrows never lends, so every root is trained once, by the first run that needs it."""
    lenders: list[int | None] = []
    for i, dst in enumerate(records):
        pick = None
        for j in range(i):
            if lenders[j] is None and root_differences(shared, records[j], dst) is None:
                pick = j
                break
        lenders.append(pick)
    return lenders


def root_from_record(checkpoints: Path) -> dict[str, Any] | None:
    """The ``root_from.json`` of a run's checkpoint folder (None when the run trained its own root)."""
    path = Path(checkpoints) / ROOT_FROM_FILE
    if not path.is_file():
        return None
    try:
        out = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return out if isinstance(out, dict) else None


def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst)
    except OSError:  # another file system, or links not allowed
        shutil.copy2(src, dst)


def lend_root(lent: LentRoot, checkpoints: Path, shared_names: tuple[str, ...]) -> list[str]:
    """Link ``lent``'s checkpoints into the run's ``checkpoints`` folder, recorded first in ``root_from.json``;
    the names linked. A later session with the same lender links only what is still missing (a session
    interrupted while linking, or a lender that trained further since); the run's own checkpoints stay.
    ``shared_names``: every checkpoint the method could lend; a run that holds one of them without a record
    trained it itself and is refused."""
    checkpoints = Path(checkpoints)
    have = root_from_record(checkpoints)
    if have is not None and Path(str(have.get("run", ""))) != lent.source:
        raise UserError(f"--root-from {lent.source}: this run was grown on {have.get('run')}'s root; give that "
                        "run, or --force to start again")  # fmt: skip
    if have is None:
        own = held(checkpoints, shared_names)
        if own:
            raise UserError(f"--root-from {lent.source}: this run already trained {', '.join(own)} itself; drop "
                            "--root-from to resume it, or --force to start again")  # fmt: skip
        atomic_write_json(checkpoints / ROOT_FROM_FILE, lent.record())
    linked = []
    for name in lent.items:
        src, dst = lent.source / "checkpoints" / name, checkpoints / name
        if dst.exists():
            continue
        tmp = checkpoints / f".{name}.lent.tmp"
        if tmp.is_dir():
            shutil.rmtree(tmp)
        else:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        if src.is_dir():
            # A checkpoint being written there now is a hidden temporary file: not taken.
            shutil.copytree(src, tmp, copy_function=_link_or_copy, ignore=shutil.ignore_patterns(".*"))
        else:
            _link_or_copy(str(src), str(tmp))
        os.replace(tmp, dst)
        linked.append(name)
    if linked and have is not None:
        atomic_write_json(checkpoints / ROOT_FROM_FILE, lent.record())  # the lender's seconds as they are now
    return linked
