"""Depths of moving points from smooth trajectories, against the points' known depths."""

from __future__ import annotations

import math

import pytest
import torch

from worldtree.motion.track_depth import ratio_map, smooth_trajectory_depths, trajectory_scale

H, W = 60, 80
K = torch.tensor([[70.0, 0.0, 39.5], [0.0, 70.0, 29.5], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _rig(T: int) -> torch.Tensor:
    """``[T, 4, 4]`` cameras of a 6-camera row visited in ping-pong order (0..5..0), looking along +z."""
    out = []
    for t in range(T):
        k = t % 10
        cam = k if k < 6 else 10 - k
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, 3] = -torch.tensor([0.12 * cam - 0.3, 0.03 * math.sin(cam), 0.0], dtype=torch.float64)
        out.append(w2c)
    return torch.stack(out)


def _observe(X: torch.Tensor, w2cs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels ``[T, N, 2]`` and camera depths ``[T, N]`` of world points ``X`` [T, N, 3]."""
    cam = X @ w2cs[:, :3, :3].transpose(1, 2) + w2cs[:, None, :3, 3]
    uv = cam[..., :2] / cam[..., 2:] * K.diagonal()[:2] + K[:2, 2]
    return uv, cam[..., 2]


def _depth_maps(T: int, value: torch.Tensor) -> torch.Tensor:
    """Depth maps constant per frame (``value`` [T]): the prior every track of that frame samples."""
    return value[:, None, None].expand(T, H, W).clone()


@pytest.mark.parametrize("velocity", [(0.0, 0.0, 0.0), (0.02, -0.01, 0.015)])
def test_points_at_rest_or_at_constant_velocity_are_recovered_from_a_wrong_prior(velocity):
    T = 20
    w2cs = _rig(T)
    t = torch.arange(T, dtype=torch.float64)[:, None]
    X = (
        torch.tensor([0.1, 0.05, 2.0], dtype=torch.float64) + t * torch.tensor(velocity, dtype=torch.float64)
    )[:, None]  # [T, 1, 3]
    uv, z_true = _observe(X, w2cs)
    wrong = z_true[:, 0] * (1.0 + 0.3 * torch.cos(1.3 * t[:, 0]))  # up to 30 % off, different every frame
    z, solved = smooth_trajectory_depths(
        uv, torch.ones(T, 1, dtype=torch.bool), _depth_maps(T, wrong), K.expand(T, 3, 3), w2cs, 2.0, 1e-8
    )
    assert bool(solved[0])
    torch.testing.assert_close(z[:, 0], z_true[:, 0], rtol=1e-4, atol=0)


def test_a_curved_path_gets_much_closer_than_its_prior():
    """A point on a circle (no exact zero-acceleration answer): the least squares at least halves the error
    of a prior 25 % off in alternating directions (the zig-zag between the cameras' rays it removes)."""
    T = 30
    w2cs = _rig(T)
    phi = 0.15 * torch.arange(T, dtype=torch.float64)
    X = torch.stack([0.3 * torch.sin(phi), 0.2 * torch.cos(phi), 2.2 + 0.3 * torch.sin(phi)], -1)[:, None]
    uv, z_true = _observe(X, w2cs)
    sign = torch.tensor([(-1.0) ** t for t in range(T)], dtype=torch.float64)
    prior = z_true[:, 0] * (1 + 0.25 * sign)
    z, solved = smooth_trajectory_depths(
        uv, torch.ones(T, 1, dtype=torch.bool), _depth_maps(T, prior), K.expand(T, 3, 3), w2cs, 2.0, 3e-3
    )
    err = (z[:, 0] / z_true[:, 0]).log().abs().median()
    err_prior = (prior / z_true[:, 0]).log().abs().median()
    assert bool(solved[0]) and float(err) < 0.5 * float(err_prior)


def test_short_tracks_keep_the_prior_and_invisible_frames_stay_empty():
    T = 10
    w2cs = _rig(T)
    X = torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64).expand(T, 1, 3)
    uv, z_true = _observe(X, w2cs)
    vis = torch.zeros(T, 1, dtype=torch.bool)
    vis[2:5] = True  # three frames: fewer than min_frames=4
    prior = z_true[:, 0] * 1.2
    z, solved = smooth_trajectory_depths(uv, vis, _depth_maps(T, prior), K.expand(T, 3, 3), w2cs, 2.0, 1e-3)
    assert not bool(solved[0])
    torch.testing.assert_close(z[2:5, 0], prior[2:5])
    assert bool((z[~vis[:, 0], 0] == 0).all())


def test_ratio_map_spreads_the_nearest_tracks_ratio_over_the_mask_only():
    T = 1
    mask = torch.zeros(T, 6, 8, dtype=torch.bool)
    mask[0, :, :4] = True
    tracks = torch.tensor([[[0.0, 0.0], [7.0, 0.0]]])  # one in the mask's corner, one outside (x > 3.5)
    ratio = torch.tensor([[2.0, 0.5]], dtype=torch.float64)
    has = torch.tensor([[True, True]])
    out = ratio_map(mask, tracks, ratio, has, k=1)
    assert bool((out[0, :, 4:] == 1).all())
    assert bool((out[0, :, :4] == 2.0).all())  # k=1: every mask pixel (x <= 3) is nearer (0, 0)
    two = ratio_map(mask, tracks, ratio, has, k=2)
    # Inverse-distance weights 1 / (d + 1) computed by hand at pixel (x=0, y=0): d = 0 and 7.
    w0, w1 = 1.0, 1.0 / 8.0
    assert float(two[0, 0, 0]) == pytest.approx((2.0 * w0 + 0.5 * w1) / (w0 + w1))


def _relative(frames: torch.Tensor, X: torch.Tensor, w2cs: torch.Tensor, factor: float):
    """Pixels ``[K, 2]`` of one world path ``X`` [T, 3] at ``frames`` and its depths divided by ``factor``."""
    uv, depth = _observe(X[:, None], w2cs)
    return uv[frames, 0], depth[frames, 0] / factor


@pytest.mark.parametrize("frames", [list(range(20)), [0, 1, 3, 4, 7, 8, 9, 13, 14, 18]])
def test_scale_of_a_constant_velocity_object_is_exact_where_the_cameras_turn(frames):
    T = 20
    w2cs = _rig(T)
    t = torch.arange(T, dtype=torch.float64)[:, None]
    X = torch.tensor([-0.2, 0.05, 1.5], dtype=torch.float64) + t * torch.tensor([0.02, -0.005, 0.01])
    f = torch.tensor(frames)
    uv, rel = _relative(f, X, w2cs, factor=0.37)
    s, fit = trajectory_scale(f, uv, rel, K.expand(T, 3, 3), w2cs)
    assert s == pytest.approx(0.37, rel=1e-9)
    assert fit == pytest.approx(1.0, abs=1e-9)


def test_scale_matches_a_brute_force_search_on_a_curved_noisy_path():
    T = 20
    w2cs = _rig(T)
    t = torch.arange(T, dtype=torch.float64)
    X = torch.stack([0.3 * torch.cos(0.4 * t), 0.1 * torch.sin(0.4 * t), 1.6 + 0.2 * torch.sin(0.4 * t)], -1)
    f = torch.arange(T)
    uv, rel = _relative(f, X, w2cs, factor=1.0)
    rel = rel * (1 + 0.03 * torch.sin(7.0 * t))  # size-like relative depths, 3 % off
    s, fit = trajectory_scale(f, uv, rel, K.expand(T, 3, 3), w2cs)
    # brute force: the sum of squared second differences of c + s q r on a fine grid of s
    Kinv = torch.linalg.inv(K)
    R, tr = w2cs[:, :3, :3], w2cs[:, :3, 3]
    c = -(R.transpose(1, 2) @ tr[..., None])[..., 0]
    pix = torch.cat([uv, torch.ones(T, 1, dtype=uv.dtype)], 1)
    rays = (R.transpose(1, 2) @ (Kinv @ pix[..., None]))[..., 0]
    grid = torch.linspace(0.2, 3.0, 28001, dtype=torch.float64)
    P = c[None] + grid[:, None, None] * (rel[:, None] * rays)[None]
    cost = ((P[:, 2:] - 2 * P[:, 1:-1] + P[:, :-2]) ** 2).sum((1, 2))
    assert s == pytest.approx(float(grid[cost.argmin()]), abs=2e-4)
    assert 0.0 < fit < 1.0


def test_cameras_at_constant_velocity_leave_the_scale_unmeasured():
    T = 12
    w2cs = torch.eye(4, dtype=torch.float64).repeat(T, 1, 1)
    w2cs[:, 0, 3] = -0.1 * torch.arange(T, dtype=torch.float64)  # a straight row at constant speed
    t = torch.arange(T, dtype=torch.float64)
    X = torch.stack([0.3 * torch.sin(0.8 * t), 0.05 * t, 1.5 + 0.1 * torch.cos(0.8 * t)], -1)  # accelerating
    f = torch.arange(T)
    uv, rel = _relative(f, X, w2cs, factor=2.0)
    s, fit = trajectory_scale(f, uv, rel, K.expand(T, 3, 3), w2cs)
    assert fit < 1e-6  # whatever s says, nothing supports it


@pytest.mark.parametrize("case", ["two_frames", "zero_depth", "nan_depth", "at_rest_cameras"])
def test_scale_refuses_degenerate_input(case):
    T = 6
    w2cs = torch.eye(4, dtype=torch.float64).repeat(T, 1, 1)
    if case != "at_rest_cameras":
        w2cs[:, 0, 3] = -0.1 * torch.arange(T, dtype=torch.float64) ** 2
    f = torch.arange(T)
    uv = torch.full((T, 2), 30.0, dtype=torch.float64)
    rel = torch.ones(T, dtype=torch.float64)
    if case == "two_frames":
        f, uv, rel = f[:2], uv[:2], rel[:2]
    elif case == "zero_depth":
        rel[3] = 0.0
    elif case == "nan_depth":
        rel[3] = float("nan")
    s, fit = trajectory_scale(f, uv, rel, K.expand(T, 3, 3), w2cs)
    assert math.isnan(s) and fit == 0.0
