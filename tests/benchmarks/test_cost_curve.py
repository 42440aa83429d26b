"""benchmarks.speed.cost_curve: the slope fit, the cells, the table and plots from run folders, resuming.

The fake run folders follow real ones: timing.json with the keys `wtbench run` writes (stages_s, stages_cpu_s,
sessions_s, total_s, peak_rss_mib, method_stats with the method's own stages and the tree's layers, as in a
quick Base / WorldTree run of the cost sweep) and metrics.csv/metrics.json from the harness's own writer; one
test reads a run folder made by the real executor."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import sys

import pandas as pd
import pytest
import torch

from benchmarks.evaluation.evaluate import COLUMNS, EvalResult, write_result
from benchmarks.speed import cost_curve as cc
from worldtree.infra.atomic import atomic_write_json


def fake_run(
    out, cell: cc.Cell, cpu_s: float, *, mpsnr: float = 20.0, tree_workers_s: float = 0.0, done=True
):
    """A finished run folder of ``cell`` whose method stages add up to ``cpu_s`` CPU seconds (wall twice that)."""
    root = cell.run_dir(out)
    root.mkdir(parents=True)
    atomic_write_json(
        root / "config.json", {"method": cell.method, "preset": cell.preset, "config": {"downscale": 2}}
    )
    row = {c: math.nan for c in COLUMNS[1:]}
    row.update(psnr=mpsnr + 5, mpsnr=mpsnr)
    table = pd.DataFrame([{"frame": "v001_t000", **row}, {"frame": "mean", **row}])[list(COLUMNS)]
    write_result(
        EvalResult(table, {"protocol": {"name": "worldtree", "version": "1"}, "mean": row}),
        root / "metrics.csv",
    )
    inner = {"priors": 0.1 * cpu_s, "sw": 0.3 * cpu_s, "photometric": 0.6 * cpu_s - tree_workers_s}
    layers = []
    if tree_workers_s:
        inner["tree"] = 0.0
        layers = [
            {
                "depth": 1,
                "mode": "parallel",
                "nodes_cpu_s": {"0": tree_workers_s / 2, "1": tree_workers_s / 2},
            }
        ]
    run_stages = {"load": 0.2, "init": 1.0, "train": sum(inner.values()), "save_model": 0.1, "render": 0.3}
    stages = {**run_stages, "eval": 5.0, "kernel_build": 30.0}
    stats = {"backend": "cpu", "num_gaussians": 1000, "stages_s": {k: 2 * v for k, v in inner.items()}}
    stats["stages_cpu_s"] = dict(inner)
    if layers:
        stats["tree"] = {"layers": layers}
    timing = {
        "stages_s": {k: 2 * v for k, v in stages.items()},
        "stages_cpu_s": stages,
        "sessions_s": [2 * sum(stages.values())],
        "total_s": 2 * sum(stages.values()),
        "peak_rss_mib": 400.0,
        "cuda_peak_allocated_mib": None,
        "num_gaussians": 1000,
        "device": "cpu",
        "method_stats": stats,
    }
    atomic_write_json(root / "timing.json", timing)
    if done:
        atomic_write_json(root / "DONE", {"finished": "2026-11-26T00:00:00Z", "mean": {}})
    return root


def test_slope_fit_recovers_the_power():
    work = [576_000, 1_152_000, 2_304_000, 4_608_000]
    for k in (0.8, 1.0, 1.37):
        got = cc.fit_slope(work, [3.5 * w**k for w in work])
        assert got is not None
        assert got[0] == pytest.approx(k, abs=1e-9) and got[1] == pytest.approx(3.5, rel=1e-6)
    assert cc.fit_slope([100, 100], [1.0, 2.0]) is None  # one amount of work: no slope
    assert cc.fit_slope([100, 200], [1.0, math.nan]) is None
    # Apart: cost = 2 * frames^0.3 * pixels^1.2 over a 2 x 2 grid.
    frames, pixels = [40, 80, 40, 80], [14_400, 14_400, 57_600, 57_600]
    a, b = cc.fit_frames_pixels(
        frames, pixels, [2 * f**0.3 * p**1.2 for f, p in zip(frames, pixels, strict=True)]
    )
    assert (a, b) == (pytest.approx(0.3), pytest.approx(1.2))
    assert cc.fit_frames_pixels([40, 80, 160], [100, 100, 100], [1.0, 2.0, 4.0]) is None  # pixels do not vary


def test_cells_cheapest_first_and_named_apart():
    cells = cc.list_cells(
        [80, 40], [(320, 180), (160, 90)], ["static", "worldtree-d2", "worldtree-auto"], ["quick"]
    )
    assert len(cells) == 12
    assert [c.work for c in cells] == sorted(c.work for c in cells)
    assert (cells[0].frames, cells[0].width) == (40, 160)
    assert len({c.name for c in cells}) == len({c.run_dir(cc.Path("o")) for c in cells}) == 12
    d2, auto = cells[1], cells[2]
    assert d2.run_dir(cc.Path("o")).parts[-2:] == ("worldtree", "quick-depth2")
    assert auto.tag == "quick-depthauto"
    assert cc.run_command(d2, cc.Path("o"), "cpu")[-4:] == ["--depth", "2", "--set", "priors_cache=false"]


def test_dry_run_lists_cells_and_train_size(tmp_path, capsys):
    out = tmp_path / "o"
    fake_run(out, cc.Cell(40, 160, 90, "static", "quick"), 10.0)
    args = [
        str(out),
        "--frames",
        "40,80",
        "--sizes",
        "160x90",
        "--methods",
        "static,base",
        "--presets",
        "quick",
    ]
    assert cc.main([*args, "--dry-run"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 5 and lines[-1] == "4 cells, 1 done"
    assert "nvls_f40_160x90-static-quick" in lines[0] and lines[0].endswith("done")
    assert "trains at 80x45 (downscale 2)" in lines[0] and lines[1].endswith("to run")
    assert not (out / "scenes").exists()


@pytest.mark.parametrize(
    "args, names",
    [
        (["--frames", "40,x"], "--frames"),
        (["--sizes", "160by90"], "--sizes"),
        (["--methods", "static,nerf"], "--methods"),
        (["--presets", "slow"], "--presets"),
        (["--max-minutes", "0"], "--max-minutes"),
    ],
)
def test_bad_options_are_one_line(tmp_path, capsys, args, names):
    assert cc.main([str(tmp_path / "o"), *args, "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {names}") and err.count("\n") == 1


def test_table_csv_slopes_and_plots_from_run_folders(tmp_path, capsys):
    out = tmp_path / "o"
    cells = cc.list_cells([40, 80], [(160, 90), (320, 180)], ["base", "worldtree-d2"], ["quick"])
    for c in cells:
        # Base linear in work; WorldTree's tree workers grow as work^1.5.
        scale = c.work / cells[0].work
        fake_run(out, c, 100.0 * scale, tree_workers_s=10.0 * scale**1.5 if c.method == "worldtree" else 0.0)
    (out / "cells").mkdir()
    (out / "cells" / f"{cells[0].name}.json").write_text(
        json.dumps(
            {
                "proc_wall_s": 260.0,
                "proc_cpu_s": 150.0,
                "load_start": "3.00 2.0 1.0",
                "load_end": "4.00 3 2",
                "probe_ms_start": 11.5,
                "probe_ms_end": 16.25,
            }
        )
    )
    rows = cc.report(cells, out)
    with (out / "cost.csv").open() as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 8 and {r["status"] for r in table} == {"done"}
    first = table[0]
    assert first["method"] == "base" and first["train_size"] == "80x45" and float(first["mpsnr"]) == 20.0
    # wtbench table's counting: CPU = stages less eval/kernel_build (+ tree workers), wall from total_s.
    assert float(first["cpu_time_s"]) == pytest.approx(100.0 + 1.6)
    assert float(first["wall_time_s"]) == pytest.approx(2 * (100.0 + 1.6))
    assert float(first["proc_wall_s"]) == 260.0 and float(first["stage_cpu_s:sw"]) == pytest.approx(30.0)
    tree_row = next(r for r in rows if r["method"] == "worldtree-d2" and r["work"] == cells[-1].work)
    assert tree_row["stage_cpu_s:tree"] == pytest.approx(10.0 * 8**1.5)
    md = (out / "cost.md").read_text()
    assert md.count("\n| ") == 8 and "| 3.00 -> 4.00 | 11.5 -> 16.2 |" in md
    assert float(first["probe_ms_end"]) == 16.25
    fits = {(f["method"], f["cost"]): f for f in cc.slopes(rows)}
    assert fits[("base", "cpu_time_s")]["slope"] == pytest.approx(1.0, abs=0.01)
    assert fits[("worldtree-d2", "stage_cpu_s:tree")]["slope"] == pytest.approx(1.5, abs=1e-6)
    assert (
        fits[("worldtree-d2", "stage_cpu_s:tree")]["steep"] and not fits[("base", "stage_cpu_s:sw")]["steep"]
    )
    assert "stage_cpu_s:tree" in cc.slope_text(cc.slopes(rows)) and "grows faster" in cc.slope_text(
        cc.slopes(rows)
    )
    assert (out / "cost.png").stat().st_size > 10_000 and (out / "cost_stages.png").stat().st_size > 10_000


def test_unfinished_run_is_pending_in_the_table(tmp_path):
    out = tmp_path / "o"
    cell = cc.Cell(40, 160, 90, "base", "quick")
    fake_run(out, cell, 50.0, done=False)
    row = cc.collect(cell, out)
    assert row["status"] == "pending" and math.isnan(row["cpu_time_s"])


def test_finished_cells_are_skipped_and_the_budget_stops(tmp_path, monkeypatch, capsys):
    out = tmp_path / "o"
    cells = cc.list_cells([40, 80], [(160, 90)], ["static"], ["quick"])
    fake_run(out, cells[0], 10.0)
    (out / "cells").mkdir()
    (out / "cells" / f"{cells[0].name}.json").write_text(json.dumps({"proc_wall_s": 120.0}))
    ran, probes = [], []

    def fake_cell(cell, out_, device, machine, probe=True):
        ran.append(cell.name)
        probes.append(probe)
        fake_run(out_, cell, 20.0)
        return {
            "status": "done",
            "proc_wall_s": 1.0,
            "proc_cpu_s": 1.0,
            "proc_maxrss_mib": 1.0,
            "proc_tree_peak_rss_mib": 1.0,
            "load_start": "",
            "load_end": "",
        }

    monkeypatch.setattr(cc, "run_cell", fake_cell)
    monkeypatch.setattr(cc, "plot_costs", lambda rows, path: False)  # plots are tested above
    monkeypatch.setattr(cc, "plot_stages", lambda rows, path: False)
    monkeypatch.setattr("benchmarks.speed.machine_info.describe", lambda: "test machine")
    args = [str(out), "--frames", "40,80", "--sizes", "160x90", "--methods", "static", "--presets", "quick"]
    # The 80-frame cell is estimated at 240 s (twice the work of a 120 s cell): over a 3-minute budget.
    assert cc.main([*args, "--max-minutes", "3"]) == 0
    assert (
        ran == []
        and "stopping before nvls_f80_160x90-static-quick: estimated 4.0 min" in capsys.readouterr().out
    )
    assert cc.main([*args, "--max-minutes", "5"]) == 0
    assert ran == ["nvls_f80_160x90-static-quick"]  # the finished 40-frame cell is not run again
    assert cc.main(args) == 0 and ran == ["nvls_f80_160x90-static-quick"]
    assert probes == [True]  # the machine-speed probe is on unless --no-probe
    capsys.readouterr()
    assert cc.main([*args, "--dry-run"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "2 cells, 2 done"


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_reads_a_run_folder_made_by_wtbench_run(tmp_path, monkeypatch, write_tiny_scene):
    from benchmarks.runner.runs import RunRequest, execute
    from methods.registry import get_method

    spec = get_method("static")
    quick = spec.presets["quick"]
    monkeypatch.setitem(spec.presets, "quick", lambda: dataclasses.replace(quick(), init_num_points=200))
    out = tmp_path / "o"
    cell = cc.Cell(6, 64, 36, "static", "quick")
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        scene = write_tiny_scene(out / "scenes" / cell.scene)
        req = RunRequest(
            scene=scene, method="static", runs_dir=out / "runs", preset="quick", device="cpu",
            overrides={"steps": 3}, progress=False, tag=cell.tag,
        )  # fmt: skip
        assert execute(req).folder.root == cell.run_dir(out)
    finally:
        torch.set_num_threads(before)
    row = cc.collect(cell, out)
    # 6 frames of 64x36 are far under the quick preset's full_size_pixels: trained at full size.
    assert row["status"] == "done" and row["train_size"] == "64x36" and row["n_gaussians"] > 0
    assert row["cpu_time_s"] > 0 and row["wall_time_s"] >= row["stage_wall_s:train"] > 0
    assert {"stage_cpu_s:train", "stage_cpu_s:load", "stage_cpu_s:render"} <= set(row)
    assert not any(k.endswith(":eval") or k.endswith(":kernel_build") for k in row)
    assert math.isfinite(row["psnr"]) and math.isfinite(row["peak_memory_mib"])


def test_process_measure_counts_children(tmp_path):
    """wait4 CPU/RSS and the sampled memory of the whole process tree include a child process."""
    child = "b = bytearray(300 * 2**20); import time; time.sleep(1.5)"
    cmd = [sys.executable, "-c", f"import subprocess, sys; subprocess.run([sys.executable, '-c', {child!r}])"]
    rc, wall, cpu, maxrss, tree = cc._run_logged(cmd, tmp_path / "log.txt")
    assert rc == 0 and wall >= 1.5 and cpu > 0
    assert maxrss >= 300 and tree >= 300 + 5  # the parent's own RSS adds to the tree's
    assert (tmp_path / "log.txt").read_text().startswith("$ ")


def test_estimate_scales_the_largest_finished_cell_at_least_linearly():
    cells = cc.list_cells([40, 80, 160], [(160, 90)], ["base"], ["quick"])
    rows = [
        {"method": "base", "preset": "quick", "status": "done", "work": c.work, "proc_wall_s": s}
        for c, s in zip(cells[:2], (108.0, 53.0), strict=True)  # faster at 80 frames: load went down
    ]
    assert cc.estimate_wall_s(cells[2], rows) == pytest.approx(106.0)  # slope < 1 fitted: 1 used
    rows[1]["proc_wall_s"] = 432.0  # slope 2
    assert cc.estimate_wall_s(cells[2], rows) == pytest.approx(432.0 * 4)
    assert math.isnan(cc.estimate_wall_s(cells[2], [{**rows[0], "status": "pending"}]))


def test_speed_probe_times_the_fixed_render_step(monkeypatch):
    """The probe is the render benchmark's step at its fixed size, in ms; a failure is NaN, not a stopped sweep."""
    ms = cc.speed_probe(backend="reference")
    assert math.isfinite(ms) and ms > 0
    seen = {}

    def fake_run_one(backend, n, width, height, threads, iters):
        seen.update(n=n, size=(width, height))
        raise RuntimeError("no kernel")

    monkeypatch.setattr("benchmarks.speed.render.run_one", fake_run_one)
    assert math.isnan(cc.speed_probe()) and seen == {"n": 20_000, "size": (320, 180)}
