"""Base and WorldTree with temporal opacity (``--set dynamic_time_std=1``) through `wtbench run` on the tiny
26-frame analytic scene (smoke schedule): both runs finish with finite scores (WorldTree's children and
ancestor copies render with the temporal opacity), and Base's saved dynamic Gaussians carry the learned log
temporal std."""

from __future__ import annotations

import json
import math

import numpy as np
import torch
from typer.testing import CliRunner

from benchmarks.cli import app
from worldtree.dynamic import TIME_STD, DynamicGaussians


def _metrics(folder) -> dict:
    return json.loads(next(folder.rglob("metrics.json")).read_text())


def test_base_and_worldtree_run_with_temporal_opacity(tmp_path, write_tiny_scene):
    scene = write_tiny_scene(tmp_path / "tiny26", frames=26)
    common = ["--scene", str(scene), "-o", str(tmp_path / "runs"), "--preset", "smoke", "--device", "cpu",
              "--set", "dynamic_time_std=1.0"]  # fmt: skip
    for method in ("base", "worldtree"):
        res = CliRunner().invoke(app, ["run", "--method", method, *common])
        assert res.exit_code == 0, res.output
    for method in ("base", "worldtree"):
        folder = tmp_path / "runs" / "tiny26" / method
        cfg = json.loads(next(folder.rglob("config.json")).read_text())
        assert cfg["config"]["dynamic_time_std"] == 1.0
        psnr = _metrics(folder)["mean"]["psnr"]
        assert np.isfinite(psnr) and psnr > 10.0
    # Base's saved dynamic Gaussians carry the temporal std, moved away from its start by the fit.
    dyn = DynamicGaussians.load(next((tmp_path / "runs" / "tiny26" / "base").rglob("dynamic_gaussians.pt")))
    assert len(dyn) > 0
    logstd = dyn.params[TIME_STD].detach()
    assert torch.isfinite(logstd).all() and float((logstd - math.log(1.0)).abs().max()) > 0
