"""Fundamental matrices, Sampson distances, EPI masks and dynamic-track labels."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from worldtree.priors.config import EpiConfig, FlowConfig
from worldtree.priors.epipolar import (
    epi_masks,
    epipolar_error_maps,
    fundamental_from_poses,
    homography_transfer_error,
    label_dynamic_tracks,
    relative_pose,
    sampson_distance,
)
from worldtree.priors.flow import FlowPair, compute_flows


def _camera(rng, centre):
    rvec = rng.normal(0, 0.1, 3)
    R = cv2.Rodrigues(rvec)[0]
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ centre
    return w2c


def _project(K, w2c, X):
    Xc = X @ w2c[:3, :3].T + w2c[:3, 3]
    return (Xc[:, :2] / Xc[:, 2:]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]


@pytest.fixture
def two_views():
    rng = np.random.default_rng(1)
    K1 = np.array([[300.0, 0, 160], [0, 310, 120], [0, 0, 1]])
    K2 = np.array([[280.0, 0, 150], [0, 280, 125], [0, 0, 1]])
    w1, w2 = _camera(rng, np.zeros(3)), _camera(rng, np.array([0.4, -0.1, 0.05]))
    X = rng.uniform([-1, -1, 3], [1, 1, 6], (200, 3))
    return K1, w1, K2, w2, X, _project(K1, w1, X), _project(K2, w2, X)


def test_fundamental_from_poses_satisfies_epipolar_constraint(two_views):
    K1, w1, K2, w2, X, x1, x2 = two_views
    F = fundamental_from_poses(K1, w1, K2, w2)
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], 1)
    h2 = np.concatenate([x2, np.ones((len(x2), 1))], 1)
    assert np.abs(np.sum(h2 * (h1 @ F.T), 1)).max() < 1e-6
    # Independent estimate from the exact correspondences agrees up to scale and sign.
    F8, _ = cv2.findFundamentalMat(x1, x2, cv2.FM_8POINT)
    F8 = F8 / np.linalg.norm(F8)
    assert min(np.linalg.norm(F - F8), np.linalg.norm(F + F8)) < 1e-4
    R, t = relative_pose(w1, w2)
    np.testing.assert_allclose(R @ w1[:3, :3], w2[:3, :3], atol=1e-12)


def test_sampson_distance_matches_opencv(two_views):
    K1, w1, K2, w2, X, x1, x2 = two_views
    F = fundamental_from_poses(K1, w1, K2, w2)
    rng = np.random.default_rng(2)
    x2n = x2 + rng.normal(0, 3, x2.shape)
    d = sampson_distance(F, x1, x2n)
    ref = np.array(
        [
            cv2.sampsonDistance(np.array([*a, 1.0]), np.array([*b, 1.0]), F)
            for a, b in zip(x1, x2n, strict=True)
        ]
    )
    np.testing.assert_allclose(d, np.sqrt(ref), rtol=1e-6, atol=1e-9)
    assert sampson_distance(F, x1, x2).max() < 1e-6


def test_pure_rotation_uses_homography():
    K = np.array([[200.0, 0, 80], [0, 200, 60], [0, 0, 1]])
    w1 = np.eye(4)
    w2 = np.eye(4)
    w2[:3, :3] = cv2.Rodrigues(np.array([0.0, 0.05, 0.0]))[0]
    Hm = K @ w2[:3, :3] @ np.linalg.inv(K)
    x1 = np.array([[10.0, 20.0], [100.0, 50.0]])
    p = np.concatenate([x1, np.ones((2, 1))], 1) @ Hm.T
    x2 = p[:, :2] / p[:, 2:]
    assert homography_transfer_error(Hm, x1, x2).max() < 1e-9
    # A pair of same-centre cameras: a flow following the rotation scores 0, one 3 px off scores 3.
    H, W = 120, 160
    py, px = np.mgrid[0:H, 0:W].astype(np.float64)
    q = np.stack([px, py, np.ones_like(px)], -1) @ Hm.T
    f = (q[..., :2] / q[..., 2:] - np.stack([px, py], -1)).astype(np.float32)
    Ks = np.stack([K, K])
    w2cs = np.stack([w1, w2])
    err = epipolar_error_maps({(0, 1): FlowPair(f, np.ones((H, W), bool))}, 2, Ks, w2cs, EpiConfig())
    assert err[0].max() < 1e-3 and not err[1].any()
    f2 = f.copy()
    f2[..., 1] += 3.0
    cfg = EpiConfig(max_pair_median_px=1e9)  # the whole frame is off here; keep the pair
    err = epipolar_error_maps({(0, 1): FlowPair(f2, np.ones((H, W), bool))}, 2, Ks, w2cs, cfg)
    np.testing.assert_allclose(err[0], 3.0, atol=1e-3)


def test_epi_mask_iou_on_planar_scene(planar, planar_u8):
    sc, fr = planar
    flows = compute_flows(planar_u8, FlowConfig())
    err = epipolar_error_maps(flows, len(planar_u8), fr["Ks"], fr["w2cs"], EpiConfig())
    mask = epi_masks(err, EpiConfig())
    gt = fr["mask"]
    iou = (mask & gt).sum() / (mask | gt).sum()
    assert iou > 0.5  # measured 0.75
    # Without poses, LMedS-estimated fundamental matrices find the same motion.
    err2 = epipolar_error_maps(
        flows, len(planar_u8), None, None, EpiConfig(use_poses=False, lmeds_points=1000)
    )
    mask2 = epi_masks(err2, EpiConfig())
    assert (mask2 & gt).sum() / (mask2 | gt).sum() > 0.5


def test_exact_static_flow_gives_empty_masks(planar_static):
    sc, fr = planar_static
    T = len(fr["rgb"])
    flows = {}
    for i in range(T - 1):
        for a, b in ((i, i + 1), (i + 1, i)):
            f, vis = sc.flow(a, b)
            flows[(a, b)] = FlowPair(f, vis)
    err = epipolar_error_maps(flows, T, fr["Ks"], fr["w2cs"], EpiConfig())
    assert err.max() < 1e-3
    assert not epi_masks(err, EpiConfig()).any()


def test_failed_pair_is_skipped():
    # A pair whose error is large everywhere (flow lost) must not paint the whole frame dynamic.
    H, W = 40, 60
    K = np.array([[100.0, 0, 30], [0, 100, 20], [0, 0, 1]])
    w1, w2 = np.eye(4), np.eye(4)
    w2[0, 3] = -0.2  # camera 2 moves right: epipolar lines are horizontal
    f = np.zeros((H, W, 2), np.float32)
    f[..., 1] = 5.0  # everything "moves" 5 px vertically
    flows = {(0, 1): FlowPair(f, np.ones((H, W), bool))}
    err = epipolar_error_maps(flows, 2, np.stack([K, K]), np.stack([w1, w2]), EpiConfig())
    assert not err.any()
    err = epipolar_error_maps(
        flows, 2, np.stack([K, K]), np.stack([w1, w2]), EpiConfig(max_pair_median_px=1e9)
    )
    # Sampson distance splits the correction between both images: a 5 px offset across parallel epipolar
    # lines of equal gradient is 5 / sqrt(2) in the joint space.
    np.testing.assert_allclose(err[0], 5.0 / np.sqrt(2.0), atol=1e-4)


def test_dynamic_track_labels_need_two_frames():
    T, H, W = 4, 10, 10
    masks = np.zeros((T, H, W), bool)
    masks[1, 0:5, 0:5] = True
    masks[2, 0:5, 0:5] = True
    tracks = np.zeros((T, 3, 2), np.float32)
    tracks[:, 0] = [2, 2]  # inside the mask in frames 1 and 2 -> dynamic
    tracks[:, 1] = [8, 8]  # never inside -> static
    tracks[:, 2] = [2, 2]
    vis = np.ones((T, 3), bool)
    vis[2, 2] = False  # inside in frame 1 only while visible -> static
    np.testing.assert_array_equal(label_dynamic_tracks(tracks, vis, masks, 2), [True, False, False])
    np.testing.assert_array_equal(label_dynamic_tracks(tracks, vis, masks, 1), [True, False, True])


def test_empty_masks_and_no_tracks_do_not_crash():
    T, H, W = 3, 8, 8
    empty = np.zeros((T, H, W), bool)
    assert label_dynamic_tracks(np.zeros((T, 0, 2), np.float32), np.zeros((T, 0), bool), empty).shape == (0,)
    lab = label_dynamic_tracks(np.full((T, 5, 2), 3.0, np.float32), np.ones((T, 5), bool), empty)
    assert lab.shape == (5,) and not lab.any()
    assert not epi_masks(np.zeros((T, H, W), np.float32), EpiConfig()).any()
