"""The compiled CPU kernel against the PyTorch reference: images and autograd gradients."""

from __future__ import annotations

import pytest
import torch

from worldtree.render import cpu_kernel, kernel_build, rasterize

pytestmark = pytest.mark.skipif(not cpu_kernel.available(), reason="C++ rasterizer did not build here")

GRAD_KEYS = ("means", "quats", "log_scales", "opacities", "colors", "w2c", "background")


def _render_and_grads(p, w, h, backend, seed=7):
    for k in GRAD_KEYS:
        p[k].grad = None
    out = rasterize(width=w, height=h, backend=backend, **p)
    g = torch.Generator().manual_seed(seed)
    dt = out.rgb.dtype
    loss = (
        (out.rgb * torch.rand(out.rgb.shape, generator=g, dtype=dt)).sum()
        + (out.alpha * torch.rand(out.alpha.shape, generator=g, dtype=dt)).sum()
        + (out.depth * torch.rand(out.depth.shape, generator=g, dtype=dt)).sum() * 0.3
    )
    loss.backward()
    grads = {k: p[k].grad.clone() for k in GRAD_KEYS}
    grads["means2d"] = out.means2d.grad.clone()
    return out, grads


@pytest.fixture(params=["native", "avx2", "portable"])
def kernel_target(request):
    """Each build target in turn (SIMD vectors sized for this CPU, for AVX2 (8 floats), for SSE2 (4 floats))."""
    if not kernel_build.runs_here(request.param):
        pytest.skip(f"this CPU cannot run the {request.param} build")
    try:
        previous = cpu_kernel.use_target(request.param)
    except Exception as e:  # a target this compiler cannot build: the other one still runs
        pytest.skip(f"{request.param} build failed here: {e}")
    yield request.param
    if previous is not None:
        cpu_kernel.use_target(previous)


@pytest.mark.parametrize(
    "seed,n,size,log_scale",
    [(0, 300, (64, 48), -2.5), (1, 200, (37, 23), -2.0), (2, 500, (100, 70), -3.0), (3, 60, (16, 16), -1.0)],
)
def test_forward_and_grads_match_reference(make_scene, kernel_target, seed, n, size, log_scale):
    p, w, h = make_scene(
        n=n, width=size[0], height=size[1], seed=seed, log_scale=log_scale, dtype=torch.float32
    )
    ref, g_ref = _render_and_grads(p, w, h, "reference")
    cpu, g_cpu = _render_and_grads(p, w, h, "cpu")
    assert cpu.backend == "cpu" and ref.backend == "reference"
    assert cpu_kernel.loaded_target() == kernel_target
    assert ref.alpha.mean() > 0.3  # a scene that really exercises compositing
    assert (cpu.rgb - ref.rgb).abs().max() < 1e-5
    assert (cpu.alpha - ref.alpha).abs().max() < 1e-5
    assert (cpu.depth - ref.depth).abs().max() < 1e-5 * ref.depth.abs().max()
    assert torch.equal(cpu.radii, ref.radii)
    for k, gr in g_ref.items():
        rel = (g_cpu[k] - gr).norm() / gr.norm().clamp_min(1e-12)
        assert gr.norm() > 0, k
        assert rel < 1e-3, f"{k}: relative gradient error {rel:.2e}"


def test_float64_matches_reference_tightly(make_scene, kernel_target):
    p, w, h = make_scene(n=150, width=45, height=38, seed=5, dtype=torch.float64)
    ref, g_ref = _render_and_grads(p, w, h, "reference")
    cpu, g_cpu = _render_and_grads(p, w, h, "cpu")
    assert (cpu.rgb - ref.rgb).abs().max() < 1e-12
    for k, gr in g_ref.items():
        assert torch.allclose(g_cpu[k], gr, rtol=1e-9, atol=1e-12), k


def test_threads_do_not_change_results(make_scene):
    """Per-(tile, Gaussian) gradient slots make the backward deterministic whatever the thread count."""
    p, w, h = make_scene(n=300, width=70, height=50, seed=9, dtype=torch.float32)
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        o1, g1 = _render_and_grads(p, w, h, "cpu")
        torch.set_num_threads(2)
        o2, g2 = _render_and_grads(p, w, h, "cpu")
    finally:
        torch.set_num_threads(old)
    assert torch.equal(o1.rgb, o2.rgb)
    for k in g1:
        assert torch.equal(g1[k], g2[k]), k


def test_saturated_pile_matches_reference(make_scene):
    """Thousands of opaque layers: most pixels stop early (T < 1e-4), exercising the stop and the backward walk."""
    p, w, h = make_scene(n=2000, width=24, height=20, seed=12, log_scale=-2.0, spread=0.15, opacity_lo=0.6)
    p = {k: (v.detach().float().requires_grad_(v.requires_grad)) for k, v in p.items()}
    ref, g_ref = _render_and_grads(p, w, h, "reference")
    cpu, g_cpu = _render_and_grads(p, w, h, "cpu")
    assert (1 - ref.alpha).min() < 2e-4 and (ref.alpha > 0.999).float().mean() > 0.2  # really saturated
    assert (cpu.rgb - ref.rgb).abs().max() < 1e-5
    assert (cpu.alpha - ref.alpha).abs().max() < 1e-5
    for k, gr in g_ref.items():
        rel = (g_cpu[k] - gr).norm() / gr.norm().clamp_min(1e-12)
        assert rel < 1e-3, f"{k}: relative gradient error {rel:.2e}"
