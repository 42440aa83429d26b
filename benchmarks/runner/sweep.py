"""Named grids of run configurations and a runner that executes them over scenes.

A grid is a list of :class:`~methods.plugin.GridPoint` (a method's options, its ablations, common overrides).
Each method declares its own grids (``MethodSpec.grids``); the harness adds only :data:`HARNESS_GRIDS`, which
work with every method (``seeds``). The runner
turns every (scene, point) pair into a :class:`benchmarks.runner.runs.RunRequest`; runs that already finished are
skipped by :func:`benchmarks.runner.runs.execute` itself, and a failing run is recorded and the sweep goes on.
Settings common to the whole grid (``--set KEY=VALUE``, imported priors) are not grid points: `wtbench sweep`
puts them into every request (``RunRequest.sets`` / ``RunRequest.priors``), so they name every run folder.
"""

from __future__ import annotations

import json
import socket
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import worldtree
from methods.plugin import Grid, GridPoint
from worldtree.infra.atomic import atomic_write_json
from worldtree.infra.errors import UserError

#: Grids of the harness, for every method (a method's own grid may not take these names).
HARNESS_GRIDS: dict[str, Grid] = {
    "seeds": Grid(
        "seeds 0..3 of one configuration (run-to-run spread; works with every method)",
        lambda: [GridPoint(f"seed {k}", overrides={"seed": k}) for k in range(4)],
    ),
}


def grids_of(spec) -> dict[str, Grid]:
    """The grids ``wtbench sweep --method NAME`` accepts: the method's own (``spec.grids``), then the harness's."""
    clash = set(spec.grids) & set(HARNESS_GRIDS)
    if clash:
        raise TypeError(f"method {spec.name!r}: grid names {sorted(clash)} are the harness's; rename them")
    return {**spec.grids, **HARNESS_GRIDS}


def resolve_grid(method: str | None, grid: str | None) -> tuple[str, str]:
    """``(method, grid)`` of ``wtbench sweep``: a grid a single method declares names its method; a method alone
    names its first grid. Anything else missing or unknown is a :class:`UserError` listing the choices."""
    from methods.registry import get_method, list_methods

    if method is not None:
        spec = get_method(method)
        known = grids_of(spec)
        if grid is None:
            if not spec.grids:
                raise UserError(f"--method {method}: has no grid of its own; give --grid {', '.join(known)}")
            return method, next(iter(spec.grids))
        if grid not in known:
            raise UserError(f"--grid {grid}: method {method!r} has the grids {', '.join(known)}")
        return method, grid
    specs = list_methods()
    owners = [s.name for s in specs if grid in s.grids]
    if grid is not None and len(owners) == 1:
        return owners[0], grid
    listing = "; ".join(f"{s.name}: {', '.join(s.grids)}" for s in specs if s.grids)
    listing += f"; every method: {', '.join(HARNESS_GRIDS)}"
    if grid is None:
        raise UserError(f"`wtbench sweep` needs --grid NAME (and --method NAME for a shared one): {listing}")
    if owners or grid in HARNESS_GRIDS:
        where = f"methods {', '.join(owners)} have" if owners else "every method has"
        raise UserError(f"--grid {grid}: {where} it; name one with --method")
    raise UserError(f"--grid {grid!r}: unknown grid; grids are {listing}")


def grid_points(name: str, spec) -> list[GridPoint]:
    """The configurations of the grid ``name`` of ``spec``'s method (see :func:`grids_of`)."""
    known = grids_of(spec)
    if name not in known:
        choices = ", ".join(known)
        raise UserError(f"--grid {name!r}: unknown grid of method {spec.name!r}; choose one of {choices}")
    return known[name].points()


def find_scenes(paths: Sequence[str | Path]) -> list[Path]:
    """Scene folders named by ``paths``: a scene folder itself (holding cameras.json) or a folder of them."""
    scenes: list[Path] = []
    for p in map(Path, paths):
        if (p / "cameras.json").is_file():
            scenes.append(p)
        elif p.is_dir():
            found = sorted(q for q in p.iterdir() if (q / "cameras.json").is_file())
            if not found:
                raise UserError(f"--scenes {p}: holds no scene folder (no */cameras.json); run `nvls build`")
            scenes.extend(found)
        else:
            raise UserError(f"--scenes {p}: no such folder; give scene folders written by `nvls build`")
    return scenes


@dataclass
class SweepOutcome:
    """What happened to one (scene, grid point) run."""

    scene: str
    label: str
    status: str  # "done", "skipped" (finished before), "failed" or "elsewhere" (another sweep has it)
    folder: str | None = None
    error: str | None = None
    mean: dict[str, float] = field(default_factory=dict)
    # Where and how it ran (None for runs not run by this sweep): the executor, its job id, the host and
    # device, seconds from submission to start and from start to end, and the job's log.
    executor: str | None = None
    job_id: str | None = None
    host: str | None = None
    device: str | None = None
    queue_wait_s: float | None = None
    wall_s: float | None = None
    log: str | None = None


def run_sweep(
    scenes: Sequence[Path],
    points: Sequence[GridPoint],
    make_request: Callable[[Path, GridPoint], Any],
    execute: Callable[[Any], Any],
    log: Callable[[str], None] = print,
) -> list[SweepOutcome]:
    """Run every (scene, point); a failure is logged and recorded, never stops the sweep."""
    outcomes = []
    total = len(scenes) * len(points)
    i = 0
    for scene in scenes:
        for pt in points:
            i += 1
            log(f"[{i}/{total}] {scene.name}: {pt.label}")
            t0 = time.time()
            try:
                res = execute(make_request(scene, pt))
            except KeyboardInterrupt:
                raise
            except Exception as e:  # one broken run must not lose the rest of a long sweep
                msg = str(e).splitlines()[0] if str(e) else type(e).__name__
                detail = msg if isinstance(e, UserError) else f"{type(e).__name__}: {msg}"
                log(f"  failed: {detail}")
                if not isinstance(e, UserError):
                    log("  " + traceback.format_exc().strip().splitlines()[-1])
                outcomes.append(SweepOutcome(scene.name, pt.label, "failed", error=detail))
                continue
            status = "skipped" if res.skipped else "done"
            outcome = SweepOutcome(scene.name, pt.label, status, str(res.folder.root), mean=dict(res.mean))
            if not res.skipped:
                outcome.executor, outcome.host = "in-process", socket.gethostname()
                outcome.device, outcome.wall_s = run_device(Path(res.folder.root)), time.time() - t0
            outcomes.append(outcome)
    return outcomes


def run_device(root: Path) -> str | None:
    """The device a finished run trained on, from its ``timing.json`` (None when unreadable)."""
    try:
        return json.loads((root / "timing.json").read_text()).get("device")
    except (OSError, ValueError, AttributeError):
        return None


def write_report(path: Path, grid: str, outcomes: Sequence[SweepOutcome], config: dict[str, Any]) -> None:
    """Write the sweep's JSON report (each run's status, folder, error and mean scores)."""
    atomic_write_json(
        path,
        {
            "grid": grid,
            "config": config,
            "tool_version": worldtree.__version__,
            "timestamp": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "runs": [json.loads(json.dumps(o.__dict__, default=str)) for o in outcomes],
        },
    )
