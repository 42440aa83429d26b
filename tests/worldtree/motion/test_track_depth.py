"""Depths of moving points from smooth trajectories, against the points' known depths."""

from __future__ import annotations

import math

import pytest
import torch

from worldtree.motion.track_depth import ratio_map, smooth_trajectory_depths

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
