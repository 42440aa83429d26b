"""Hand-made finished run folders for the table/plot tests.

Paths come from :class:`benchmarks.runner.runs.RunFolder` and the metrics files from the harness's own writer
(:func:`benchmarks.evaluation.evaluate.write_result`), so the fixtures follow the real format; config.json and
timing.json carry the keys that :func:`benchmarks.runner.runs.execute` writes (docs/running.md).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pandas as pd

from benchmarks.evaluation.evaluate import COLUMNS, EvalResult, write_result
from benchmarks.runner.runs import RunFolder
from worldtree.infra.atomic import atomic_write_json, atomic_write_text


def write_run(
    runs_dir: Path,
    scene: str,
    method: str,
    tag: str,
    means: dict[str, float],
    *,
    preset: str = "quick",
    overrides: dict[str, int] | None = None,
    seed: int = 0,
    config: dict[str, Any] | None = None,
    train_s: float = 10.0,
    other_stages_s: float = 1.0,
    eval_s: float = 5.0,
    peak_rss_mib: float = 500.0,
    cuda_peak_mib: float | None = None,
    method_stats: dict[str, Any] | None = None,
    protocol: str = "worldtree",
    done: bool = True,
    scene_dir: Path | None = None,
    train_cpu_s: float | None = None,
) -> RunFolder:
    """One run folder ``runs_dir/scene/method/tag``; ``means`` fills the mean row (missing columns empty).

    timing.json: stages load/init/save_model/render of ``other_stages_s / 4`` each, train ``train_s``
    (also ``train.wall_s_all_sessions``), eval ``eval_s``. ``scene_dir``: the scene folder config.json names
    (default ``/data/<scene>``, which need not exist). ``train_cpu_s``: also ``stages_cpu_s`` with train
    ``train_cpu_s``, load 0.5 and eval 2.0 (None: no CPU seconds recorded, as older runs).
    """
    folder = RunFolder(runs_dir / scene / method / tag)
    folder.root.mkdir(parents=True, exist_ok=True)
    record = {
        "method": method,
        "preset": preset,
        "overrides": dict(overrides or {}),
        "config": {"seed": seed, "steps": 30, **(config or {})},
        "seed": seed,
        "scene": str(scene_dir if scene_dir is not None else Path("/data") / scene),
        "device": "cpu",
        "version": "0.1.0",
    }
    atomic_write_json(folder.config_json, record)
    atomic_write_text(folder.command_txt, f"wtbench run --method {method} --scene /data/{scene}\n")
    row = {c: float(means.get(c, math.nan)) for c in COLUMNS[1:]}
    table = pd.DataFrame([{"frame": "v001_t000", **row}, {"frame": "mean", **row}])[list(COLUMNS)]
    res = EvalResult(table, {"protocol": {"name": protocol, "version": "1"}, "mean": row, "warnings": []})
    write_result(res, folder.metrics_csv)
    quarter = other_stages_s / 4
    stats = {"backend": "cpu", **(method_stats or {"num_gaussians": 1000})}
    timing = {
        "stages_s": {
            "load": quarter,
            "init": quarter,
            "train": train_s,
            "save_model": quarter,
            "render": quarter,
            "eval": eval_s,
        },
        "total_s": train_s + other_stages_s + eval_s,
        "train": {"steps": 30, "wall_s_all_sessions": train_s, "wall_s_this_session": train_s},
        "peak_rss_mib": peak_rss_mib,
        "cuda_peak_allocated_mib": cuda_peak_mib,
        "num_gaussians": stats.get("num_gaussians"),
        "backend": "cpu",
        "device": "cpu",
        "method_stats": stats,
    }
    if train_cpu_s is not None:
        timing["stages_cpu_s"] = {"load": 0.5, "train": train_cpu_s, "eval": 2.0}
    atomic_write_json(folder.timing_json, timing)
    if done:
        atomic_write_json(folder.done, {"finished": "2026-01-01T00:00:00Z", "mean": {}})
    return folder
