"""benchmarks.api: a finished run loaded back renders what the run rendered; its cameras, times, render modes,
Gaussians and tree nodes; one-line errors for missing or unfinished runs; the documented example runs."""

from __future__ import annotations

import json
import runpy
import shutil
import sys

import numpy as np
import pytest
import torch

from benchmarks.api import load_run
from worldtree.gaussian_frame import render_frame
from worldtree.infra.errors import UserError
from worldtree.scene_schema import read_cameras

METHODS = ("static", "base", "worldtree")


def _u8(img: torch.Tensor) -> np.ndarray:
    """As the runner writes renders/ (benchmarks.runner.runs._render_test)."""
    return (img.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)


@pytest.fixture(scope="module")
def loaded(api_runs):
    return {m: load_run(api_runs[m], device="cpu") for m in METHODS}


@pytest.mark.parametrize("method", METHODS)
def test_loaded_test_renders_equal_the_runs_own(loaded, method):
    run = loaded[method]
    assert run.method_name == method and run.test_times == list(range(14))
    for t in run.test_times:
        ours = _u8(run.render("test", t))
        saved = run.saved_test_render(t)
        assert ours.shape == saved.shape == (36, 64, 3)
        assert np.array_equal(ours, saved), (method, t, int(np.abs(ours.astype(int) - saved).max()))


def test_cameras_and_times_follow_the_scene(loaded, api_runs):
    run = loaded["base"]
    doc = read_cameras(api_runs["scene"])
    assert run.times == list(range(14))
    assert list(run.cameras) == [f"train_{i:03d}" for i in range(14)] + ["test"]
    for i, fr in enumerate(doc.frames):
        cam = run.cameras[f"train_{i:03d}"]
        assert cam.kind == "train" and cam.frame == i and cam.time == fr.time
        assert (cam.width, cam.height) == (doc.width, doc.height)
        np.testing.assert_array_equal(cam.K.numpy(), np.asarray(doc.camera(fr.camera).K, np.float32))
        np.testing.assert_array_equal(cam.w2c.numpy(), np.asarray(doc.camera(fr.camera).w2c, np.float32))
    test = run.cameras["test"]
    assert test.kind == "test" and test.frame is None and test.time == 0
    np.testing.assert_array_equal(test.w2c.numpy(), np.asarray(doc.camera(doc.test_camera).w2c, np.float32))


def test_a_camera_of_ones_own_is_placed_by_the_method(loaded):
    """(K, w2c, W, H) in the scene frame at any size: the base model places it (the run's Sim(3) and the
    training frames' residuals at the time given), unless it is a training frame's own camera, which is drawn
    from that frame's fitted pose."""
    run = loaded["base"]
    cam = run.cameras["train_003"]
    K = cam.K.clone()
    K[:2] *= 0.5
    moved = cam.w2c.clone()
    moved[0, 3] += 0.05  # 5 cm sideways: no training camera
    img = run.render((K, moved, 32, 18), time=3)
    assert img.shape == (18, 32, 3) and img.dtype == torch.float32 and img.device.type == "cpu"
    assert 0 <= float(img.min()) and float(img.max()) <= 1 and float(img.std()) > 0.01
    frame = run.gaussians_at(3)
    np.testing.assert_allclose(
        run.model_w2c((K, moved, 32, 18), 3).numpy(),
        run.method.state.placement.place(moved, 3.0).numpy(),
        atol=1e-6,
    )
    own = run.model_w2c((K, cam.w2c, 32, 18), 3)
    torch.testing.assert_close(own, run.model_w2c("train_003"), atol=0, rtol=0)
    # The fitted pose is not the Sim(3)'s image of the given one (else this test would not tell them apart).
    assert float((own - frame.scene_to_model.apply_w2c(cam.w2c)).abs().max()) > 1e-5
    with pytest.raises(TypeError, match="give the time"):
        run.render((K, cam.w2c, 32, 18))


@pytest.mark.parametrize("method", METHODS)
def test_render_modes(loaded, method):
    run = loaded[method]
    rgb = run.render("train_005", mode="rgb")
    depth = run.render("train_005", mode="depth")
    alpha = run.render("train_005", mode="alpha")
    dyn = run.render("train_005", mode="dynamic")
    assert rgb.shape == dyn.shape == (36, 64, 3) and depth.shape == alpha.shape == (36, 64)
    assert float(alpha.min()) >= 0 and float(alpha.max()) <= 1 + 1e-5
    drawn = torch.isfinite(depth)
    assert bool(drawn.any()) and torch.equal(drawn, alpha >= 0.5)
    # The tiny scene's wall is at z = 4 and its square at z = 2 (scene units, whatever the model's scale).
    assert 1.0 < float(depth[drawn].median()) < 8.0
    if method == "static":
        assert float(dyn.abs().max()) == 0.0  # nothing dynamic
    else:
        assert float(dyn.max()) > 0.0
    with pytest.raises(UserError, match="mode 'normals'"):
        run.render("test", 0, mode="normals")


@pytest.mark.parametrize("method", METHODS)
def test_gaussians_at_is_what_render_draws(loaded, method):
    """The frame rasterized from the pose the method uses equals the method's own render."""
    run = loaded[method]
    for t in (2, 9):
        frame = run.gaussians_at(t)
        n = len(frame)
        assert frame.time == t and frame.means.shape == (n, 3) and frame.log_scales.shape == (n, 3)
        assert torch.allclose(frame.quats.norm(dim=-1), torch.ones(n), atol=1e-5)
        assert float(frame.opacities.min()) >= 0 and float(frame.opacities.max()) <= 1
        assert frame.dynamic.dtype == torch.bool and (int(frame.dynamic.sum()) > 0) == (method != "static")
        assert frame.node == run.node_at(t)
        cam = run.cameras["test"]
        pose = run.model_w2c("test", t)
        ours = render_frame(frame, cam.K, pose, cam.width, cam.height)
        torch.testing.assert_close(ours, run.render("test", t), atol=1e-6, rtol=0)


def test_node_at(loaded):
    # 14 frames split once at (0 + 13) // 2 = 6: node 2 draws [0, 5], node 3 draws [6, 13].
    assert [loaded["worldtree"].node_at(t) for t in range(14)] == [2] * 6 + [3] * 8
    assert loaded["base"].node_at(4) is None and loaded["static"].node_at(4) is None


def test_device_is_picked(api_runs):
    run = load_run(api_runs["static"])
    assert run.device.type == ("cuda" if torch.cuda.is_available() else "cpu")


def test_bad_runs_and_arguments_are_one_line_errors(api_runs, loaded, tmp_path):
    with pytest.raises(
        UserError, match=r"nowhere: no such run folder; give a folder written by `wtbench run`"
    ):
        load_run(tmp_path / "nowhere")
    with pytest.raises(UserError, match="no config.json"):
        load_run(tmp_path)
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    shutil.copy(api_runs["base"] / "config.json", unfinished / "config.json")
    with pytest.raises(UserError, match="no saved model .* run its command.txt again"):
        load_run(unfinished)
    moved = tmp_path / "moved"
    shutil.copytree(api_runs["static"], moved)
    record = json.loads((moved / "config.json").read_text())
    record["scene"] = str(tmp_path / "gone")
    (moved / "config.json").write_text(json.dumps(record))
    with pytest.raises(UserError, match=r"gone/cameras.json: missing; pass scene="):
        load_run(moved, device="cpu")
    again = load_run(moved, device="cpu", scene=api_runs["scene"])  # the scene given by hand
    assert np.array_equal(_u8(again.render("test", 3)), again.saved_test_render(3))
    with pytest.raises(UserError, match="time 14: .* covers times 0..13"):
        loaded["base"].render("test", 14)
    with pytest.raises(UserError, match="camera 'train_99'"):
        loaded["base"].render("train_99")


def test_documented_example_runs(api_runs, tmp_path, capsys, monkeypatch):
    """docs/examples/python_api.py on a finished run (what docs/python_api.md shows)."""
    from pathlib import Path

    example = Path(__file__).resolve().parents[2] / "docs" / "examples" / "python_api.py"
    monkeypatch.setattr(sys, "argv", [str(example), str(api_runs["worldtree"]), str(tmp_path / "out")])
    runpy.run_path(str(example), run_name="__main__")
    out = capsys.readouterr().out
    assert "worldtree run" in out and "node 3" in out
    assert "time 0: " in out and "time 13: " in out
    written = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert written == ["depth_t004.png", "dynamic_t004.png", "test_t004.png", "train_000_t000.png"]
