"""The synthetic rig generator: geometry checked against closed forms, ground truth consistent with images."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nvidia_ls.synth import FLOOR_Y, SynthConfig, gt_flow, make_scene, render_view, write_raw_scene
from worldtree.imageio import read_image, read_mask

CFG = SynthConfig(cameras=12, steps=10, width=96, height=54, supersample=1)


def _backproject(K, w2c, depth):
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    pix = np.stack([u, v, np.ones_like(u)], -1).astype(float)
    cam = (pix @ np.linalg.inv(K).T) * depth[..., None]
    R, t = w2c[:3, :3], w2c[:3, 3]
    return (cam - t) @ R  # R^T (x_cam - t)


def test_rig_geometry():
    sc = make_scene(CFG)
    assert sc.Ks.shape == (12, 3, 3) and sc.w2cs.shape == (12, 4, 4)
    f = 0.5 * 96 / np.tan(np.radians(30))
    np.testing.assert_allclose(sc.Ks[0], [[f, 0, 47.5], [0, f, 26.5], [0, 0, 1]])
    for w in sc.w2cs:
        np.testing.assert_allclose(w[:3, :3] @ w[:3, :3].T, np.eye(3), atol=1e-12)
        assert np.linalg.det(w[:3, :3]) > 0
        assert w[2, 2] > 0.95  # every camera looks roughly along +z
    centres = np.stack([-w[:3, :3].T @ w[:3, 3] for w in sc.w2cs])
    assert np.ptp(centres[:, 1]) > 0.2  # two rows
    np.testing.assert_allclose(np.ptp(centres[:, 0]), CFG.rig_width, rtol=0.02)


def test_depth_backprojects_onto_the_floor_and_the_back_wall():
    sc = make_scene(CFG)
    view = render_view(sc, sc.Ks[3], sc.w2cs[3], 96, 54, time=0.0)
    pts = _backproject(sc.Ks[3], sc.w2cs[3], view.depth.astype(float))
    static = view.object_id == 0
    on_floor = static & (np.abs(pts[..., 1] - FLOOR_Y) < 1e-3)
    on_back = static & (np.abs(pts[..., 2] - 8.0) < 1e-3)
    assert on_floor.sum() > 200 and on_back.sum() > 200
    # Bottom image row sees the floor, at the depth a ray-plane intersection gives in closed form.
    K, w2c = sc.Ks[3], sc.w2cs[3]
    d_cam = np.linalg.inv(K) @ np.array([48.0, 53.0, 1.0])
    d_world = w2c[:3, :3].T @ d_cam
    origin = -w2c[:3, :3].T @ w2c[:3, 3]
    s = (FLOOR_Y - origin[1]) / d_world[1]
    if view.object_id[53, 48] == 0:
        np.testing.assert_allclose(view.depth[53, 48], s * d_cam[2], rtol=1e-4)


def test_sphere_silhouette_matches_its_pose():
    sc = make_scene(CFG)
    for t in (0.0, 4.5):
        view = render_view(sc, sc.Ks[0], sc.w2cs[0], 96, 54, time=t)
        T = sc.object_pose(0, t)
        pc = sc.w2cs[0][:3, :3] @ T[:3, 3] + sc.w2cs[0][:3, 3]
        proj = sc.Ks[0] @ pc
        u, v = proj[:2] / proj[2]
        ys, xs = np.nonzero(view.object_id == 1)
        # The sphere's silhouette is centred near the projected centre (exact up to perspective, ~1 px).
        if len(xs) > 30 and 5 < u < 90 and 5 < v < 49:
            assert abs(xs.mean() - u) < 1.5 and abs(ys.mean() - v) < 1.5
        # Pixels of the sphere are at distance radius from its centre.
        pts = _backproject(sc.Ks[0], sc.w2cs[0], view.depth.astype(float))[view.object_id == 1]
        np.testing.assert_allclose(np.linalg.norm(pts - T[:3, 3], axis=1), 0.45, atol=2e-3)


def test_slow_fast_profile():
    sc = make_scene(SynthConfig(steps=41, motion="slow_fast"))
    phase = np.array([sc.phase(t) for t in range(41)])
    assert phase[0] == 0 and phase[-1] == 1 and np.all(np.diff(phase) > 0)
    speed = np.diff(phase)
    np.testing.assert_allclose(speed[25:].mean() / speed[:15].mean(), 4.0, rtol=1e-6)
    const = make_scene(SynthConfig(steps=41))
    np.testing.assert_allclose(np.diff([const.phase(t) for t in range(41)]), 1 / 40)


@pytest.mark.parametrize(("motion", "loops"), [("near_static", 0.02), ("slow", 0.25), ("fast", 2.0)])
def test_constant_speed_profiles(motion, loops):
    sc = make_scene(SynthConfig(steps=41, motion=motion))
    np.testing.assert_allclose(np.diff([sc.phase(t) for t in range(41)]), loops / 40)
    # The sphere moves by the loop fraction: near_static barely (< 0.1 world units), fast returns to start.
    moved = np.linalg.norm(sc.object_pose(0, 40)[:3, 3] - sc.object_pose(0, 0)[:3, 3])
    if motion == "near_static":
        assert moved < 0.2
    if motion == "fast":
        assert moved < 1e-9


def test_written_ground_truth_is_consistent(tmp_path):
    cfg = SynthConfig(cameras=3, steps=4, width=48, height=32, depth=True, supersample=1)
    raw = write_raw_scene(tmp_path / "S", cfg)
    sc = make_scene(cfg)
    meta = json.loads((raw / "gt" / "cameras.json").read_text())
    np.testing.assert_allclose(np.asarray(meta["cameras"][1]["w2c"]), sc.w2cs[1])
    objs = json.loads((raw / "gt" / "objects.json").read_text())
    np.testing.assert_allclose(objs["objects"][1]["world_from_object"][2], sc.object_pose(1, 2.0))
    view = render_view(sc, sc.Ks[2], sc.w2cs[2], 48, 32, time=3.0)
    np.testing.assert_array_equal(read_image(raw / "mv_images" / "00003" / "cam03.png"), view.rgb)
    np.testing.assert_array_equal(read_mask(raw / "gt" / "masks" / "00003" / "cam03.png"), view.object_id > 0)
    np.testing.assert_array_equal(np.load(raw / "gt" / "depth" / "00003" / "cam03.npy"), view.depth)
    assert np.load(raw / "gt" / "poses_bounds.npy").shape == (3, 17)


def test_cameras_written_side_by_side_match_single_renders_and_progress_counts_up(tmp_path):
    # The writer renders cameras on a thread per core; every file must still be the camera's own render.
    cfg = SynthConfig(cameras=4, steps=2, width=40, height=24, supersample=1)
    calls = []
    raw = write_raw_scene(tmp_path / "S", cfg, progress=lambda done, total: calls.append((done, total)))
    sc = make_scene(cfg)
    for ci in range(cfg.cameras):
        view = render_view(sc, sc.Ks[ci], sc.w2cs[ci], 40, 24, time=1.0)
        np.testing.assert_array_equal(read_image(raw / "mv_images" / "00001" / f"cam{ci + 1:02d}.png"), view.rgb)
    assert calls == [(k, 4) for k in range(1, 5)]


def test_deterministic_in_seed():
    a = render_view(make_scene(CFG), make_scene(CFG).Ks[0], make_scene(CFG).w2cs[0], 96, 54, 2.0)
    sc = make_scene(CFG)
    b = render_view(sc, sc.Ks[0], sc.w2cs[0], 96, 54, 2.0)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    other = make_scene(SynthConfig(cameras=12, steps=10, width=96, height=54, supersample=1, seed=1))
    c = render_view(other, other.Ks[0], other.w2cs[0], 96, 54, 2.0)
    assert np.abs(a.rgb.astype(int) - c.rgb).mean() > 5


def test_gt_flow_static_and_moving():
    sc = make_scene(CFG)
    K, w2c = sc.Ks[0], sc.w2cs[0]
    # Same camera, two times: the static set does not move; the sphere's centre pixel moves with the sphere.
    # 0.1 step: the sphere spins 12 degrees, so few of its points turn out of sight.
    flow, ids = gt_flow(sc, K, w2c, 2.0, K, w2c, 2.1, 96, 54)
    np.testing.assert_allclose(flow[ids == 0], 0, atol=1e-3)
    assert np.nanmax(np.abs(flow[ids == 1])) > 0.5

    # Independent check through a second render: the pixel the flow points to at t=2.1 shows the same material
    # point of the sphere (same object-local coordinates), up to the pixel footprint.
    view3 = render_view(sc, K, w2c, 96, 54, 2.1)
    pts2 = _backproject(K, w2c, render_view(sc, K, w2c, 96, 54, 2.0).depth.astype(float))
    pts3 = _backproject(K, w2c, view3.depth.astype(float))
    T2inv, T3inv = np.linalg.inv(sc.object_pose(0, 2.0)), np.linalg.inv(sc.object_pose(0, 2.1))
    ys, xs = np.nonzero(ids == 1)
    errs = []
    for y, x in zip(ys, xs, strict=True):
        x3, y3 = (int(round(a)) for a in (x + flow[y, x, 0], y + flow[y, x, 1]))
        if 0 <= x3 < 96 and 0 <= y3 < 54 and view3.object_id[y3, x3] == 1:
            a = T2inv[:3, :3] @ pts2[y, x] + T2inv[:3, 3]
            b = T3inv[:3, :3] @ pts3[y3, x3] + T3inv[:3, 3]
            errs.append(np.linalg.norm(a - b))
    assert len(errs) > 20 and np.median(errs) < 0.05
    # Another camera, same time: static flow = reprojection through the depth map (a stereo pair).
    flow2, ids2 = gt_flow(sc, K, w2c, 0.0, sc.Ks[1], sc.w2cs[1], 0.0, 96, 54)
    assert np.isfinite(flow2[ids2 >= 0]).all() and np.nanmean(np.abs(flow2[..., 0])) > 0.5
