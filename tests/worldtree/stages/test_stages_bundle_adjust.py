"""Tracklet BA on a synthetic rig: known cameras, static points on a bumpy surface, tracks = projections + noise, and a
depth prior with a wrong scale per frame."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from worldtree.stages.bundle_adjust import BundleAdjustConfig, bundle_adjust
from worldtree.stages.cameras import centres, rotation_angle_deg

W, H, T = 64, 36, 8


def height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """World z of the static surface (a bumpy sheet ~4 units ahead; not a plane, which would be degenerate)."""
    return 4.0 + 0.6 * np.sin(1.5 * x + 0.3) * np.cos(1.2 * y) + 0.2 * x


def intersect(c: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Ray parameter s of the first hit of ``c + s * rays`` with the surface (fixed-point iteration)."""
    s = (4.0 - c[2]) / rays[:, 2]
    for _ in range(60):
        p = c + s[:, None] * rays
        s = (height(p[:, 0], p[:, 1]) - c[2]) / rays[:, 2]
    return s


def make_problem(seed: int = 0, n_points: int = 300, noise_px: float = 0.3):
    rng = np.random.default_rng(seed)
    K = np.array([[50.0, 0, (W - 1) / 2], [0, 50.0, (H - 1) / 2], [0, 0, 1]])
    w2cs = []
    for t in range(T):
        R = Rotation.from_euler("xyz", [0.02 * np.sin(t), 0.05 * np.cos(t), 0.01 * t], degrees=False)
        c = np.array([-0.6 + 1.2 * t / (T - 1), 0.1 * np.sin(t), 0.05 * t])
        w = np.eye(4)
        w[:3, :3] = R.as_matrix().T
        w[:3, 3] = -R.as_matrix().T @ c
        w2cs.append(w)
    w2cs = np.stack(w2cs)
    # Points on the surface seen by the middle camera.
    uv = rng.uniform([4, 4], [W - 5, H - 5], size=(n_points, 2))
    mid = w2cs[T // 2]
    rays_c = np.linalg.solve(K, np.c_[uv, np.ones(n_points)].T).T
    rays_w = rays_c @ mid[:3, :3]  # R^T ray
    c_mid = -mid[:3, :3].T @ mid[:3, 3]
    X = c_mid + intersect(c_mid, rays_w)[:, None] * rays_w
    # Tracks and visibility.
    tracks = np.zeros((T, n_points, 2))
    vis = np.zeros((T, n_points), bool)
    for t in range(T):
        cam = X @ w2cs[t][:3, :3].T + w2cs[t][:3, 3]
        p = cam @ K.T
        p = p[:, :2] / p[:, 2:]
        tracks[t] = p + rng.normal(scale=noise_px, size=p.shape)
        vis[t] = (p[:, 0] > 0) & (p[:, 0] < W - 1) & (p[:, 1] > 0) & (p[:, 1] < H - 1)
    # Exact depth maps by ray-surface intersection, then a wrong scale per frame.
    jj, ii = np.meshgrid(np.arange(W), np.arange(H))
    pix = np.stack([jj, ii, np.ones_like(jj)], -1).reshape(-1, 3).astype(float)
    depth = np.zeros((T, H, W))
    for t in range(T):
        rc = np.linalg.solve(K, pix.T).T  # camera rays with z = 1
        rw = rc @ w2cs[t][:3, :3]
        c = -w2cs[t][:3, :3].T @ w2cs[t][:3, 3]
        depth[t] = intersect(c, rw).reshape(H, W)  # camera z, as the rays have z = 1 in the camera
    wrong = np.exp(rng.uniform(np.log(0.8), np.log(1.25), size=T))
    depth_prior = depth * wrong[:, None, None]
    # Perturbed starting poses (frame 0 exact: it is the gauge).
    init = w2cs.copy()
    for t in range(1, T):
        dR = Rotation.from_rotvec(rng.normal(size=3) * np.deg2rad(1.0) / np.sqrt(3)).as_matrix()
        init[t][:3, :3] = dR @ init[t][:3, :3]
        init[t][:3, 3] = dR @ init[t][:3, 3] + rng.normal(scale=0.04, size=3)
    f = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float32))  # noqa: E731
    return {
        "tracks": f(tracks),
        "visible": torch.from_numpy(vis),
        "depth": f(depth_prior),
        "Ks": f(np.repeat(K[None], T, 0)),
        "init": f(init),
        "truth": f(w2cs),
        "wrong": wrong,
    }


def umeyama_centre_error(a: torch.Tensor, b: torch.Tensor) -> float:
    """Max centre distance after the best similarity (numpy, independent of the code under test)."""
    x, y = centres(a).double().numpy(), centres(b).double().numpy()
    mx, my = x.mean(0), y.mean(0)
    U, D, Vt = np.linalg.svd((y - my).T @ (x - mx))
    S = np.eye(3)
    S[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ S @ Vt
    s = np.trace(np.diag(D) @ S) / ((x - mx) ** 2).sum()
    return float(np.linalg.norm(s * (x - mx) @ R.T + my - y, axis=1).max())


def test_ba_reduces_pose_error_and_recovers_relative_depth_scales():
    p = make_problem()
    static = torch.ones(p["tracks"].shape[1], dtype=torch.bool)
    cfg = BundleAdjustConfig(steps=500, lr_rot=2e-3, lr_trans=2e-3, lr_depth_scale=2e-2, lr_track_depth=2e-2)
    res = bundle_adjust(p["tracks"], p["visible"], static, p["depth"], p["Ks"], p["init"], cfg)
    rot_before = float(rotation_angle_deg(p["init"][1:, :3, :3], p["truth"][1:, :3, :3]).max())
    rot_after = float(rotation_angle_deg(res.w2cs[1:, :3, :3], p["truth"][1:, :3, :3]).max())
    c_before = umeyama_centre_error(p["init"], p["truth"])
    c_after = umeyama_centre_error(res.w2cs, p["truth"])
    assert rot_after < 0.3 * rot_before, (rot_before, rot_after)
    assert c_after < 0.3 * c_before, (c_before, c_after)
    assert res.reproj_px_after < 0.7, res.reproj_px_after
    assert res.reproj_px_after < 0.5 * res.reproj_px_before  # the floor is the noise of the anchors
    # scale_t * wrong_t is the same for every frame: the depth priors agree after rescaling.
    k = res.depth_scale.double().numpy() * p["wrong"]
    assert np.std(np.log(k)) < 0.01, k
    # Gauge: frame 0 untouched, scales have a geometric mean of 1.
    torch.testing.assert_close(res.w2cs[0], p["init"][0])
    assert abs(float(res.depth_scale.log().mean())) < 1e-5


def test_ba_ignores_dynamic_tracks_and_caps_the_count():
    p = make_problem(seed=1, n_points=120)
    static = torch.ones(120, dtype=torch.bool)
    static[:20] = False
    # Dynamic tracks get garbage positions: they must not be used at all.
    p["tracks"][:, :20] = torch.rand(T, 20, 2) * torch.tensor([W, H])
    cfg = BundleAdjustConfig(steps=5, max_tracks=50, seed=3)
    res = bundle_adjust(p["tracks"], p["visible"], static, p["depth"], p["Ks"], p["init"], cfg)
    assert res.track_ids.numel() == 50
    assert bool((res.track_ids >= 20).all())
    assert res.points.shape == (50, 3)


def test_ba_disabled_or_without_tracks_returns_the_input():
    p = make_problem(seed=2, n_points=30)
    none_static = torch.zeros(30, dtype=torch.bool)
    res = bundle_adjust(p["tracks"], p["visible"], none_static, p["depth"], p["Ks"], p["init"])
    torch.testing.assert_close(res.w2cs, p["init"])
    torch.testing.assert_close(res.depth_scale, torch.ones(T))
    res = bundle_adjust(
        p["tracks"],
        p["visible"],
        ~none_static,
        p["depth"],
        p["Ks"],
        p["init"],
        BundleAdjustConfig(enabled=False),
    )
    torch.testing.assert_close(res.w2cs, p["init"])
    assert res.track_ids.numel() > 0 or res.points.shape[0] == 0


def test_ba_outlier_tracks_are_clamped():
    """A few grossly wrong static tracks must not spoil the result (clamped residuals)."""
    p = make_problem(seed=4)
    static = torch.ones(p["tracks"].shape[1], dtype=torch.bool)
    p["tracks"][3:, :15] += 200.0  # far outside the clamp, in frames 3.. only
    cfg = BundleAdjustConfig(steps=500, lr_rot=2e-3, lr_trans=2e-3, lr_depth_scale=2e-2, lr_track_depth=2e-2)
    res = bundle_adjust(p["tracks"], p["visible"], static, p["depth"], p["Ks"], p["init"], cfg)
    rot_after = float(rotation_angle_deg(res.w2cs[1:, :3, :3], p["truth"][1:, :3, :3]).max())
    rot_before = float(rotation_angle_deg(p["init"][1:, :3, :3], p["truth"][1:, :3, :3]).max())
    assert rot_after < 0.3 * rot_before
    assert all(np.isfinite(list(h.values())).all() for h in res.history)
