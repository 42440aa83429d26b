"""The closed-form test scene is a sound oracle: its ground truth agrees with its own images."""

from __future__ import annotations

import cv2
import numpy as np

from benchmarks.fixtures.planar_scene import ping_pong


def test_ping_pong_order():
    assert [ping_pong(t, 4) for t in range(9)] == [0, 1, 2, 3, 2, 1, 0, 1, 2]
    assert ping_pong(5, 1) == 0


def test_gt_flow_is_photoconsistent(planar):
    # Warping frame j by the true flow i->j must reproduce frame i wherever the point is visible in both.
    sc, fr = planar
    H, W = fr["depth"].shape[1:]
    py, px = np.mgrid[0:H, 0:W].astype(np.float32)
    for i, j in ((0, 1), (3, 2), (2, 5)):
        f, vis = sc.flow(i, j)
        warped = cv2.remap(fr["rgb"][j], px + f[..., 0], py + f[..., 1], cv2.INTER_LINEAR)
        inner = vis.copy()
        inner[:2], inner[-2:], inner[:, :2], inner[:, -2:] = False, False, False, False
        err = np.abs(warped - fr["rgb"][i]).mean(-1)[inner]
        assert np.median(err) < 0.01
        assert vis.mean() > 0.8


def test_gt_depth_matches_wall_geometry(planar):
    # Wall pixels: the back-projected point must lie on the plane z = wall_depth in world coordinates.
    sc, fr = planar
    K, w2c = fr["Ks"][0], fr["w2cs"][0]
    kind = sc.render(K, w2c, 0)["kind"]
    ys, xs = np.nonzero(kind == 0)
    z = fr["depth"][0][ys, xs].astype(np.float64)
    cam = np.stack([(xs - K[0, 2]) / K[0, 0] * z, (ys - K[1, 2]) / K[1, 1] * z, z], -1)
    world = (cam - w2c[:3, 3]) @ w2c[:3, :3]
    np.testing.assert_allclose(world[:, 2], sc.cfg.wall_depth, atol=1e-4)
