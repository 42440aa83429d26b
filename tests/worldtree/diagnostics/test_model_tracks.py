"""Tracks read off a fitted model: positions against the known motion, occlusion, the temporal window."""

from __future__ import annotations

import math

import torch

from worldtree.diagnostics.model_tracks import model_tracks, pick_gaussians
from worldtree.dynamic import DynamicGaussians
from worldtree.gaussians import GaussianSet
from worldtree.motion.scaffold import ScaffoldConfig, build_scaffold

T, W, H, F = 4, 64, 64, 100.0
STEP = -0.4  # world units per frame along x


def _scene(device, time_std: float = 0.0):
    """A cluster of points at depth 5 translating along -x behind (from frame 2 on) an opaque static wall
    that covers the left part of the image at depth 2; one camera at the origin for every frame."""
    g = torch.Generator().manual_seed(0)
    x0 = torch.rand(40, 3, generator=g) * torch.tensor([0.3, 0.3, 0.2]) + torch.tensor([0.3, -0.15, 5.0])
    shift = torch.tensor([STEP, 0.0, 0.0]) * torch.arange(T, dtype=torch.float32)[:, None]
    traj = (x0[None] + shift[:, None]).to(device)  # [T, N, 3]
    scaffold = build_scaffold(traj, torch.ones(T, 40, dtype=torch.bool, device=device), 5.0,
                              ScaffoldConfig(node_spacing_units=1.0))  # fmt: skip
    t_ref = torch.arange(40, device=device) % T
    pts = traj[t_ref, torch.arange(40, device=device)]
    dyn = DynamicGaussians.from_points_at(pts, torch.full_like(pts, 0.5), t_ref, init_opacity=0.9,
                                          time_std=time_std)  # fmt: skip
    with torch.no_grad():
        dyn.params["log_scales"].fill_(math.log(0.01))
    gx, gy = torch.meshgrid(torch.linspace(-0.8, -0.05, 16), torch.linspace(-0.8, 0.8, 32), indexing="ij")
    wall_pts = torch.stack([gx.flatten(), gy.flatten(), torch.full((gx.numel(),), 2.0)], 1).to(device)
    wall = GaussianSet.from_points(wall_pts, torch.zeros_like(wall_pts), init_opacity=0.99)
    K = torch.tensor([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]], device=device)
    return traj, scaffold, dyn, wall, K.expand(T, 3, 3), torch.eye(4, device=device).expand(T, 4, 4)


def test_tracks_follow_the_motion_and_hide_behind_the_wall(device):
    traj, scaffold, dyn, wall, Ks, w2cs = _scene(device)
    idx = pick_gaussians(dyn, max_tracks=1000)
    assert len(idx) == len(dyn)
    tr = model_tracks(wall, dyn, scaffold, Ks, w2cs, W, H, idx)
    # Independent: the pinhole projection of the known trajectory of each Gaussian's own point.
    p = traj[:, idx]
    expect = torch.stack([F * p[..., 0] / p[..., 2] + W / 2, F * p[..., 1] / p[..., 2] + H / 2], -1)
    assert float((tr.xy - expect).abs().max()) < 1e-3
    # The wall covers u < 32 + 50 * -0.05 = 29.5 (+ its Gaussians' spread); points project at
    # 32 + 20 x / (z / 5): frame 0 (x >= 0.3, u >= 38) is clear, frame 3 (x <= -0.6, u <= 20) is hidden.
    assert bool(tr.visible[0].all()) and not bool(tr.visible[3].any())
    # Without the wall (nothing drawn in front) every frame is visible.
    empty = GaussianSet.from_points(torch.tensor([[0.0, 0.0, 50.0]], device=device), init_opacity=0.01)
    assert bool(model_tracks(empty, dyn, scaffold, Ks, w2cs, W, H, idx).visible.all())


def test_temporal_window_and_points_behind_the_camera(device):
    traj, scaffold, dyn, wall, Ks, w2cs = _scene(device, time_std=1.0)
    empty = GaussianSet.from_points(torch.tensor([[0.0, 0.0, 50.0]], device=device), init_opacity=0.01)
    idx = torch.arange(len(dyn), device=device)
    tr = model_tracks(empty, dyn, scaffold, Ks, w2cs, W, H, idx, window=1.5)
    t = torch.arange(T, device=device)[:, None]
    assert torch.equal(tr.visible, (t - dyn.t_ref[None]).abs() <= 1)
    # A camera turned around (180 degrees about y) sees every point behind it: finite, never visible.
    back = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0], device=device)).expand(T, 4, 4)
    tb = model_tracks(empty, dyn, scaffold, Ks, back, W, H, idx)
    assert bool(torch.isfinite(tb.xy).all()) and not bool(tb.visible.any())


def test_pick_gaussians_skips_faint_ones_and_caps_the_count():
    _, _, dyn, _, _, _ = _scene("cpu")
    with torch.no_grad():
        dyn.params["opacity_logits"][:10] = -8.0
    idx = pick_gaussians(dyn, max_tracks=20, min_opacity=0.3, seed=1)
    assert len(idx) == 20 and bool((idx >= 10).all()) and torch.equal(idx, idx.sort().values)
    assert torch.equal(idx, pick_gaussians(dyn, max_tracks=20, min_opacity=0.3, seed=1))
