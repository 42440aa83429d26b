"""`wtbench table`/`plot` on a run folder made by the real `wtbench run` code (3 steps of the static baseline
on the tiny analytic scene), so that the reader cannot drift from the writer."""

from __future__ import annotations

import dataclasses
import json
import math

import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

from benchmarks.cli import app
from benchmarks.reporting.results import HARNESS_METRICS, collect_runs
from benchmarks.runner.runs import RunRequest, execute
from methods.registry import get_method


@pytest.fixture
def real_run(tmp_path, monkeypatch, write_tiny_scene):
    spec = get_method("static")
    quick = spec.presets["quick"]
    monkeypatch.setitem(spec.presets, "quick", lambda: dataclasses.replace(quick(), init_num_points=200))
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        scene = write_tiny_scene(tmp_path / "scenes" / "tiny")
        req = RunRequest(
            scene=scene,
            method="static",
            runs_dir=tmp_path / "runs",
            preset="quick",
            device="cpu",
            overrides={"steps": 3, "downscale": 1},
            progress=False,
        )
        result = execute(req)
    finally:
        torch.set_num_threads(before)
    return tmp_path / "runs", result.folder


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_real_run_folder_reads_back(real_run, tmp_path):
    runs, folder = real_run
    got = collect_runs([runs])
    assert got.notes == []
    long = got.long.set_index("metric")
    assert set(long["method"]) == {"static"} and set(long["scene"]) == {"tiny"}
    assert set(long["configuration"]) == {"quick downscale=1 steps=3"}
    assert set(long["protocol"]) == {json.loads(folder.metrics_json.read_text())["protocol"]["name"]}
    mean = pd.read_csv(folder.metrics_csv).iloc[-1]
    for m in HARNESS_METRICS:
        want = float(mean[m])
        assert (math.isnan(want) and math.isnan(long.loc[m, "value"])) or long.loc[
            m, "value"
        ] == pytest.approx(want)
    timing = json.loads(folder.timing_json.read_text())
    stages = dict(timing["stages_s"])
    # One session: the run's wall time less scoring and the one-time kernel compile, which covers every stage.
    assert len(timing["sessions_s"]) == 1 and timing["total_s"] == pytest.approx(timing["sessions_s"][0])
    want = timing["total_s"] - stages.pop("eval") - stages.pop("kernel_build", 0.0)
    assert long.loc["wall_time_s", "value"] == pytest.approx(want)
    assert want >= sum(stages.values()) - 1e-6
    for stage, secs in timing["stages_s"].items():  # the long table carries every stage's time
        assert long.loc[f"stage_s:{stage}", "value"] == pytest.approx(secs)
    assert long.loc["peak_memory_mb", "value"] == pytest.approx(timing["peak_rss_mib"])
    assert long.loc["n_gaussians", "value"] == timing["num_gaussians"]

    out = tmp_path / "table.csv"
    res = CliRunner().invoke(app, ["table", str(runs), "-o", str(out)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    wide = pd.read_csv(out)
    assert wide.loc[0, "psnr:mean(tiny)"] == pytest.approx(float(mean["psnr"]))
    res = CliRunner().invoke(app, ["plot", str(runs), "-o", str(tmp_path / "p.png")], catch_exceptions=False)
    assert res.exit_code == 0 and (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"
