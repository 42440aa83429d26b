"""A run grown on another run's root (``wtbench run --root-from RUN``, ``wtbench sweep --share-root``): the
run-folder side of :mod:`methods.shared_root` (which runs may share, and the linking).

``wtbench run --root-from RUN`` checks the lending run folder (its config.json against this run's, its device
kind, that it holds some of the checkpoints) before anything is written, then links them under the run
folder's lock. The run folder must hold none of those checkpoints yet (a run that trained part of its own
root keeps it). ``timing.json`` carries ``checkpoints/root_from.json`` as ``root_from`` and the table adds its
seconds to the run's time, so a tree grown on a lent root costs in the table what it would have cost alone.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from methods.shared_root import LentRoot, held, lendable, read_run_json, root_differences, root_from_record
from worldtree.infra.errors import UserError

__all__ = ["check_root_from", "sweep_lender"]


def _device_kind(name: Any) -> str | None:
    """``cpu`` / ``cuda`` of a recorded device name; None for ``auto`` (not known from the name)."""
    name = str(name)
    if name.startswith("cuda"):
        return "cuda"
    return "cpu" if name == "cpu" else None


def check_root_from(source: Path, target: Path, spec: Any, record: dict[str, Any], device_kind: str) -> LentRoot:
    """What the run of ``spec`` (its config.json ``record``, to be written in run folder ``target``, on a device
    of kind ``device_kind``) may take from the run folder ``source``; a one-line :class:`UserError` naming the
    difference when it may not. Reads only."""
    shared = spec.shared_root
    if shared is None:
        raise UserError(f"--root-from: method {spec.name!r} trains every stage itself; drop --root-from")
    source = Path(source).resolve()
    if not (source / "config.json").is_file():
        raise UserError(f"--root-from {source}: not a run folder (no config.json); give a folder written by wtbench run")
    if source == Path(target).resolve():
        raise UserError(f"--root-from {source}: that is this run's own folder; give another run")
    src = read_run_json(source / "config.json", "config.json")
    where = f"--root-from {source}"
    why = root_differences(shared, src, record)
    if why is not None:
        raise UserError(f"{where}: {why}")
    timing = source / "timing.json"
    src_kind = _device_kind(read_run_json(timing, "timing.json").get("device")) if timing.is_file() else None
    src_kind = src_kind or _device_kind(src.get("device"))
    if src_kind is not None and src_kind != device_kind:
        raise UserError(f"{where}: trained on {src_kind}, this run is on {device_kind}; give a run of the same device kind")
    lent = lendable(source, str(src["method"]), shared)
    if not lent.items:
        raise UserError(f"{where}: holds none of {', '.join(shared.checkpoints)} under checkpoints/ yet; "
                        "let it train first")  # fmt: skip
    return lent


def sweep_lender(lender: Path, borrower: Path, shared: Any) -> Path | None:
    """``lender`` when a sweep's run in folder ``borrower`` should take its root from it now: the lender holds a
    config.json and some of ``shared``'s checkpoints (one that failed early leaves its borrowers to train
    alone), and the borrower did not train any of them itself (an earlier sweep without sharing). Else None."""
    from benchmarks.runner.runs import RunFolder

    lender, borrower = Path(lender), Path(borrower)
    ready = (lender / "config.json").is_file() and bool(held(lender / "checkpoints", shared.checkpoints))
    own = root_from_record(borrower / "checkpoints") is None and bool(held(borrower / "checkpoints", shared.checkpoints))
    return lender if ready and not own and not RunFolder(borrower).is_done() else None
