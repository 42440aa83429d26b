"""Neighbour coupling (``worldtree.stages.frame_coupling``): a textured blob translated between two frames.
The carried frame-0 picture matches image 1 exactly at the true motion, worse at any other, its gradient
agrees with finite differences, and only the motion receives gradient."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from worldtree.dynamic import DynamicGaussians
from worldtree.gaussians import GaussianSet
from worldtree.motion.regularizers import MotionLossConfig
from worldtree.motion.scaffold import ScaffoldConfig, build_scaffold
from worldtree.render import rasterize
from worldtree.stages.frame_coupling import carried_frame, neighbour
from worldtree.stages.photometric import PhotometricConfig, PhotometricFit

W, H = 40, 30
SHIFT = torch.tensor([0.15, 0.05, 0.0])  # the blob's true motion from frame 0 to frame 1 (world units)
K = torch.tensor([[36.0, 0, (W - 1) / 2], [0, 36.0, (H - 1) / 2], [0, 0, 1]])


def _blob_scene(dtype=torch.float32):
    """Textured background sheet at z ~ 4, a textured blob at z ~ 2.5 that translates by SHIFT; both frames
    seen by the same camera. Returns (images [2, H, W, 3], static, blob Gaussians at frame 0)."""
    g = torch.Generator().manual_seed(3)
    n_s, n_d = 250, 50
    xy = (torch.rand(n_s, 2, generator=g) - 0.5) * torch.tensor([4.6, 3.4])
    static = GaussianSet.from_tensors(
        torch.cat([xy, 4.0 + 0.3 * torch.rand(n_s, 1, generator=g)], 1).to(dtype),
        torch.full((n_s, 3), 0.12, dtype=dtype),
        torch.full((n_s,), 0.9, dtype=dtype),
        torch.rand(n_s, 3, generator=g).to(dtype),
    )
    blob = torch.randn(n_d, 3, generator=g) * torch.tensor([0.15, 0.12, 0.04]) + torch.tensor([-0.1, 0, 2.5])
    blob_col = torch.rand(n_d, 3, generator=g)  # textured: a pure colour would not show a small slide
    dyn = DynamicGaussians.from_points_at(blob.to(dtype), blob_col.to(dtype), torch.zeros(n_d, dtype=torch.long),
                                          init_opacity=0.95, time_std=1.0)  # fmt: skip
    with torch.no_grad():
        dyn.params["log_scales"].fill_(float(np.log(0.045)))
        for v in dyn.params.values():
            if v.is_floating_point():
                v.data = v.data.to(dtype)
    imgs = []
    with torch.no_grad():
        for t in range(2):
            m = torch.cat([static.means, dyn.means + t * SHIFT.to(dtype)])
            q = torch.cat([static.quats, dyn.quats])
            ls = torch.cat([static.log_scales, dyn.log_scales])
            o = torch.cat([static.opacities, dyn.opacities])
            c = torch.cat([static.colors, dyn.colors])
            imgs.append(
                rasterize(m, q, ls, o, c, K.to(dtype), torch.eye(4, dtype=dtype), W, H).rgb.clamp(0, 1)
            )
    return torch.stack(imgs), static, dyn, blob


def _scaffold(blob: torch.Tensor, moved: torch.Tensor, dtype=torch.float32):
    """Scaffold of the blob points that translate by ``moved`` between the two frames."""
    pts = blob.to(dtype)
    traj = torch.stack([pts, pts + moved.to(dtype)])
    return build_scaffold(traj, torch.ones(2, len(pts), dtype=torch.bool), 2.5, ScaffoldConfig(knn_k=6))


def _fit(imgs, static, dyn, scf) -> PhotometricFit:
    cfg = PhotometricConfig(steps=10, lambda_couple=1.0, lambda_depth=0.0, track_every=0)
    depth = torch.full(imgs.shape[:3], 3.0)
    w2cs = torch.eye(4)[None].repeat(2, 1, 1)
    return PhotometricFit(cfg, imgs, depth, K[None].repeat(2, 1, 1), w2cs, static, dyn, scf, None, None, 1.0)


def test_neighbour_alternates_and_stays_inside():
    assert [neighbour(3, 6, k) for k in range(4)] == [4, 2, 4, 2]
    assert {neighbour(0, 6, k) for k in range(3)} == {1} and {neighbour(5, 6, k) for k in range(3)} == {4}


def test_coupling_is_zero_at_the_true_motion_and_grows_away_from_it():
    imgs, static, dyn, blob = _blob_scene()
    losses = {}
    for frac in (0.0, 0.5, 1.0, 1.5):
        fit = _fit(imgs, static, dyn, _scaffold(blob, frac * SHIFT))
        with torch.no_grad():
            losses[frac] = float(fit.coupling_loss(0, 1))
    # At the true motion the carried blob is the blob of image 1 (same Gaussians, same renderer): ~0 up to
    # float rounding; any other motion leaves part of it in the wrong place (the blob covers ~6% of the image).
    assert losses[1.0] < 1e-4, losses
    assert losses[0.0] > losses[0.5] > 20 * max(losses[1.0], 1e-6), losses
    assert losses[1.5] > 20 * max(losses[1.0], 1e-6), losses


def test_only_the_motion_receives_gradient_and_frame_js_own_gaussians_are_left_out():
    imgs, static, dyn, blob = _blob_scene()
    fit = _fit(imgs, static, dyn, _scaffold(blob, 0.5 * SHIFT))
    fit.coupling_loss(0, 1).backward()
    assert fit.scaffold.pos.grad is not None and float(fit.scaffold.pos.grad[1].abs().sum()) > 0
    for gs in (static, dyn):
        for name in ("means", "sh0", "opacity_logits", "log_scales", "quats"):
            grad = gs.params[name].grad
            assert grad is None or float(grad.abs().sum()) == 0.0, name
    # A Gaussian of frame 1 itself is not carried (the scaffold would not move it at frame 1).
    n_s = len(static)
    with torch.no_grad():
        dyn.params["t_ref"][:5] = 1
    got = carried_frame(static, dyn, fit.scaffold, 0, 1, dyn.attach(fit.scaffold))
    assert got is not None and got[0].shape[0] == n_s + len(dyn) - 5


def test_coupling_gradient_matches_finite_differences():
    dt = torch.float64
    imgs, static, dyn, blob = _blob_scene(dt)
    scf = _scaffold(blob, 0.6 * SHIFT, dt)
    cache = dyn.attach(scf)

    def loss_now() -> torch.Tensor:
        m, q, ls, o, c = carried_frame(static, dyn, scf, 0, 1, cache)
        out = rasterize(m, q, ls, o, c, K.to(dt), torch.eye(4, dtype=dt), W, H, backend="reference")
        return (out.rgb - imgs[1]).abs().mean()

    def loss_moved(delta: torch.Tensor) -> float:  # every node's frame-1 position moved by ``delta``
        with torch.no_grad():
            scf.pos[1] += delta
            v = float(loss_now())
            scf.pos[1] -= delta
        return v

    loss_now().backward()
    auto = scf.pos.grad[1].sum(0)  # d loss / d (common shift of every node at frame 1)
    eps = 1e-5
    fd = torch.tensor([(loss_moved(eps * e) - loss_moved(-eps * e)) / (2 * eps) for e in torch.eye(3, dtype=dt)],
                      dtype=dt)  # fmt: skip
    torch.testing.assert_close(auto, fd, rtol=1e-4, atol=1e-8)
    # The gradient points towards the true motion (the blob sits 40% short of it along SHIFT).
    assert float((auto * SHIFT.to(dt)).sum()) < 0


def test_the_coupling_alone_pulls_a_short_motion_towards_the_true_one():
    imgs, static, dyn, blob = _blob_scene()
    scf = _scaffold(blob, 0.6 * SHIFT)
    # The RGB term and the motion regularisers off (at frame 1 the faded carried blob would pull the motion
    # too; with two frames the velocity term pulls it to rest), the coupling every step: the scaffold moves
    # only because of it.
    cfg = PhotometricConfig(steps=40, lambda_rgb=0.0, lambda_couple=1.0, couple_every=1, lambda_depth=0.0,
                            track_every=0, lr_node_pos=3e-3, camera_start_step=10_000,
                            motion=MotionLossConfig(0.0, 0.0, 0.0, 0.0, 0.0, 0.0))  # fmt: skip
    depth = torch.full(imgs.shape[:3], 3.0)
    fit = PhotometricFit(cfg, imgs, depth, K[None].repeat(2, 1, 1), torch.eye(4)[None].repeat(2, 1, 1),
                         static, dyn, scf, None, None, 1.0)  # fmt: skip

    def moved() -> float:  # mean node motion from frame 0 to 1, as a fraction of SHIFT
        with torch.no_grad():
            return float((fit.scaffold.pos[1] - fit.scaffold.pos[0]).mean(0) @ SHIFT) / float(SHIFT @ SHIFT)

    before = moved()
    for step in range(1, cfg.steps + 1):
        fit.training_step(step).loss.backward()
        for opt in (fit.static_opt, fit.dyn_opt, fit.other_opt):
            opt.set_step(step)
            opt.step()
            opt.zero_grad()
    after = moved()
    assert before == pytest.approx(0.6, abs=1e-4)
    assert after > 0.85, (before, after)
