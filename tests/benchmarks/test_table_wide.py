"""benchmarks.reporting.tables.build_wide: per-scene cells, seed averaging, mean over the common scenes, group-by."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from benchmarks.reporting.results import collect_runs
from benchmarks.reporting.tables import build_wide
from worldtree.infra.errors import UserError


def _fixture():
    path = Path(__file__).with_name("runs_fixture.py")
    spec = importlib.util.spec_from_file_location("wt_tests_runs_fixture_wide", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


rf = _fixture()

# (method, config extras, scene, tag, seed); worldtree -sac has no run on scene C.
RUNS = [
    ("static", {}, "A", "quick", 0),
    ("static", {}, "B", "quick", 0),
    ("static", {}, "C", "quick", 0),
    ("worldtree", {}, "A", "quick", 0),
    ("worldtree", {}, "A", "quick-seed1", 1),
    ("worldtree", {}, "B", "quick", 0),
    ("worldtree", {}, "C", "quick", 0),
    ("worldtree", {"ablate": ["sac"]}, "A", "quick-sac", 0),
    ("worldtree", {"ablate": ["sac"]}, "B", "quick-sac", 0),
]


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    rng = np.random.default_rng(7)
    truth = []
    for method, cfg, scene, tag, seed in RUNS:
        psnr = float(rng.uniform(15, 30))
        lpips = float(rng.uniform(0.05, 0.3))
        if method == "static" and scene == "B":
            lpips = math.nan  # one missing value: static's lpips mean must be empty
        train = float(rng.uniform(5, 50))
        rf.write_run(
            root,
            scene,
            method,
            tag,
            {"psnr": psnr, "lpips": lpips},
            seed=seed,
            config=cfg,
            train_s=train,
            other_stages_s=0.0,
        )
        label = "quick -sac" if cfg else "quick"
        truth.append(
            {
                "method": method,
                "configuration": label,
                "scene": scene,
                "psnr": psnr,
                "lpips": lpips,
                "t": train,
            }
        )
    return root, pd.DataFrame(truth)


def test_cells_and_means_match_pandas(written):
    root, truth = written
    table = build_wide(collect_runs([root]).long)
    assert table.scenes == ("A", "B", "C")
    assert table.mean_scenes == ("A", "B")  # C lacks a worldtree -sac run
    assert "psnr:mean(A, B)" in table.frame.columns and "lpips:mean(A, B)" in table.frame.columns
    assert any("scene C has no run for method=worldtree / configuration=quick -sac" in n for n in table.notes)
    assert any("average several runs" in n for n in table.notes)  # worldtree quick on A: two seeds
    assert any("n_tree_nodes" in n and "left out" in n for n in table.notes)
    assert "n_tree_nodes:A" not in table.frame.columns

    # Independent computation: average seeds per (row, scene), then the plain mean over A and B.
    cells = truth.groupby(["method", "configuration", "scene"])[["psnr", "lpips", "t"]].mean(
        numeric_only=True
    )
    frame = table.frame.set_index(["method", "configuration"])
    assert list(frame.index) == [("static", "quick"), ("worldtree", "quick"), ("worldtree", "quick -sac")]
    for (method, conf, scene), row in cells.iterrows():
        got = frame.loc[(method, conf)]
        assert got[f"psnr:{scene}"] == pytest.approx(row["psnr"])
        assert got[f"wall_time_s:{scene}"] == pytest.approx(row["t"])
        if math.isnan(row["lpips"]):
            assert math.isnan(got[f"lpips:{scene}"])
        else:
            assert got[f"lpips:{scene}"] == pytest.approx(row["lpips"])
    for (method, conf), got in frame.iterrows():
        sub = cells.loc[(method, conf)].loc[["A", "B"]]
        assert got["psnr:mean(A, B)"] == pytest.approx(sub["psnr"].mean())
        if sub["lpips"].isna().any():
            assert math.isnan(got["lpips:mean(A, B)"])
        else:
            assert got["lpips:mean(A, B)"] == pytest.approx(sub["lpips"].mean())
    assert math.isnan(frame.loc[("worldtree", "quick -sac"), "psnr:C"])
    assert math.isnan(frame.loc[("static", "quick"), "lpips:mean(A, B)"])


def test_group_by_method_and_mean_only(written):
    root, truth = written
    table = build_wide(collect_runs([root]).long, group_by=("method",), metrics=("psnr",), mean_only=True)
    assert list(table.frame.columns) == ["method", "psnr:mean(A, B, C)"]
    # Per scene: mean over every run of the method there (seeds and configurations); then over A, B, C.
    per_scene = truth.groupby(["method", "scene"])["psnr"].mean()
    for _, row in table.frame.iterrows():
        assert row["psnr:mean(A, B, C)"] == pytest.approx(per_scene.loc[row["method"]].mean())


def test_no_common_scene_and_bad_options(tmp_path):
    rf.write_run(tmp_path, "A", "static", "quick", {"psnr": 20.0})
    rf.write_run(tmp_path, "B", "base", "quick", {"psnr": 21.0})
    long = collect_runs([tmp_path]).long
    table = build_wide(long, metrics=("psnr",))
    assert table.mean_scenes == () and "psnr:mean(none)" in table.frame.columns
    assert table.frame["psnr:mean(none)"].isna().all()
    assert any("none, so they are empty" in n for n in table.notes)
    with pytest.raises(UserError, match="--group-by"):
        build_wide(long, group_by=("scene",))
    with pytest.raises(UserError, match="--group-by"):
        build_wide(long, group_by=())
    with pytest.raises(UserError, match="no run has n_tree_nodes"):
        build_wide(long[long["metric"] == "psnr"], metrics=("n_tree_nodes",))
