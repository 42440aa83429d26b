"""A scene without test views (your own video, `nvls import CLIP`): `wtbench run` trains and saves the model,
records "no ground truth" instead of scores, `wtbench table` lists the run without scores and says so, and the
training-view PSNR script scores the fit."""

from __future__ import annotations

import json
import math
import shutil

from benchmarks.reporting.results import collect_runs
from benchmarks.runner.runs import NO_GROUND_TRUTH, RunRequest, execute


def _without_test_views(scene):
    doc = json.loads((scene / "cameras.json").read_text())
    doc["test_frames"] = []
    (scene / "cameras.json").write_text(json.dumps(doc))
    for sub in ("gt_images", "masks"):
        shutil.rmtree(scene / sub, ignore_errors=True)
    return scene


def test_run_table_and_training_psnr_without_test_views(tmp_path, write_tiny_scene):
    scene = _without_test_views(write_tiny_scene(tmp_path / "own", frames=6))
    res = execute(
        RunRequest(
            method="static", scene=scene, runs_dir=tmp_path / "runs", preset="quick", device="cpu",
            overrides={"steps": 6, "downscale": 1}, sets=["init_num_points=200"], progress=False,
        )
    )  # fmt: skip
    run = res.folder.root
    assert res.mean == {} and (run / "DONE").is_file() and (run / "model").is_dir()
    assert not (run / "metrics.csv").exists()
    record = json.loads((run / "metrics.json").read_text())
    assert record["ground_truth"] is False and record["protocol"]["name"] == NO_GROUND_TRUTH

    found = collect_runs([tmp_path / "runs"])
    assert any("no ground truth for 1 run(s)" in n for n in found.notes), found.notes
    psnr = found.long[found.long["metric"] == "psnr"]
    assert len(psnr) == 1 and math.isnan(psnr["value"].iloc[0])
    assert set(found.long["protocol"]) == {NO_GROUND_TRUTH}

    from benchmarks.speed.train_psnr import training_psnr

    scores = training_psnr(run, every=5)
    assert sorted(scores) == [0, 5] and all(math.isfinite(v) and v > 5 for v in scores.values())
