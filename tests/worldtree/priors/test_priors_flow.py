"""DIS flow against exact flows (a known warp and the closed-form scene) and the FB check's formula."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from worldtree.priors.config import FlowConfig
from worldtree.priors.flow import (
    compute_flows,
    endpoint_error,
    fb_consistency,
    flow_pairs,
    lands_inside,
    rigid_flow,
    to_gray_u8,
)


def _texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.resize(rng.random((h // 6, w // 6)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(img * 255, 0, 255).astype(np.uint8)


def test_dis_recovers_a_known_homography():
    # Image 1 is image 0 warped by a homography, so the true flow is known in closed form.
    img0 = _texture(120, 160)
    Hm = np.array([[1.01, 0.02, 3.0], [-0.01, 0.99, -2.0], [1e-5, 0.0, 1.0]])
    img1 = cv2.warpPerspective(img0, Hm, (160, 120), flags=cv2.INTER_LINEAR)
    rgb0, rgb1 = (np.repeat(i[..., None], 3, 2) for i in (img0, img1))
    flows = compute_flows(np.stack([rgb0, rgb1]), FlowConfig(offsets=(1,)))
    py, px = np.mgrid[0:120, 0:160].astype(np.float64)
    p = np.stack([px, py, np.ones_like(px)], -1) @ Hm.T
    gt = p[..., :2] / p[..., 2:] - np.stack([px, py], -1)
    inner = np.zeros((120, 160), bool)
    inner[10:-10, 10:-10] = True
    assert endpoint_error(flows[(0, 1)].flow, gt, inner) < 0.3
    assert flows[(0, 1)].valid[inner].mean() > 0.9  # measured 0.93 (FB + photometric checks)


def test_dis_on_planar_scene_epe(planar, planar_u8):
    sc, fr = planar
    flows = compute_flows(planar_u8[:3], FlowConfig(offsets=(1,)))
    for (i, j), fp in flows.items():
        gt, vis = sc.flow(i, j)
        # Measured 0.27 px (static + moving square, 160x96); bound with margin.
        assert endpoint_error(fp.flow, gt, vis & fp.valid) < 0.6
        # Occluded pixels are caught by the FB check far more often than visible ones.
        assert fp.valid[vis].mean() > 0.9


def test_depth_initialised_flow_matches_truth(planar, planar_u8):
    sc, fr = planar
    # With the exact depth the rigid flow of static pixels is exact, so DIS only refines it.
    init = rigid_flow(fr["depth"][0], fr["Ks"][0], fr["w2cs"][0], fr["Ks"][1], fr["w2cs"][1])
    gt, vis = sc.flow(0, 1)
    static = vis & ~fr["mask"][0]
    assert endpoint_error(init, gt, static) < 1e-3
    flows = compute_flows(
        planar_u8[:2], FlowConfig(offsets=(1,)), depth=fr["depth"], Ks=fr["Ks"], w2cs=fr["w2cs"]
    )
    assert endpoint_error(flows[(0, 1)].flow, gt, vis & flows[(0, 1)].valid) < 0.6


def test_fb_check_formula():
    H, W = 20, 30
    d = np.zeros((H, W, 2), np.float32)
    d[..., 0] = 2.0
    # Perfectly inverse fields pass wherever the target stays inside the image.
    ok = fb_consistency(d, -d)
    assert ok[:, : W - 3].all() and not ok[:, W - 2 :].any()
    # |f + b| = 4 against 0.5 (2 + 2) + 0.5 = 2.5 fails; a 1 px disagreement (1 < 2.5) passes.
    assert not fb_consistency(d, d)[:, :10].any()
    b = -d.copy()
    b[..., 1] = 1.0
    assert fb_consistency(d, b)[:, :10].all()
    # Zero flow both ways with the constant slack of 0.5 px passes.
    z = np.zeros_like(d)
    assert fb_consistency(z, z).all()
    assert lands_inside(d)[:, : W - 3].all() and not lands_inside(d)[:, W - 2 :].any()


def test_flow_pairs_and_gray():
    assert flow_pairs(4, (1, 2)) == [
        (0, 1),
        (1, 0),
        (1, 2),
        (2, 1),
        (2, 3),
        (3, 2),
        (0, 2),
        (2, 0),
        (1, 3),
        (3, 1),
    ]
    assert flow_pairs(2, (3,)) == []
    g = to_gray_u8(np.full((2, 2, 3), 0.5, np.float32))
    assert g.dtype == np.uint8 and int(g[0, 0]) in (127, 128)


@pytest.mark.parametrize("preset", ["ultrafast", "fast"])
def test_presets_run(preset, planar_u8):
    flows = compute_flows(planar_u8[:2], FlowConfig(preset=preset, offsets=(1,)))
    assert set(flows) == {(0, 1), (1, 0)}
    assert np.isfinite(flows[(0, 1)].flow).all()


def test_rigid_flow_on_a_large_frame_matches_projection():
    # 300 x 200 = 60000 pixels (beyond cv2.remap's 32767-per-side map limit); checked at a few pixels by hand.
    H, W = 200, 300
    rng = np.random.default_rng(5)
    depth = (2.0 + rng.random((H, W))).astype(np.float32)
    K = np.array([[250.0, 0, 150], [0, 250, 100], [0, 0, 1]])
    w1, w2 = np.eye(4), np.eye(4)
    w2[:3, :3] = cv2.Rodrigues(np.array([0.02, -0.03, 0.01]))[0]
    w2[:3, 3] = [-0.1, 0.02, 0.0]
    f = rigid_flow(depth, K, w1, K, w2)
    for y, x in ((0, 0), (57, 211), (199, 299)):
        X = np.linalg.inv(K) @ np.array([x, y, 1.0]) * depth[y, x]
        p = K @ (w2[:3, :3] @ X + w2[:3, 3])
        np.testing.assert_allclose(f[y, x], p[:2] / p[2] - [x, y], atol=1e-3)
