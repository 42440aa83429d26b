"""What the report shows of each run folder: its state, its evaluation record, its per-frame scores and where
its scene's ground truth is.

Every run folder is listed, finished or not, with the state the sweep's bookkeeping gives it
(:func:`benchmarks.runner.sweep_executors.run_states`, as `wtbench sweep --status` shows it; runs made by
`wtbench run` alone have no job record and are judged by ``DONE`` and their lock):

- ``done``: ``DONE`` present and read into the tables;
- ``damaged``: ``DONE`` present but the tables could not read it (the collection's note says why);
- ``running``: a live process holds the run folder's lock (:mod:`worldtree.infra.folder_lock`), or its job runs;
- ``queued``: its sweep job waits (Slurm);
- ``failed``: its last sweep job failed or vanished (the error and the job's log are named);
- ``unfinished``: stopped outside a job: interrupted, failed under `wtbench run`, or not started yet.

Failures that a sweep recorded in its report (``RUNS_DIR/sweep-<grid>.json``) are listed beside them.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from benchmarks.reporting.results import (
    HARNESS_METRICS,
    describe_configuration,
    find_run_folders,
    read_json,
    read_metrics_table,
    unusable_value,
)

STATES = ("done", "running", "queued", "failed", "unfinished", "damaged")


def read_frame_scores(csv: Path) -> pd.DataFrame | None:
    """Per-frame rows of a run's ``metrics.csv`` (the ``mean`` row dropped): index the frame names, columns
    the :data:`benchmarks.reporting.results.HARNESS_METRICS` present, NaN where empty. None when unreadable."""
    table = read_metrics_table(csv)
    if table is None:
        return None
    table = table[table["frame"] != "mean"].set_index("frame")
    cols = [m for m in HARNESS_METRICS if m in table.columns]
    table = table[cols].apply(pd.to_numeric, errors="coerce")
    # As in the tables (benchmarks.reporting.results.unusable_value): an impossible value is a missing one.
    for m in cols:
        table[m] = table[m].mask(table[m].map(lambda v, m=m: unusable_value(m, float(v))))
    return table


@dataclass
class RunEntry:
    """One run folder as the report lists it."""

    folder: Path
    rel: str
    """``scene/method/tag`` under its RUNS_DIR."""
    scene: str
    method: str
    tag: str
    state: str
    """One of :data:`STATES`."""
    detail: str = ""
    configuration: str = ""
    seed: int | None = None
    record: dict[str, Any] = field(default_factory=dict)
    """The run's ``metrics.json`` (the evaluation record), empty when absent."""
    scene_dir: Path | None = None
    """The scene folder named by ``config.json``, when it exists here."""
    frames: pd.DataFrame | None = None
    """Per-frame scores (:func:`read_frame_scores`)."""
    video: Path | None = None
    """``test_view.mp4`` (written by ``wtbench video``) when present."""

    @property
    def protocol(self) -> str:
        """``name vversion`` of the evaluation protocol, or ``unknown``."""
        p = self.record.get("protocol")
        if not isinstance(p, dict) or not p.get("name"):
            return "unknown"
        return f"{p['name']} v{p['version']}" if p.get("version") else str(p["name"])

    @property
    def checksums(self) -> dict[str, str]:
        """sha256 of the scored renders, ground truth and masks, as the evaluation record holds them."""
        inputs = self.record.get("inputs")
        if not isinstance(inputs, dict):
            return {}
        names = {"pred_sha256": "renders", "gt_sha256": "ground truth", "mask_sha256": "masks"}
        return {label: str(inputs[k]) for k, label in names.items() if inputs.get(k)}

    def provenance(self, digits: int = 64) -> str:
        """One line per fact of the run's record (protocol, checksums cut to ``digits`` hex digits, tool
        version, time), for hover text."""
        lines = [self.rel, f"protocol: {self.protocol}"]
        lines += [f"{k} sha256: {v[:digits]}" for k, v in self.checksums.items()]
        for key, label in (("tool_version", "tool version"), ("timestamp", "scored")):
            if self.record.get(key):
                lines.append(f"{label}: {self.record[key]}")
        return "\n".join(lines)


def _scene_dir(config: dict[str, Any] | None) -> Path | None:
    scene = (config or {}).get("scene")
    if not scene:
        return None
    path = Path(str(scene))
    return path if (path / "cameras.json").is_file() else None


#: Checkpoint file names (worldtree.checkpoint's ``ckpt_<step>.pt``), matched here so that listing a run's
#: state does not import torch.
_CKPT = re.compile(r"^ckpt_(\d+)\.pt$")


def _unfinished_detail(folder: Path) -> str:
    ckpt_dir = folder / "checkpoints"
    steps = (
        [int(m.group(1)) for p in ckpt_dir.iterdir() if (m := _CKPT.match(p.name))]
        if ckpt_dir.is_dir()
        else []
    )
    if steps:
        return f"no DONE; newest checkpoint at step {max(steps)} (re-run to resume)"
    return "no DONE and no checkpoint: failed early, interrupted, or not started yet"


def gather_runs(runs_dirs: Sequence[str | Path], finished: set[str]) -> list[RunEntry]:
    """Every run folder under ``runs_dirs`` with its state (module doc). ``finished``: the ``run`` values of
    the collection's long table (the runs the tables read)."""
    from benchmarks.runner.sweep_executors import run_states

    entries: list[RunEntry] = []
    seen: set[Path] = set()
    for d in map(Path, runs_dirs):
        states = {s.run: s for s in run_states(d)}
        # A queued job's folder may hold only its job record: listed too.
        folders = sorted(set(find_run_folders(d)) | {d / rel for rel in states})
        for run in folders:
            if run.resolve() in seen:
                continue
            seen.add(run.resolve())
            config = read_json(run / "config.json")
            st = states.get(str(run.relative_to(d)))
            state = st.state if st is not None else "unfinished"
            job = f"job {st.job_id}" if st is not None and st.job_id else ""
            detail = "; ".join(x for x in (job, st.detail if st is not None else "") if x)
            if state == "done" and str(run) not in finished:
                state, detail = "damaged", "DONE present but config.json or metrics.csv unreadable"
            elif state == "done":
                detail = job
            elif state == "unfinished":
                detail = "; ".join(x for x in (job, _unfinished_detail(run)) if x)
            seed = (config or {}).get("seed")
            video = run / "test_view.mp4"
            entries.append(
                RunEntry(
                    folder=run,
                    rel=str(run.relative_to(d)),
                    scene=run.parent.parent.name,
                    method=str((config or {}).get("method") or run.parent.name),
                    tag=run.name,
                    state=state,
                    detail=detail,
                    configuration=describe_configuration(config) if config else "",
                    seed=seed if isinstance(seed, int) and not isinstance(seed, bool) else None,
                    record=read_json(run / "metrics.json") or {},
                    scene_dir=_scene_dir(config),
                    frames=read_frame_scores(run / "metrics.csv") if state == "done" else None,
                    video=video if video.is_file() else None,
                )
            )
    return entries


@dataclass(frozen=True)
class SweepFailure:
    """A run a sweep reported as failed."""

    report: str
    scene: str
    label: str
    error: str


def sweep_failures(runs_dirs: Sequence[str | Path]) -> list[SweepFailure]:
    """Failed runs named by the sweep reports ``RUNS_DIR/sweep-*.json`` (unreadable reports are ignored)."""
    out = []
    for d in map(Path, runs_dirs):
        for path in sorted(d.glob("sweep-*.json")):
            report = read_json(path) or {}
            for r in report.get("runs") or []:
                if isinstance(r, dict) and r.get("status") == "failed":
                    out.append(
                        SweepFailure(
                            path.name,
                            str(r.get("scene", "")),
                            str(r.get("label", "")),
                            str(r.get("error") or "no message"),
                        )  # fmt: skip
                    )
    return out


def frame_times(scene_dir: Path | None, names: Sequence[str]) -> list[float]:
    """Time of each test frame ``names`` from the scene's ``cameras.json`` (matched by file stem), else its
    position in ``names``."""
    times: dict[str, float] = {}
    meta = read_json(scene_dir / "cameras.json") if scene_dir is not None else None
    for fr in (meta or {}).get("test_frames") or []:
        try:
            times[Path(fr["file"]).stem] = float(fr["time"])
        except (KeyError, TypeError, ValueError):
            continue
    return [times.get(n, float(i)) for i, n in enumerate(names)]


def test_frame_files(scene_dir: Path) -> dict[str, tuple[Path, Path | None]]:
    """Test frame name -> (ground-truth image, mask or None) of a scene folder (``cameras.json``)."""
    meta = read_json(scene_dir / "cameras.json") or {}
    out = {}
    for fr in meta.get("test_frames") or []:
        if isinstance(fr, dict) and fr.get("file"):
            mask = scene_dir / fr["mask"] if fr.get("mask") else None
            out[Path(fr["file"]).stem] = (scene_dir / fr["file"], mask)
    return out
