"""Named grids of run configurations and a runner that executes them over scenes.

A grid is a list of :class:`GridPoint` (method options such as ablations, depth, chain length). The runner
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
from worldtree.atomic import atomic_write_json
from worldtree.errors import UserError


@dataclass(frozen=True)
class GridPoint:
    """One configuration of a grid: a label, the method options it sets (``RunRequest.options``) and the
    common fields it overrides (``RunRequest.overrides``: steps, seed, downscale)."""

    label: str
    options: dict[str, Any] = field(default_factory=dict)
    overrides: dict[str, int] = field(default_factory=dict)


def _ablation_rows() -> list[GridPoint]:
    # The paper's Table (BA, SW) x (TPT, SAC): BA/SW in {off/off, on/off, on/on}, TPT/SAC likewise.
    rows = []
    for ba, sw in ((False, False), (True, False), (True, True)):
        for tpt, sac in ((False, False), (True, False), (True, True)):
            ablate = [n for n, on in (("ba", ba), ("sw", sw), ("tpt", tpt), ("sac", sac)) if not on]
            if not tpt:
                ablate.remove("sac")  # root only: SAC has no ancestors to use, `tpt` says it all
            flags = "".join("+" if on else "-" for on in (ba, sw, tpt, sac))
            label = f"BA{flags[0]} SW{flags[1]} TPT{flags[2]} SAC{flags[3]}"
            rows.append(GridPoint(label, {"ablate": sorted(ablate)} if ablate else {}))
    return rows


GRIDS: dict[str, tuple[str, Callable[[], list[GridPoint]]]] = {
    "paper-ablation": ("the paper's 9-row ablation: (BA, SW) x (TPT, SAC)", _ablation_rows),
    "depth": (
        "tree depth 0..4 (the paper's depth study)",
        lambda: [GridPoint(f"depth {d}", {"depth": d}) for d in range(5)],
    ),
    "adaptive": (
        "fixed tree depths 0..3 and --depth auto (criterion-grown tree, Gaussian budget, early stop)",
        lambda: (
            [GridPoint(f"depth {d}", {"depth": d}) for d in (0, 1, 2, 3)]
            + [GridPoint("depth auto", {"depth": "auto"})]
        ),
    ),
    "tree": (
        "the root alone (depth 0), fixed depths 1 and 2, and --depth auto: does the tree beat its root?",
        lambda: [GridPoint(f"depth {d}", {"depth": d}) for d in (0, 1, 2, "auto")],
    ),
    "chain": (
        "chain length 0..4 at depth 4 (the paper's chain-length study)",
        lambda: [GridPoint(f"chain {k}", {"depth": 4, "chain_length": k}) for k in range(5)],
    ),
    "split": (
        "split strategies binary, gradient, flow",
        lambda: [GridPoint(f"split {s}", {"split": s}) for s in ("binary", "gradient", "flow")],
    ),
    "seeds": (
        "seeds 0..3 of one configuration (run-to-run spread; works with every method)",
        lambda: [GridPoint(f"seed {k}", overrides={"seed": k}) for k in range(4)],
    ),
}


def grid_points(name: str) -> list[GridPoint]:
    """The configurations of the grid ``name`` (see :data:`GRIDS`)."""
    if name not in GRIDS:
        raise UserError(f"--grid {name!r}: unknown grid; choose one of {', '.join(GRIDS)}")
    return GRIDS[name][1]()


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
