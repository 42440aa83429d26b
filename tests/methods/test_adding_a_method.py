"""The example method of docs/adding_a_method.md: one file registers it and `wtbench run` runs it end to end."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks.runner.runs import RunRequest, execute
from methods import registry
from worldtree.imageio import read_image

DOCS = Path(__file__).resolve().parents[2] / "docs"


def test_the_documented_example_is_the_tested_file():
    code = (DOCS / "examples" / "frame_copy.py").read_text()
    assert code.strip() in (DOCS / "adding_a_method.md").read_text()


@pytest.fixture
def frame_copy():
    path = DOCS / "examples" / "frame_copy.py"
    spec = importlib.util.spec_from_file_location("docs_example_frame_copy", path)
    spec.loader.exec_module(importlib.util.module_from_spec(spec))  # registers "frame-copy"
    yield registry.get_method("frame-copy")
    registry._METHODS.pop("frame-copy", None)  # other tests list the registered methods


def test_example_method_registers_and_runs(tmp_path, write_tiny_scene, frame_copy):
    assert frame_copy.name == "frame-copy"
    scene = write_tiny_scene(tmp_path / "tiny", frames=4)
    res = execute(
        RunRequest(scene=scene, method="frame-copy", runs_dir=tmp_path / "runs", preset="quick", progress=False)
    )
    assert res.folder.is_done() and np.isfinite(res.mean["psnr"])
    timing = json.loads(res.folder.timing_json.read_text())
    assert "copy" in timing["method_stats"]["stages_s"] and timing["train"] is None
    # Independent check: each render is the training image of its time (same size here: area resize is exact).
    meta = json.loads((scene / "cameras.json").read_text())
    for fr in meta["frames"]:
        want = read_image(scene / fr["file"])
        got = read_image(res.folder.renders / f"v001_t{fr['time']:03d}.png")
        assert np.abs(got.astype(int) - want.astype(int)).max() <= 1
