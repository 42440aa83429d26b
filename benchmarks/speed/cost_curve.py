"""The cost curve: wall time, CPU time and peak memory of static, Base and WorldTree against frames x pixels.

    python -m benchmarks.speed.cost_curve OUT [--frames 40,80,160] [--sizes 160x90,320x180,480x270]
        [--methods static,base,worldtree-d2,worldtree-auto] [--presets quick,paper] [--device auto]
        [--max-minutes M] [--dry-run] [--report-only] [--no-probe]

For every frame count F and size WxH it generates a scene of the NVIDIA-LS layout (`nvls synth`: the
12-camera rig, F time steps rendered at WxH, the demo's slow_fast motion; `nvls build` with the generator's
exact poses, so no SfM time is mixed in) under OUT/scenes, then runs `wtbench run` on it for each method and
preset into OUT/runs/<scene>/<method>/<tag>, one subprocess at a time so that each run is measured alone.
The quick preset trains at a downscale (printed with the cells and written in the table); the scene's size
is what the run is scored at. Base and WorldTree run with ``priors_cache=false`` so that every run computes
its own 2D priors (a cached copy would make whichever ran second look cheaper).

Per run it records the run's own figures from ``timing.json`` (``wall_time_s``, ``cpu_time_s`` and peak memory
as ``wtbench table`` counts them: docs/tables.md; per-stage wall and CPU seconds; Gaussian count), mPSNR and
PSNR, and from outside the process: its wall time, CPU time (user + system of the process and every process
it waited for: the tree's workers, the kernel build, evaluation and start-up included) and the largest RSS of
any one of them, the load average when it started and ended, the machine (``machine_info.describe``) and the
machine's speed just before and after the run (``speed_probe``: one fixed rasterizer forward + backward, 20,000
Gaussians at 320x180, in ms; a shared machine's speed drifts by 1.4x between sessions at equal load, which the
load average does not show, so a cell's times are read beside it; ``--no-probe`` leaves it out).
A cell's record is kept in OUT/cells/<cell>.json, its output in OUT/logs/<cell>.log.

Writes OUT/cost.csv, OUT/cost.md, OUT/cost.png (time and memory against frames x pixels, log-log, one line
per method/preset, a slope-1 reference) and OUT/cost_stages.png (CPU seconds per stage), and prints the fitted
log-log slope of each cost per method/preset and per stage: cost = c * work^k, ``k > 1.15`` flagged as
growing faster than the work.

Resumable: a cell whose run folder holds DONE is not run again (its figures are read back); an interrupted
run is resumed by `wtbench run` itself from its last checkpoint. ``--max-minutes`` stops the sweep before a
run whose estimated wall time (fitted on the finished cells of its method and preset) would go past the
budget, counted from the start of this invocation. ``--dry-run`` lists the cells and what is done.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from worldtree.infra.cli_runner import Terminated, signals_raise, stop_report

FRAMES = (40, 80, 160)
SIZES = ((160, 90), (320, 180), (480, 270))
PRESETS = ("quick", "paper")
#: Method key -> (registered method, run-folder tag suffix, extra `wtbench run` options).
METHODS: dict[str, tuple[str, str, tuple[str, ...]]] = {
    "static": ("static", "", ()),
    "base": ("base", "", ("--set", "priors_cache=false")),
    "worldtree-d2": ("worldtree", "-depth2", ("--depth", "2", "--set", "priors_cache=false")),
    "worldtree-auto": ("worldtree", "-depthauto", ("--depth", "auto", "--set", "priors_cache=false")),
}
#: A fitted slope above this is reported as cost growing faster than the work.
STEEP = 1.15
#: Stages of the run (timing.json ``stages_s``) that are not the method's cost.
NOT_COST = ("eval", "kernel_build")


class CostError(Exception):
    """A bad option or path; the message is one line naming it and the fix."""


@dataclass(frozen=True)
class Cell:
    """One run of the sweep: a method and preset on the F-frame WxH scene."""

    frames: int
    width: int
    height: int
    method_key: str
    preset: str

    @property
    def scene(self) -> str:
        return f"nvls_f{self.frames}_{self.width}x{self.height}"

    @property
    def method(self) -> str:
        return METHODS[self.method_key][0]

    @property
    def tag(self) -> str:
        return self.preset + METHODS[self.method_key][1]

    @property
    def name(self) -> str:
        return f"{self.scene}-{self.method_key}-{self.preset}"

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def work(self) -> int:
        """Frames x pixels at the scene's own size."""
        return self.frames * self.pixels

    def run_dir(self, out: Path) -> Path:
        return out / "runs" / self.scene / self.method / self.tag

    def is_done(self, out: Path) -> bool:
        return (self.run_dir(out) / "DONE").is_file()


def parse_list(text: str, option: str, allowed: Sequence[str] | None = None) -> list[str]:
    items = [s.strip() for s in text.split(",") if s.strip()]
    if not items:
        raise CostError(f"{option} {text!r}: give a comma list, e.g. {','.join(allowed or ['40', '80'])}")
    if allowed is not None:
        bad = [s for s in items if s not in allowed]
        if bad:
            raise CostError(f"{option}: unknown {', '.join(bad)}; choose from {','.join(allowed)}")
    return items


def parse_frames(text: str) -> list[int]:
    out = []
    for s in parse_list(text, "--frames"):
        if not s.isdigit() or int(s) < 2:
            raise CostError(f"--frames: {s!r} is not a frame count of at least 2; give e.g. 40,80,160")
        out.append(int(s))
    return out


def parse_sizes(text: str) -> list[tuple[int, int]]:
    out = []
    for s in parse_list(text, "--sizes"):
        w, _, h = s.lower().partition("x")
        if not (w.isdigit() and h.isdigit()) or int(w) < 16 or int(h) < 16:
            raise CostError(f"--sizes: {s!r} is not WxH of at least 16x16; give e.g. 160x90,320x180")
        out.append((int(w), int(h)))
    return out


def list_cells(
    frames: Iterable[int], sizes: Iterable[tuple[int, int]], methods: Iterable[str], presets: Iterable[str]
) -> list[Cell]:
    """Every cell, cheapest work first (then quick before paper, methods in the order given)."""
    methods, presets = list(methods), list(presets)
    scenes = sorted({(f, w, h) for f in frames for (w, h) in sizes}, key=lambda s: (s[0] * s[1] * s[2], s))
    return [Cell(f, w, h, m, p) for (f, w, h) in scenes for p in presets for m in methods]


def train_downscale(cell: Cell) -> int:
    """The downscale the cell's preset trains at (from the method's preset config)."""
    from methods.registry import get_method

    return int(get_method(cell.method).presets[cell.preset]().downscale)


# ---------------------------------------------------------------------------------------------- fitting


def fit_slope(work: Sequence[float], cost: Sequence[float]) -> tuple[float, float] | None:
    """Least-squares fit of ``log cost = k log work + log c``: ``(k, c)``; None without two distinct works
    with a finite positive cost."""
    pts = [
        (math.log(w), math.log(c))
        for w, c in zip(work, cost, strict=True)
        if w > 0 and c > 0 and math.isfinite(c)
    ]
    xs = [x for x, _ in pts]
    if len(pts) < 2 or max(xs) - min(xs) < 1e-12:
        return None
    mx = sum(xs) / len(xs)
    my = sum(y for _, y in pts) / len(pts)
    k = sum((x - mx) * (y - my) for x, y in pts) / sum((x - mx) ** 2 for x in xs)
    return k, math.exp(my - k * mx)


def estimate_wall_s(cell: Cell, rows: Sequence[Mapping[str, Any]]) -> float:
    """Expected wall seconds of ``cell`` from the finished rows of its method and preset: the time of the
    largest finished work scaled by ``(work / that work) ** k``, ``k`` the fitted log-log slope but at least 1
    (a timing taken under changing load can fit a slope below 1 or even negative), 1 with a single finished
    work; NaN when none is finished."""
    same = [
        r
        for r in rows
        if r["method"] == cell.method_key and r["preset"] == cell.preset and r["status"] == "done"
    ]
    pts = [(float(r["work"]), _seconds(r)) for r in same]
    pts = [(w, s) for w, s in pts if math.isfinite(s) and s > 0]
    if not pts:
        return math.nan
    fit = fit_slope([w for w, _ in pts], [s for _, s in pts])
    k = max(fit[0], 1.0) if fit is not None else 1.0
    w_ref, s_ref = max(pts)
    return s_ref * (cell.work / w_ref) ** k


def _seconds(row: Mapping[str, Any]) -> float:
    v = _num(row.get("proc_wall_s"))
    return v if math.isfinite(v) else _num(row.get("wall_time_s"))


# ---------------------------------------------------------------------------------------------- reading


def _num(v: Any) -> float:
    if v is None or isinstance(v, bool) or v == "":
        return math.nan
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def _read_json(path: Path) -> dict[str, Any]:
    try:
        obj = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return obj if isinstance(obj, dict) else {}


def stage_costs(timing: Mapping[str, Any]) -> dict[str, tuple[float, float]]:
    """``{stage: (wall s, CPU s)}`` of one run: the method's own stages (``method_stats.stages_s``: priors, ba,
    sw, scaffold, photometric, tree, test_pose ...; the tree's CPU includes its parallel workers) or the run's
    ``train`` when the method reports none (static), plus the run's load, init, save_model and render."""
    stages = timing.get("stages_s") or {}
    cpu = timing.get("stages_cpu_s") or {}
    stats = timing.get("method_stats") or {}
    inner = stats.get("stages_s") if isinstance(stats, Mapping) else None
    inner_cpu = (stats.get("stages_cpu_s") if isinstance(stats, Mapping) else None) or {}
    out: dict[str, tuple[float, float]] = {}
    for k, v in stages.items():
        if k in NOT_COST or (k == "train" and inner):
            continue
        out[k] = (_num(v), _num(cpu.get(k)))
    for k, v in (inner or {}).items():
        out[k] = (_num(v), _num(inner_cpu.get(k)))
    tree = stats.get("tree") if isinstance(stats, Mapping) else None
    if isinstance(tree, Mapping) and "tree" in out:
        workers = 0.0
        for layer in tree.get("layers") or ():
            if isinstance(layer, Mapping) and layer.get("mode", "parallel") == "parallel":
                nodes = layer.get("nodes_cpu_s")
                if isinstance(nodes, Mapping):
                    workers += sum(x for x in map(_num, nodes.values()) if math.isfinite(x))
        wall, own = out["tree"]
        out["tree"] = (wall, (own if math.isfinite(own) else 0.0) + workers)
    return out


def _mean_scores(run: Path) -> dict[str, float]:
    from benchmarks.reporting.results import read_metrics_table

    table = read_metrics_table(run / "metrics.csv")
    if table is None:
        return {"mpsnr": math.nan, "psnr": math.nan}
    mean = table[table["frame"] == "mean"]
    if len(mean) != 1:
        return {"mpsnr": math.nan, "psnr": math.nan}
    return {m: _num(mean.iloc[0][m]) if m in mean.columns else math.nan for m in ("mpsnr", "psnr")}


def collect(cell: Cell, out: Path) -> dict[str, Any]:
    """One row of cost.csv for ``cell``: its run folder's figures and the sweep's record of the run."""
    from benchmarks.reporting.results import cost_metrics

    run = cell.run_dir(out)
    record = _read_json(out / "cells" / f"{cell.name}.json")
    done = (run / "DONE").is_file()
    row: dict[str, Any] = {
        "scene": cell.scene,
        "frames": cell.frames,
        "width": cell.width,
        "height": cell.height,
        "work": cell.work,
        "method": cell.method_key,
        "preset": cell.preset,
        "status": "done" if done else record.get("status", "pending"),
    }
    config = _read_json(run / "config.json").get("config") or {}
    ds = _num(config.get("downscale"))
    if not math.isfinite(ds):
        ds = _num(record.get("train_downscale"))
    row["train_downscale"] = int(ds) if math.isfinite(ds) else ""
    row["train_size"] = f"{cell.width // int(ds)}x{cell.height // int(ds)}" if math.isfinite(ds) else ""
    timing = _read_json(run / "timing.json") if done else {}
    cost = cost_metrics(timing, _read_json(run / "model" / "model.json")) if done else {}
    row["wall_time_s"] = cost.get("wall_time_s", math.nan)
    row["cpu_time_s"] = cost.get("cpu_time_s", math.nan)
    row["peak_memory_mib"] = cost.get("peak_memory_mb", math.nan)
    row["peak_rss_mib"] = _num(timing.get("peak_rss_mib"))
    row["cuda_peak_mib"] = _num(timing.get("cuda_peak_allocated_mib"))
    row["n_gaussians"] = cost.get("n_gaussians", math.nan)
    row.update(_mean_scores(run) if done else {"mpsnr": math.nan, "psnr": math.nan})
    row["sessions"] = len(timing.get("sessions_s") or []) if done else ""
    for k in (
        "proc_wall_s",
        "proc_cpu_s",
        "proc_maxrss_mib",
        "proc_tree_peak_rss_mib",
        "load_start",
        "load_end",
        "probe_ms_start",
        "probe_ms_end",
        "started",
    ):
        row[k] = record.get(k, "")
    row["device"] = timing.get("device", "")
    row["machine"] = record.get("machine", "")
    for stage, (wall, cpu) in stage_costs(timing).items():
        row[f"stage_wall_s:{stage}"] = wall
        row[f"stage_cpu_s:{stage}"] = cpu
    return row


# ---------------------------------------------------------------------------------------------- running


def tree_rss_mib(pid: int) -> float:
    """Resident memory (MiB) of process ``pid`` and all its descendants now, from /proc (Linux); NaN
    elsewhere or when ``pid`` is gone."""
    total_kib, todo, seen = 0, [pid], set()
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total_kib += int(line.split()[1])
                    break
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, ValueError):
            if p == pid:
                return math.nan
    return total_kib / 1024


class _TreeMemory:
    """Samples :func:`tree_rss_mib` of a process every ``every`` seconds in a thread; ``peak`` is the largest."""

    def __init__(self, pid: int, every: float = 0.5):
        import threading

        self.pid, self.every, self.peak = pid, every, math.nan
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.is_set():
            now = tree_rss_mib(self.pid)
            if math.isfinite(now) and not now <= self.peak:
                self.peak = now
            self._stop.wait(self.every)

    def stop(self) -> float:
        self._stop.set()
        self._thread.join()
        return self.peak


def _run_logged(cmd: list[str], log: Path) -> tuple[int, float, float, float, float]:
    """Run ``cmd`` with its output appended to ``log``: ``(exit status, wall s, CPU s, max RSS MiB, peak
    tree RSS MiB)``. CPU and max RSS come from ``wait4`` (the process and every descendant it waited for; RSS
    of the largest single one); the tree's RSS is the sum over the process and its live descendants (the
    tree's parallel workers), sampled every half second."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("a") as fh:
        fh.write("$ " + " ".join(cmd) + "\n")
        fh.flush()
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT)
        memory = _TreeMemory(proc.pid)
        try:
            _, status, usage = os.wait4(proc.pid, 0)
        except (KeyboardInterrupt, Terminated):
            proc.terminate()  # the run saves its timing ledger on SIGTERM and resumes next time
            proc.wait()
            raise
        finally:
            tree_peak = memory.stop()
        proc.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - t0
    maxrss_kib = usage.ru_maxrss if sys.platform != "darwin" else usage.ru_maxrss / 1024
    return proc.returncode, wall, usage.ru_utime + usage.ru_stime, maxrss_kib / 1024, tree_peak


def _tool(name: str) -> str:
    """The console script ``name`` beside this Python (the venv's), else on PATH."""
    here = Path(sys.executable).parent / name
    found = str(here) if here.is_file() else shutil.which(name)
    if found is None:
        raise CostError(
            f"{name}: not found beside {sys.executable} or on PATH; install the package (pip install -e .)"
        )
    return found


def ensure_scene(out: Path, frames: int, width: int, height: int, log: Path) -> Path:
    """OUT/scenes/<name> for F frames at WxH, generated and built unless already there."""
    name = Cell(frames, width, height, "static", "quick").scene
    raw = out / "scenes" / "raw" / name
    scene = out / "scenes" / name
    if not (raw / "gt" / "cameras.json").is_file():
        print(f"generating {raw} (12 cameras x {frames} steps at {width}x{height})", flush=True)
        cmd = [_tool("nvls"), "synth", str(raw), "--force", "--steps", str(frames)]
        cmd += ["--width", str(width), "--height", str(height), "--motion", "slow_fast"]
        rc, *_ = _run_logged(cmd, log)
        if rc != 0:
            raise CostError(f"nvls synth {raw} failed (exit {rc}); see {log}")
    if not (scene / "manifest.json").is_file():
        print(f"building {scene}", flush=True)
        cmd = [_tool("nvls"), "build", str(raw), "-o", str(out / "scenes"), "--name", name, "--force"]
        cmd += ["--poses", str(raw / "gt" / "poses_bounds.npy"), "--frames", str(frames)]
        rc, *_ = _run_logged(cmd, log)
        if rc != 0:
            raise CostError(f"nvls build {raw} failed (exit {rc}); see {log}")
    return scene


def run_command(cell: Cell, out: Path, device: str) -> list[str]:
    cmd = [_tool("wtbench"), "run", "--method", cell.method, "--scene", str(out / "scenes" / cell.scene)]
    cmd += ["-o", str(out / "runs"), "--preset", cell.preset, "--device", device, "--tag", cell.tag]
    return cmd + list(METHODS[cell.method_key][2])


def _round_or_none(x: float, digits: int = 2) -> float | None:
    return round(x, digits) if math.isfinite(x) else None


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else ""


PROBE_GAUSSIANS, PROBE_SIZE, PROBE_ITERS = 20_000, (320, 180), 10


def speed_probe(backend: str = "auto") -> float:
    """The machine's speed now: median ms of one rasterizer forward + backward (``benchmarks.speed.render``'s
    step: 20,000 Gaussians at 320x180, torch's thread count), NaN when it cannot run. Same work every call, so
    two cells' probes compare how fast the machine was for each."""
    import torch

    from benchmarks.speed.render import run_one

    try:
        w, h = PROBE_SIZE
        return float(run_one(backend, PROBE_GAUSSIANS, w, h, torch.get_num_threads(), PROBE_ITERS)["ms_median"])
    except Exception as e:  # a probe must never stop the sweep; the table shows the gap
        print(f"warning: speed probe failed ({type(e).__name__}: {e}); left empty", file=sys.stderr, flush=True)
        return math.nan


def run_cell(cell: Cell, out: Path, device: str, machine: str, probe: bool = True) -> dict[str, Any]:
    """Run one cell (its scene made first) and keep the record of the run in OUT/cells/<cell>.json."""
    log = out / "logs" / f"{cell.name}.log"
    ensure_scene(out, cell.frames, cell.width, cell.height, out / "logs" / f"{cell.scene}.log")
    cmd = run_command(cell, out, device)
    record: dict[str, Any] = {
        "command": " ".join(cmd),
        "machine": machine,
        "probe_ms_start": _round_or_none(speed_probe()) if probe else None,
        "load_start": _load(),
        "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "train_downscale": train_downscale(cell),
    }
    rc, wall, cpu, rss, tree_rss = _run_logged(cmd, log)
    record.update(
        load_end=_load(),
        proc_wall_s=round(wall, 2),
        proc_cpu_s=round(cpu, 2),
        proc_maxrss_mib=round(rss, 1),
        proc_tree_peak_rss_mib=round(tree_rss, 1) if math.isfinite(tree_rss) else None,
        probe_ms_end=_round_or_none(speed_probe()) if probe else None,
        status="done" if rc == 0 and cell.is_done(out) else f"failed (exit {rc})",
    )
    (out / "cells").mkdir(parents=True, exist_ok=True)
    path = out / "cells" / f"{cell.name}.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(record, indent=2) + "\n")
    tmp.replace(path)
    return record


# ---------------------------------------------------------------------------------------------- writing


def _fmt(v: Any, digits: int = 1) -> str:
    x = _num(v)
    if isinstance(v, str) and not math.isfinite(x):
        return v
    return "" if not math.isfinite(x) else f"{x:,.{digits}f}"


def write_csv(rows: Sequence[Mapping[str, Any]], path: Path) -> None:
    columns: list[str] = []
    for r in rows:
        columns += [k for k in r if k not in columns]
    stage_cols = sorted(c for c in columns if c.startswith("stage_"))
    columns = [c for c in columns if not c.startswith("stage_")] + stage_cols
    tmp = path.with_suffix(".csv.tmp")
    with tmp.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=columns, restval="")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if isinstance(v, float) and math.isnan(v) else v) for k, v in r.items()})
    tmp.replace(path)


MD_COLUMNS = (
    ("frames", "Frames", 0),
    ("size", "Size", None),
    ("method", "Method", None),
    ("preset", "Preset", None),
    ("train_size", "Trained at", None),
    ("wall_time_s", "Wall s", 1),
    ("cpu_time_s", "CPU s", 1),
    ("peak_memory_mib", "Peak MiB", 0),
    ("proc_tree_peak_rss_mib", "All procs MiB", 0),
    ("n_gaussians", "Gaussians", 0),
    ("mpsnr", "mPSNR", 2),
    ("psnr", "PSNR", 2),
    ("load", "Load start -> end", None),
    ("probe", "Probe ms start -> end", None),
    ("status", "Status", None),
)


def markdown_table(rows: Sequence[Mapping[str, Any]]) -> str:
    lines = ["| " + " | ".join(title for _, title, _ in MD_COLUMNS) + " |"]
    lines.append("|" + "|".join("---:" if d is not None else "---" for _, _, d in MD_COLUMNS) + "|")
    for r in rows:
        cells = []
        for key, _, digits in MD_COLUMNS:
            if key == "size":
                cells.append(f"{r['width']}x{r['height']}")
            elif key == "load":
                a, b = str(r.get("load_start") or ""), str(r.get("load_end") or "")
                cells.append(f"{a.split(' ')[0]} -> {b.split(' ')[0]}" if a and b else "")
            elif key == "probe":
                a, b = _num(r.get("probe_ms_start")), _num(r.get("probe_ms_end"))
                cells.append(f"{a:.1f} -> {b:.1f}" if math.isfinite(a) and math.isfinite(b) else "")
            elif digits is None:
                cells.append(str(r.get(key, "")))
            else:
                cells.append(_fmt(r.get(key), digits))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def fit_frames_pixels(
    frames: Sequence[float], pixels: Sequence[float], cost: Sequence[float]
) -> tuple[float, float] | None:
    """Least-squares fit of ``log cost = a log frames + b log pixels + log c``: ``(a, b)``; None unless both
    frames and pixels vary independently over the finite positive costs."""
    import numpy as np

    pts = [
        (math.log(f), math.log(p), math.log(c))
        for f, p, c in zip(frames, pixels, cost, strict=True)
        if f > 0 and p > 0 and c > 0 and math.isfinite(c)
    ]
    if len(pts) < 3:
        return None
    a = np.array([[f, p, 1.0] for f, p, _ in pts])
    if np.linalg.matrix_rank(a, tol=1e-9) < 3:
        return None
    sol, *_ = np.linalg.lstsq(a, np.array([c for _, _, c in pts]), rcond=None)
    return float(sol[0]), float(sol[1])


def slopes(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Fitted log-log slopes per method/preset of wall, CPU and memory and of each stage's CPU seconds:
    ``slope`` against work (frames x pixels), ``vs_frames``/``vs_pixels`` apart when both vary (else NaN),
    ``share``: a stage's part of the run's CPU seconds at the largest work (1 for the run's totals).
    ``steep``: slope > :data:`STEEP` for a total, or for a stage of at least 2 % of the run's CPU."""
    done = [r for r in rows if r["status"] == "done"]
    groups: dict[tuple[str, str], list[Mapping[str, Any]]] = {}
    for r in done:
        groups.setdefault((r["method"], r["preset"]), []).append(r)
    out = []
    for (method, preset), rs in groups.items():
        keys = ["wall_time_s", "cpu_time_s", "peak_memory_mib", "proc_tree_peak_rss_mib"]
        keys += sorted({k for r in rs for k in r if k.startswith("stage_cpu_s:")})
        largest = max(rs, key=lambda r: float(r["work"]))
        for key in keys:
            costs = [_num(r.get(key)) for r in rs]
            fit = fit_slope([float(r["work"]) for r in rs], costs)
            if fit is None:
                continue
            apart = fit_frames_pixels(
                [float(r["frames"]) for r in rs], [float(r["width"]) * float(r["height"]) for r in rs], costs
            )
            share = 1.0
            if key.startswith("stage_"):
                share = _num(largest.get(key)) / _num(largest.get("cpu_time_s"))
            out.append(
                {
                    "method": method,
                    "preset": preset,
                    "cost": key,
                    "slope": fit[0],
                    "vs_frames": apart[0] if apart else math.nan,
                    "vs_pixels": apart[1] if apart else math.nan,
                    "share": share,
                    "steep": fit[0] > STEEP and not share < 0.02,
                }
            )
    return out


def slope_text(fits: Sequence[Mapping[str, Any]]) -> str:
    if not fits:
        return "no slope yet: a method/preset needs finished cells at two amounts of work\n"
    lines = [
        f"log-log slope of cost against work = frames x pixels (1 = proportional; > {STEEP} flagged unless under "
        "2 % of the run's CPU), and apart against frames and pixels where both vary:",
        f"  {'method':<15} {'preset':<6} {'cost':<30} {'work':>5} {'frames':>6} {'pixels':>6} {'share':>6}",
    ]
    for f in fits:
        flag = "  <-- grows faster than the work" if f["steep"] else ""
        apart = " ".join(
            f"{f[k]:6.2f}" if math.isfinite(f[k]) else f"{'':>6}" for k in ("vs_frames", "vs_pixels")
        )
        lines.append(
            f"  {f['method']:<15} {f['preset']:<6} {f['cost']:<30} {f['slope']:5.2f} {apart} {f['share']:6.0%}{flag}"
        )
    return "\n".join(lines) + "\n"


def _series(rows: Sequence[Mapping[str, Any]], key: str) -> dict[str, list[tuple[float, float]]]:
    out: dict[str, list[tuple[float, float]]] = {}
    for r in rows:
        v = _num(r.get(key))
        if r["status"] == "done" and math.isfinite(v) and v > 0:
            out.setdefault(f"{r['method']} {r['preset']}", []).append((float(r["work"]), v))
    return {k: sorted(v) for k, v in out.items()}


def _reference(ax, pts: list[tuple[float, float]], top: bool = False) -> None:
    """A dashed slope-1 line from the smallest work, at the geometric mean of the costs there (``top``: at the
    largest, so that the dominant stage reads against it)."""
    lo = min(w for w, _ in pts)
    hi = max(w for w, _ in pts)
    if hi <= lo:
        return
    at = [c for w, c in pts if w == lo]
    c0 = max(at) if top else math.exp(sum(map(math.log, at)) / len(at))
    ax.plot([lo, hi], [c0, c0 * hi / lo], "k--", lw=1, label="slope 1 (cost ~ work)")


def plot_costs(rows: Sequence[Mapping[str, Any]], path: Path) -> bool:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (
        ("wall_time_s", "wall time (s)"),
        ("cpu_time_s", "CPU time (s)"),
        ("peak_memory_mib", "peak memory (MiB)"),
    )
    if not any(_series(rows, k) for k, _ in panels):
        return False
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.8))
    for ax, (key, label) in zip(axes, panels, strict=True):
        series = _series(rows, key)
        for name, pts in series.items():
            ax.plot([w for w, _ in pts], [c for _, c in pts], "o-", label=name)
        every = [p for pts in series.values() for p in pts]
        if every:
            _reference(ax, every)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("work: frames x pixels (scene size)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 5), frameon=False)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def plot_stages(rows: Sequence[Mapping[str, Any]], path: Path) -> bool:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    order = {m: i for i, m in enumerate([*METHODS, *PRESETS])}
    groups = sorted(
        {(r["method"], r["preset"]) for r in rows if r["status"] == "done"},
        key=lambda g: (order.get(g[1], 99), order.get(g[0], 99), g),
    )
    if not groups:
        return False
    cols = min(len(groups), 4)
    nrows = math.ceil(len(groups) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.6 * cols, 5.4 * nrows), squeeze=False)
    for ax, (method, preset) in zip(axes.flat, groups, strict=False):
        rs = [r for r in rows if r["method"] == method and r["preset"] == preset]
        stages = sorted({k for r in rs for k in r if k.startswith("stage_cpu_s:")})
        every = []
        for key in stages:
            pts = _series(rs, key).get(f"{method} {preset}", [])
            if pts and max(c for _, c in pts) >= 0.5:  # stages under half a second clutter the plot
                ax.plot([w for w, _ in pts], [c for _, c in pts], "o-", label=key.split(":", 1)[1])
                every += pts
        if every:
            _reference(ax, every, top=True)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(f"{method} {preset}: CPU s per stage")
        ax.set_xlabel("frames x pixels")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=3, frameon=False)
    for ax in list(axes.flat)[len(groups) :]:
        ax.set_visible(False)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def report(cells: Sequence[Cell], out: Path, plots: bool = True) -> list[dict[str, Any]]:
    """Collect every cell and write OUT/cost.csv, OUT/cost.md (and the plots); returns the rows."""
    rows = [collect(c, out) for c in cells]
    out.mkdir(parents=True, exist_ok=True)
    write_csv(rows, out / "cost.csv")
    fits = slopes(rows)
    text = markdown_table(rows) + "\n```\n" + slope_text(fits) + "```\n"
    (out / "cost.md").write_text(text)
    if plots:
        plot_costs(rows, out / "cost.png")
        plot_stages(rows, out / "cost_stages.png")
    return rows


# ---------------------------------------------------------------------------------------------- main


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "out", type=Path, help="folder of scenes/, runs/, cells/, logs/ and the cost table and plots"
    )
    ap.add_argument("--frames", default=",".join(map(str, FRAMES)))
    ap.add_argument("--sizes", default=",".join(f"{w}x{h}" for w, h in SIZES))
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--presets", default=",".join(PRESETS))
    ap.add_argument("--device", default="auto", help="auto, cpu, cuda (given to wtbench run)")
    ap.add_argument(
        "--max-minutes", type=float, default=None, help="stop before a run that would exceed this"
    )
    ap.add_argument("--dry-run", action="store_true", help="list the cells and what is done, run nothing")
    ap.add_argument("--report-only", action="store_true", help="write the table and plots from what is done")
    ap.add_argument(
        "--no-probe", dest="probe", action="store_false",
        help="skip the machine-speed probe (a rasterizer step timed before and after each run)",
    )
    args = ap.parse_args(argv)
    try:
        if args.max_minutes is not None and args.max_minutes <= 0:
            raise CostError(f"--max-minutes {args.max_minutes}: give a positive number of minutes")
        if args.out.exists() and not args.out.is_dir():
            raise CostError(f"{args.out}: is a file; give a folder for the sweep")
        cells = list_cells(
            parse_frames(args.frames),
            parse_sizes(args.sizes),
            parse_list(args.methods, "--methods", list(METHODS)),
            parse_list(args.presets, "--presets", PRESETS),
        )
        with signals_raise():  # SIGTERM too stops the cell's run through its finally blocks (its time kept)
            return _sweep(cells, args)
    except CostError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, Terminated) as e:
        line, code = stop_report(e)
        print(line, file=sys.stderr)
        return code


def _sweep(cells: list[Cell], args: argparse.Namespace) -> int:
    out: Path = args.out
    if args.dry_run:
        for c in cells:
            state = "done" if c.is_done(out) else "to run"
            ds = train_downscale(c)
            trained = f"trains at {c.width // ds}x{c.height // ds} (downscale {ds})"
            print(f"{c.name:<44} work {c.work:>11,}  {trained:<34} {state}")
        print(f"{len(cells)} cells, {sum(c.is_done(out) for c in cells)} done")
        return 0
    if args.report_only:
        rows = report(cells, out)
        print(slope_text(slopes(rows)), end="")
        return 0
    from benchmarks.speed.machine_info import describe

    machine = describe()
    print(machine, flush=True)
    start = time.perf_counter()
    rows = [collect(c, out) for c in cells]
    failed = 0
    for i, cell in enumerate(cells):
        if cell.is_done(out):
            print(f"[{i + 1}/{len(cells)}] {cell.name}: done, skipped", flush=True)
            continue
        if args.max_minutes is not None:
            est = estimate_wall_s(cell, rows)
            elapsed = time.perf_counter() - start
            if math.isfinite(est) and elapsed + est > args.max_minutes * 60:
                print(
                    f"stopping before {cell.name}: estimated {est / 60:.1f} min, {elapsed / 60:.1f} of "
                    f"{args.max_minutes:g} min used; run again (with more --max-minutes) to continue",
                    flush=True,
                )
                break
        print(f"[{i + 1}/{len(cells)}] {cell.name}: running (load {_load()})", flush=True)
        record = run_cell(cell, out, args.device, machine, probe=args.probe)
        failed += record["status"] != "done"
        print(
            f"    {record['status']}: {record['proc_wall_s']:.0f} s wall, {record['proc_cpu_s']:.0f} s CPU, "
            f"max RSS {record['proc_maxrss_mib']:.0f} MiB (all processes {record.get('proc_tree_peak_rss_mib')} MiB), "
            f"load {record['load_start']} -> {record['load_end']}",
            flush=True,
        )
        rows = report(cells, out, plots=False)
    rows = report(cells, out)
    print(slope_text(slopes(rows)), end="")
    print(f"wrote {out / 'cost.csv'}, {out / 'cost.md'}, {out / 'cost.png'}, {out / 'cost_stages.png'}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
