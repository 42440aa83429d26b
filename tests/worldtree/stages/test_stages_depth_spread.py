"""The depth-spread term of the photometric fit against closed forms and an uncentred float64 computation."""

from __future__ import annotations

import torch

from tests.worldtree.stages.test_stages_photometric import scene
from worldtree.render import rasterize
from worldtree.stages.photometric import PhotometricConfig, PhotometricFit, relative_depth_variance


def _two_layers(z1: float, z2: float, o1: float, o2: float, z_ref: float):
    """Two Gaussians on the optical axis of a 9x9 camera; the rendered centred moments at the centre pixel."""
    K = torch.tensor([[20.0, 0, 4.0], [0, 20.0, 4.0], [0, 0, 1]], dtype=torch.float64)
    means = torch.tensor([[0.0, 0.0, z1], [0.0, 0.0, z2]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=torch.float64)
    log_scales = torch.full((2, 3), -1.0, dtype=torch.float64)
    c = means[:, 2] / z_ref - 1.0
    cols = torch.stack([c, c * c, torch.zeros_like(c)], 1)
    out = rasterize(means, quats, log_scales, torch.tensor([o1, o2], dtype=torch.float64), cols, K,
                    torch.eye(4, dtype=torch.float64), 9, 9, backend="reference")  # fmt: skip
    return out.rgb[4:5, 4:5, :2], out.alpha[4:5, 4:5]


def test_two_layers_closed_form():
    z1, z2, o1, o2 = 2.0, 3.0, 0.6, 0.5
    moments, alpha = _two_layers(z1, z2, o1, o2, z_ref=2.4)
    w1, w2 = o1, (1 - o1) * o2  # front-to-back weights at the centre pixel (Gaussian value 1 there)
    assert abs(float(alpha) - (w1 + w2)) < 1e-9
    mean = (w1 * z1 + w2 * z2) / (w1 + w2)
    var = (w1 * z1**2 + w2 * z2**2) / (w1 + w2) - mean**2
    got = relative_depth_variance(moments, alpha)
    assert abs(float(got) - var / mean**2) < 1e-9


def test_one_surface_has_no_spread_whatever_the_reference_depth():
    for z_ref in (0.5, 2.0, 40.0):
        moments, alpha = _two_layers(2.0, 2.0, 0.6, 0.5, z_ref)
        assert abs(float(relative_depth_variance(moments, alpha))) < 1e-12


def test_transparent_pixels_give_none_and_nothing_non_finite():
    assert relative_depth_variance(torch.zeros(4, 4, 2), torch.zeros(4, 4)) is None
    alpha = torch.tensor([[0.6, 1e-9]], requires_grad=True)
    moments = torch.tensor([[[0.1, 0.02], [0.0, 0.0]]], requires_grad=True)
    v = relative_depth_variance(moments, alpha)
    v.backward()
    assert torch.isfinite(v) and torch.isfinite(alpha.grad).all() and torch.isfinite(moments.grad).all()


def test_fit_term_equals_an_uncentred_float64_computation():
    imgs, depth, Ks, w2cs, static, dyn, scf = scene()
    fit = PhotometricFit(PhotometricConfig(steps=1), imgs, depth, Ks, w2cs, static, dyn, scf, None, None, 1.0)
    i = 2
    frame = fit.gaussians_at(i)
    got = fit.depth_spread_loss(i, frame)
    assert got is not None
    got = float(got.detach())
    # Brute force: the same Gaussians in float64 with raw z and z^2 as colours, no centring.
    m, q, ls, o, _ = (x.detach().double() for x in frame)
    w2c = fit.camera(i).detach().double()
    z = m @ w2c[2, :3] + w2c[2, 3]
    out = rasterize(m, q, ls, o, torch.stack([z, z * z, torch.zeros_like(z)], 1), Ks[i].double(), w2c,
                    imgs.shape[2], imgs.shape[1], backend="reference")  # fmt: skip
    keep = out.alpha > 0.5
    a = out.alpha[keep]
    ez, ez2 = out.rgb[..., 0][keep] / a, out.rgb[..., 1][keep] / a
    want = ((ez2 - ez * ez).clamp_min(0) / (ez * ez)).mean()
    assert abs(got - float(want)) < 1e-4 * max(float(want), 1e-3)
    # The scene has an object in front of a background sheet with depth jitter: a spread exists.
    assert float(want) > 0


def test_the_term_joins_the_loss_on_its_steps_only():
    imgs, depth, Ks, w2cs, static, dyn, scf = scene()
    cfg = PhotometricConfig(steps=1, lambda_depth_spread=2.0, depth_spread_every=3)
    fit = PhotometricFit(cfg, imgs, depth, Ks, w2cs, static, dyn, scf, None, None, 1.0)
    _, parts3, _ = fit.frame_losses(1, 3)
    _, parts4, _ = fit.frame_losses(1, 4)
    assert "spread" in parts3 and parts3["spread"] > 0
    assert "spread" not in parts4
