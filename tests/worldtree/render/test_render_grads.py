"""Analytic gradients (hand-written C++ backward and reference autograd) against central finite differences."""

from __future__ import annotations

import pytest
import torch

from worldtree.render import cpu_kernel, rasterize

BACKENDS = [
    "reference",
    pytest.param("cpu", marks=pytest.mark.skipif(not cpu_kernel.available(), reason="no build")),
]
KEYS = ("means", "quats", "log_scales", "opacities", "colors", "w2c", "background")


def _loss(p, w, h, backend, weights):
    out = rasterize(width=w, height=h, backend=backend, **p)
    wr, wa, wd = weights
    return (out.rgb * wr).sum() + (out.alpha * wa).sum() + (out.depth * wd).sum(), out


NO_BUILD = pytest.mark.skipif(not cpu_kernel.available(), reason="no build")


# The reference is slower per call, so it gets one scene; the hand-written backward gets two.
@pytest.mark.parametrize(
    "backend,seed",
    [("reference", 0), pytest.param("cpu", 0, marks=NO_BUILD), pytest.param("cpu", 1, marks=NO_BUILD)],
)
def test_gradients_match_finite_differences(make_scene, backend, seed):
    # Few, large, semi-transparent Gaussians on a small image that spans several tiles (float64).
    p, w, h = make_scene(n=6, width=21, height=18, seed=seed, log_scale=-1.6, spread=0.3, opacity_lo=0.3)
    g = torch.Generator().manual_seed(seed + 10)
    weights = (
        torch.rand(h, w, 3, generator=g, dtype=torch.float64),
        torch.rand(h, w, generator=g, dtype=torch.float64),
        0.2 * torch.rand(h, w, generator=g, dtype=torch.float64),
    )
    loss, out = _loss(p, w, h, backend, weights)
    assert out.visible.all() and out.alpha.max() > 0.5
    loss.backward()
    eps = 1e-6
    for k in KEYS:
        analytic = p[k].grad
        numeric = torch.zeros_like(analytic)
        flat = p[k].detach().view(-1)
        rows = 12 if k == "w2c" else flat.numel()  # pose: the 3x4 upper block of the 4x4 matrix
        with torch.no_grad():
            for i in range(rows):
                old = float(flat[i])
                flat[i] = old + eps
                lp, _ = _loss(p, w, h, backend, weights)
                flat[i] = old - eps
                lm, _ = _loss(p, w, h, backend, weights)
                flat[i] = old
                numeric.view(-1)[i] = (lp - lm) / (2 * eps)
        if k == "w2c":
            analytic = analytic[:3]
            numeric = numeric[:3]
        scale = numeric.abs().max()
        assert scale > 0, k
        err = (analytic - numeric).abs().max() / scale
        assert err < 1e-4, f"{backend} {k}: max error {err:.2e} of the largest component {scale:.3g}"


@pytest.mark.parametrize("backend", BACKENDS)
def test_pose_gradient_in_se3_tangent(make_scene, backend):
    """d loss / d xi for w2c(xi) = exp(xi^) w2c, analytic (through the 4x4 gradient) vs finite differences."""
    p, w, h = make_scene(n=8, width=24, height=20, seed=4, log_scale=-1.7, spread=0.3)
    base = p["w2c"].detach().clone()

    def hat(xi):
        v, om = xi[:3], xi[3:]
        m = torch.zeros(4, 4, dtype=xi.dtype)
        m[0, 1], m[0, 2], m[1, 2] = -om[2], om[1], -om[0]
        m[1, 0], m[2, 0], m[2, 1] = om[2], -om[1], om[0]
        m[:3, 3] = v
        return m

    def loss_at(xi):
        q = dict(p)
        q["w2c"] = torch.linalg.matrix_exp(hat(xi)) @ base
        out = rasterize(width=w, height=h, backend=backend, **q)
        return out.rgb.sum() + 0.5 * out.alpha.sum()

    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    loss_at(xi).backward()
    eps = 1e-6
    numeric = torch.zeros(6, dtype=torch.float64)
    with torch.no_grad():
        for i in range(6):
            d = torch.zeros(6, dtype=torch.float64)
            d[i] = eps
            numeric[i] = (loss_at(d) - loss_at(-d)) / (2 * eps)
    assert numeric.abs().max() > 1e-3
    assert torch.allclose(xi.grad, numeric, rtol=1e-5, atol=1e-6 * numeric.abs().max())


@pytest.mark.parametrize("backend", BACKENDS)
def test_means2d_grad_is_the_screen_space_gradient(make_scene, backend):
    """means2d.grad equals the gradient of the compositing w.r.t. the 2D centres (moving one centre by FD)."""
    from worldtree.render.projection import project_gaussians
    from worldtree.render.reference import rasterize_reference

    p, w, h = make_scene(n=5, width=20, height=20, seed=2, log_scale=-1.6, spread=0.3)
    out = rasterize(width=w, height=h, backend=backend, **p)
    out.rgb.sum().backward()
    with torch.no_grad():
        proj = project_gaussians(p["means"], p["quats"], p["log_scales"], p["K"], p["w2c"], w, h)
        eps = 1e-6

        def loss_at(m):
            args = (proj.conics, p["opacities"], p["colors"], proj.depths, proj.radii, p["background"], w, h)
            return rasterize_reference(m, *args)[0].sum()

        for i in range(5):
            for c in range(2):
                m = proj.means2d.clone()
                m[i, c] += eps
                lp = loss_at(m)
                m[i, c] -= 2 * eps
                lm = loss_at(m)
                fd = (lp - lm) / (2 * eps)
                assert abs(float(out.means2d.grad[i, c]) - float(fd)) < 1e-5 * max(1.0, abs(float(fd)))
