"""A test camera that is a training frame's camera (the NVIDIA short protocol): Base places it at that frame's
fitted pose, not through the Sim(3) of all the frames."""

from __future__ import annotations

import dataclasses

import pytest
import torch

import methods.base  # noqa: F401  (registers "base")
from methods.registry import get_method
from worldtree.scene import load_scene
from worldtree.trainer import TrainContext


def _fit(scene_dir, **test_pose):
    spec = get_method("base")
    cfg = spec.config("smoke")
    cfg = dataclasses.replace(
        cfg, priors_cache=False, test_pose=dataclasses.replace(cfg.test_pose, **test_pose)
    )
    torch.manual_seed(0)
    method = spec.build(cfg, load_scene(scene_dir), torch.device("cpu"))
    method.fit(TrainContext(checkpoint_dir=None, progress=False))
    return method


@pytest.fixture(scope="module")
def on_rig(tmp_path_factory, write_tiny_scene):
    return write_tiny_scene(tmp_path_factory.mktemp("scene") / "on_rig", test_on_rig=True)


def test_the_test_camera_starts_at_its_frames_fitted_pose(on_rig):
    torch.set_num_threads(1)
    sc = load_scene(on_rig)
    assert torch.equal(sc.test_w2c, sc.w2cs[0])  # the fixture: the test camera is frame 0's rig camera
    m = _fit(on_rig, enabled=False)  # no refinement: the test pose is where it starts
    s = m.state
    fitted = s.fit.cameras()[0]
    assert s.info["test_pose_start"] == "frame 0"
    for t, pose in s.test_poses.items():
        torch.testing.assert_close(pose, fitted, atol=0, rtol=0, msg=f"time {t}")
    # The same camera at frame 0's time draws what frame 0's fitted camera draws, pixel for pixel.
    K, W, H = sc.test_K, sc.test_images.shape[2], sc.test_images.shape[1]
    assert torch.equal(
        m.render(K, sc.test_w2c, W, H, 0, test_view=True), m.render_mode(K, sc.w2cs[0], W, H, 0, frame=0)
    )
    # BA and the photometric fit moved frame 0's camera off the Sim(3)'s image of its given pose; the old start.
    assert float((s.sim3.apply_w2c(sc.test_w2c) - fitted).abs().max()) > 1e-5


def test_any_other_test_camera_is_placed_at_each_time_and_sigma_0_is_the_sim3(on_rig, tiny_scene):
    """Off a training frame's camera (or with the same-camera start off), the test camera starts where the
    placement puts it: the Sim(3) and the residual of the frames near each test time; without refinement each
    test time keeps its own placement. ``residual_time_sigma=0`` is the Sim(3) alone (the placement before)."""
    torch.set_num_threads(1)
    for scene_dir, sets in ((on_rig, {"start_at_same_camera": False}), (tiny_scene, {})):
        m = _fit(scene_dir, enabled=False, **sets)
        s = m.state
        assert s.info["test_pose_start"] == "placed"
        sc = s.scene
        for t in sc.test_times.tolist():
            want = s.placement.place(sc.test_w2c, min(int(t), sc.num_frames - 1))
            torch.testing.assert_close(s.test_poses[int(t)], want, atol=0, rtol=0)
        # The residuals moved it off the Sim(3)'s image (else this test would not tell them apart).
        assert float((s.test_poses[0] - s.sim3.apply_w2c(sc.test_w2c)).abs().max()) > 1e-6
    m = _fit(tiny_scene, enabled=False, residual_time_sigma=0.0)
    s = m.state
    for pose in s.test_poses.values():
        torch.testing.assert_close(pose, s.sim3.apply_w2c(s.scene.test_w2c), atol=0, rtol=0)
