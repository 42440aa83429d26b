"""`wtbench run`: the run-folder layout, resume after an interruption, skip when finished, --force, and
one-line errors for bad input."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import pandas as pd
import pytest
from typer.testing import CliRunner

from benchmarks.cli import app
from benchmarks.runner.runs import RunRequest, execute, run_tag
from methods.static3dgs import StaticGaussians
from worldtree.infra.errors import UserError


def test_run_twice_skips_and_layout(scene, tmp_path, small_quick):
    runner = CliRunner()
    args = ["run", "--method", "static", "--scene", str(scene), "-o", str(tmp_path), "--preset", "quick"]
    args += ["--steps", "4", "--downscale", "1", "--device", "cpu"]
    first = runner.invoke(app, args, catch_exceptions=False)
    assert first.exit_code == 0, first.output
    folder = tmp_path / "tiny" / "static" / "quick-steps4-downscale1"
    for name in ("DONE", "config.json", "command.txt", "timing.json", "metrics.csv", "metrics.json"):
        assert (folder / name).is_file(), name
    assert sorted(p.name for p in (folder / "renders").iterdir()) == [f"v001_t{t:03d}.png" for t in range(6)]
    assert (folder / "model" / "gaussians.pt").is_file() and (folder / "model" / "gaussians.ply").is_file()
    table = pd.read_csv(folder / "metrics.csv")
    assert len(table) == 7 and table["frame"].iloc[-1] == "mean" and table["psnr"].notna().all()
    cfg = json.loads((folder / "config.json").read_text())
    assert cfg["method"] == "static" and cfg["preset"] == "quick" and cfg["seed"] == 0
    assert cfg["overrides"] == {"steps": 4, "downscale": 1} and cfg["config"]["steps"] == 4
    assert "version" in cfg
    timing = json.loads((folder / "timing.json").read_text())
    assert timing["train"]["steps"] == 4 and timing["num_gaussians"] > 0 and timing["device"] == "cpu"
    assert timing["peak_rss_mib"] > 0 and set(timing["stages_s"]) >= {"train", "render", "eval"}
    assert "--steps 4" in (folder / "command.txt").read_text()
    stamp = (folder / "DONE").stat().st_mtime_ns

    second = runner.invoke(app, args, catch_exceptions=False)
    assert second.exit_code == 0
    assert "already finished" in second.output
    assert (folder / "DONE").stat().st_mtime_ns == stamp


def test_interrupted_run_resumes_from_checkpoint(scene, tmp_path, small_quick, monkeypatch):
    req = RunRequest(
        scene=scene, method="static", runs_dir=tmp_path, preset="quick", device="cpu",
        overrides={"steps": 6}, progress=False,
    )  # fmt: skip
    original = StaticGaussians.training_step

    def failing(self, step):
        if step == 5:
            raise KeyboardInterrupt
        return original(self, step)

    monkeypatch.setattr(StaticGaussians, "training_step", failing)
    with pytest.raises(KeyboardInterrupt):
        execute(req)
    folder = tmp_path / "tiny" / "static" / run_tag("quick", {"steps": 6})
    assert not (folder / "DONE").exists() and (folder / "checkpoints" / "ckpt_0000004.pt").is_file()
    monkeypatch.setattr(StaticGaussians, "training_step", original)
    res = execute(req)
    assert not res.skipped and (folder / "DONE").is_file()
    timing = json.loads((folder / "timing.json").read_text())
    assert timing["train"]["resumed_from_step"] == 4 and timing["train"]["steps_this_session"] == 2
    # --force starts again from scratch.
    res = execute(dataclasses.replace(req, force=True))
    assert json.loads((folder / "timing.json").read_text())["train"]["resumed_from_step"] == 0
    # The same folder with another configuration is refused.
    with pytest.raises(UserError, match="different config"):
        execute(dataclasses.replace(req, overrides={"steps": 7}, tag=folder.name))


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--method", "nosuch", "--scene", "."], "is not a registered method; choose one of:"),
        (["--method", "static", "--scene", "/no/such/scene"], "no such folder"),
        (["--method", "static", "--scene", ".", "--preset", "huge"], "has presets paper, quick"),
    ],
)
def test_bad_input_is_one_line_error(tmp_path, extra, needle, write_tiny_scene):
    scene_dir = tmp_path / "empty_scene"
    scene_dir.mkdir()
    extra = [str(scene_dir) if a == "." else a for a in extra]
    if "--preset" in extra:  # needs a scene that loads as far as the preset check
        write_tiny_scene(scene_dir, frames=1)
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.cli", "run", *extra, "-o", str(tmp_path / "runs")],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], out.stderr


def test_tensorboard_without_package_is_refused_up_front(scene, tmp_path):
    pytest.importorskip("torch")
    try:
        import tensorboard  # noqa: F401

        pytest.skip("tensorboard is installed here")
    except ImportError:
        pass
    req = RunRequest(scene=scene, method="static", runs_dir=tmp_path, preset="quick", tensorboard=True)
    with pytest.raises(UserError, match="tensorboard package"):
        execute(req)
    assert not (tmp_path / "tiny").exists(), "nothing is written before the check"
