"""benchmarks.reporting.results: finished runs -> long table, configuration labels, cost metrics, skipped runs."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from benchmarks.reporting.results import (
    LONG_COLUMNS,
    METRICS,
    collect_runs,
    cost_metrics,
    describe_configuration,
    select,
)
from worldtree.infra.errors import UserError


def _fixture():
    path = Path(__file__).with_name("runs_fixture.py")
    spec = importlib.util.spec_from_file_location("wt_tests_runs_fixture_collect", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


rf = _fixture()

FULL = {
    "psnr": 24.5,
    "ssim": 0.81,
    "lpips": 0.1,
    "avge": 0.05,
    "mpsnr": 18.25,
    "mssim": 0.66,
    "mlpips": 0.12,
    "mavge": 0.09,
}


def test_long_table_values_and_skips(tmp_path):
    rf.write_run(tmp_path, "Balloon1", "static", "quick", FULL, train_s=12.0, other_stages_s=2.0, eval_s=7.0)
    rf.write_run(
        tmp_path,
        "Jumping",
        "worldtree",
        "quick",
        {"psnr": 20.0, "mpsnr": 15.0},
        config={"ablate": ["sw", "ba"], "depth": 3},
        method_stats={"num_gaussians": 2000, "num_scaffold_nodes": 64, "num_tree_nodes": 7},
        cuda_peak_mib=1234.0,
    )
    rf.write_run(tmp_path, "Jumping", "static", "quick", FULL, done=False)  # unfinished
    queued = tmp_path / "Truck" / "static" / "quick-seed1"  # a sweep's job not started yet: job.json only
    queued.mkdir(parents=True)
    (queued / "job.json").write_text('{"jobs": [{"executor": "slurm", "job_id": "7", "state": "submitted"}]}')
    broken = rf.write_run(tmp_path, "Truck", "static", "quick", FULL)
    broken.metrics_csv.write_text("frame,psnr\nv001_t000,3\n")  # no mean row

    got = collect_runs([tmp_path])
    long = got.long
    assert list(long.columns) == list(LONG_COLUMNS)
    staged = long["metric"].str.startswith("stage_s:")
    assert (~staged).sum() == 2 * len(METRICS)  # two readable finished runs, every metric listed once each
    # ... and every stage of their timing.json (load, init, train, save_model, render, eval).
    assert staged.sum() == 2 * 6 and set(long.loc[staged, "metric"]) >= {"stage_s:train", "stage_s:eval"}
    assert any(
        "2 unfinished run" in n and "Jumping/static/quick" in n and "Truck/static/quick-seed1" in n
        for n in got.notes
    )
    assert any("Truck" in n and "metrics.csv" in n for n in got.notes)

    a = long[(long["scene"] == "Balloon1")].set_index("metric")["value"]
    for k, v in FULL.items():
        assert a[k] == pytest.approx(v)
    # Independent: every stage but eval, train counted over all sessions.
    assert a["wall_time_s"] == pytest.approx(12.0 + 2.0)
    assert a["peak_memory_mb"] == pytest.approx(500.0)
    assert a["n_gaussians"] == 1000
    assert math.isnan(a["n_scaffold_nodes"]) and math.isnan(a["n_tree_nodes"])

    b = long[(long["scene"] == "Jumping")]
    assert set(b["method"]) == {"worldtree"} and set(b["configuration"]) == {"quick -ba -sw depth=3"}
    bv = b.set_index("metric")["value"]
    assert bv["psnr"] == 20.0 and math.isnan(bv["lpips"]) and math.isnan(bv["mavge"])
    assert bv["peak_memory_mb"] == 1234.0  # CUDA peak preferred over the process RSS
    assert (bv["n_gaussians"], bv["n_scaffold_nodes"], bv["n_tree_nodes"]) == (2000, 64, 7)
    assert set(long["protocol"]) == {"worldtree"}
    # The same root twice counts its runs once; a hidden (temporary) folder is not a run.
    rf.write_run(tmp_path, "Jumping", "static", ".quick.tmp", FULL)
    assert len(collect_runs([tmp_path, tmp_path / "."]).long) == 2 * (len(METRICS) + 6)


def test_configuration_label_rules():
    assert describe_configuration({}) == "default"
    assert describe_configuration({"preset": "paper"}) == "paper"
    rec = {"preset": "quick", "overrides": {"steps": 200, "seed": 3, "downscale": 1}}
    assert describe_configuration(rec) == "quick downscale=1 steps=200"  # seed left out, keys sorted
    # A registered method labels its own declared options with their tags, in its order.
    rec = {"method": "worldtree", "preset": "quick",
           "config": {"tree": {"depth": 4, "chain_length": 2, "split": "flow"}, "sequential": True}}  # fmt: skip
    assert describe_configuration(rec) == "quick depth=4 chain=2 split=flow seq"
    rec = {"method": "worldtree", "preset": "paper", "ablate": "sac,tpt", "config": {"ablate": ["ignored"]}}
    assert describe_configuration(rec) == "paper -tpt -sac"  # top level first; the method's ablation order
    rec = {"method": "worldtree", "config": {"ablate": ["zz", "-sw", "ba"], "depth": None}}
    assert describe_configuration(rec) == "-ba -sw -zz"
    # The record's own labels win (a run records its method's vocabulary; no registry needed to read it).
    rec = {"method": "elsewhere", "labels": {"options": [["lag", "L"], ["fast", "f"]], "ablations": ["z", "a"]},
           "config": {"ablate": ["a", "z"], "lag": 3, "fast": True}}  # fmt: skip
    assert describe_configuration(rec) == "-z -a L=3 f"
    # A method unknown here: its given options as key=value, ablations alphabetically.
    rec = {"method": "elsewhere", "options": {"lag": 2, "ablate": ["b", "a"]}, "config": {"ablate": ["b", "a"], "lag": 2}}
    assert describe_configuration(rec) == "-a -b lag=2"
    assert describe_configuration({"config": "not a dict", "overrides": None}) == "default"
    rec = {"preset": "quick", "sets": ["z.b=2", "a.c=1"], "imported_priors": {"masks": "/data/sam2/masks"}}
    assert describe_configuration(rec) == "quick a.c=1 z.b=2 masks=masks"  # sets sorted, then priors


def test_cost_metrics_fallbacks():
    # Only total_s: taken as the wall time; no memory, sizes from model.json.
    got = cost_metrics({"total_s": 9.5}, {"num_gaussians": 77})
    assert got["wall_time_s"] == 9.5 and math.isnan(got["peak_memory_mb"]) and got["n_gaussians"] == 77
    # A resumed run: this session trained 3 s, all sessions 8 s.
    t = {"stages_s": {"train": 3.0, "render": 1.0, "eval": 4.0}, "train": {"wall_s_all_sessions": 8.0}}
    assert cost_metrics(t, None)["wall_time_s"] == pytest.approx(9.0)
    # The C++ rasterizer's one-time build is not the method's time.
    t["stages_s"]["kernel_build"] = 50.0
    assert cost_metrics(t, None)["wall_time_s"] == pytest.approx(9.0)
    assert all(math.isnan(v) for v in cost_metrics(None, None).values())


def test_empty_and_missing_runs_dir(tmp_path):
    with pytest.raises(UserError, match="no finished run"):
        collect_runs([tmp_path])
    rf.write_run(tmp_path, "S", "static", "quick", FULL, done=False)
    with pytest.raises(UserError, match="no finished run"):
        collect_runs([tmp_path])
    with pytest.raises(UserError, match="no such folder"):
        collect_runs([tmp_path / "nope"])


def test_select_protocols_and_metrics(tmp_path):
    rf.write_run(tmp_path, "A", "static", "quick", FULL, protocol="worldtree")
    rf.write_run(tmp_path, "A", "static", "paper", FULL, protocol="dycheck")
    long = collect_runs([tmp_path]).long
    with pytest.raises(UserError, match="--protocol"):
        select(long)
    with pytest.raises(UserError, match="--protocol nope"):
        select(long, "nope")
    one = select(long, "dycheck", ["psnr", "wall_time_s"])
    assert set(one["tag"]) == {"paper"} and sorted(one["metric"]) == ["psnr", "wall_time_s"]
    with pytest.raises(UserError, match="--metrics"):
        select(long, "dycheck", ["bogus"])


def test_real_harness_table_is_read(tmp_path):
    """A metrics.csv written by the harness from real images (LPIPS off) gives back its own mean row."""
    from benchmarks.evaluation.evaluate import evaluate_arrays, write_result

    folder = rf.write_run(tmp_path, "S", "static", "quick", FULL)
    rng = np.random.default_rng(0)
    gts = [rng.integers(0, 256, (40, 48, 3), dtype=np.uint8) for _ in range(3)]
    preds = [np.clip(g.astype(int) + rng.integers(-20, 21, g.shape), 0, 255).astype(np.uint8) for g in gts]
    masks = [np.ones((40, 48), bool) for _ in gts]
    res = evaluate_arrays(preds, gts, masks, lpips_weights=False, device="cpu")
    write_result(res, folder.metrics_csv)
    want = pd.read_csv(folder.metrics_csv).iloc[-1]
    got = collect_runs([tmp_path]).long.set_index("metric")["value"]
    for k in ("psnr", "ssim", "mpsnr", "mssim"):
        assert got[k] == pytest.approx(float(want[k]), rel=1e-9)
    assert math.isnan(got["lpips"]) and math.isnan(got["mavge"])


def test_cpu_time_counts_the_tree_workers_and_leaves_out_scoring():
    # The run's process: 30 s of fit + 2 s render; eval and the kernel build are not the method's cost.
    t = {
        "stages_cpu_s": {"train": 30.0, "render": 2.0, "eval": 7.0, "kernel_build": 40.0},
        "method_stats": {"tree": {"layers": [{"nodes_cpu_s": {"2": 5.0, "3": 6.0}}, {"nodes_cpu_s": {"4": 1.5}}]}},
    }
    assert cost_metrics(t, None)["cpu_time_s"] == pytest.approx(30.0 + 2.0 + 5.0 + 6.0 + 1.5)
    # A damaged entry counts as nothing rather than poisoning the sum.
    t["method_stats"]["tree"]["layers"].append({"nodes_cpu_s": {"5": "nan?"}})
    assert cost_metrics(t, None)["cpu_time_s"] == pytest.approx(44.5)
    # A layer that ran in the run's own process (one node: in-process; or --sequential) is in its stages_cpu_s
    # already (seen on the demo: a one-node layer was counted twice before).
    t["method_stats"]["tree"]["layers"].append({"mode": "in-process", "nodes_cpu_s": {"13": 25.0}})
    t["method_stats"]["tree"]["layers"].append({"mode": "sequential", "nodes_cpu_s": {"14": 9.0}})
    assert cost_metrics(t, None)["cpu_time_s"] == pytest.approx(44.5)
    t["method_stats"]["tree"]["layers"].append({"mode": "parallel", "nodes_cpu_s": {"15": 0.5}})
    assert cost_metrics(t, None)["cpu_time_s"] == pytest.approx(45.0)
    # No CPU record (an older run folder): empty, not zero.
    assert math.isnan(cost_metrics({"total_s": 3.0}, None)["cpu_time_s"])
