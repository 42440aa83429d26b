"""CUDA paths: the reference on the GPU against the CPU, and gsplat against the reference. Skipped without CUDA."""

from __future__ import annotations

import pytest
import torch

from worldtree.render import rasterize
from worldtree.render.backends import gsplat_available

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
needs_gsplat = pytest.mark.skipif(not gsplat_available(), reason="needs the gsplat package")
KEYS = ("means", "quats", "log_scales", "opacities", "colors", "w2c", "background")


def _on_cuda(p):
    return {k: v.detach().cuda().requires_grad_(v.requires_grad) for k, v in p.items()}


def test_reference_on_cuda_matches_cpu(make_scene):
    p, w, h = make_scene(n=200, width=50, height=40, seed=1, log_scale=-2.3, dtype=torch.float32)
    cpu = rasterize(width=w, height=h, backend="reference", **p)
    (cpu.rgb.sum() + cpu.alpha.sum()).backward()
    q = _on_cuda(p)
    gpu = rasterize(width=w, height=h, backend="reference", **q)
    (gpu.rgb.sum() + gpu.alpha.sum()).backward()
    assert (gpu.rgb.cpu() - cpu.rgb).abs().max() < 1e-5
    for k in KEYS:
        assert (q[k].grad.cpu() - p[k].grad).norm() / p[k].grad.norm() < 1e-3, k


@needs_gsplat
def test_gsplat_matches_reference(make_scene):
    # Opacities <= 0.9 keep alpha under both caps (0.99 here, 0.999 in gsplat).
    p, w, h = make_scene(n=300, width=64, height=48, seed=0, log_scale=-2.5, dtype=torch.float32)
    with torch.no_grad():
        p["opacities"].clamp_(max=0.9)
    outs = {}
    for backend in ("reference", "gsplat"):
        q = _on_cuda(p)
        out = rasterize(width=w, height=h, backend=backend, **q)
        assert out.backend == backend
        (out.rgb.sum() + 0.5 * out.alpha.sum() + 0.1 * out.depth.sum()).backward()
        outs[backend] = (out, {k: q[k].grad for k in KEYS}, out.means2d.grad)
    (ref, g_ref, m_ref), (gs, g_gs, m_gs) = outs["reference"], outs["gsplat"]
    assert (gs.rgb - ref.rgb).abs().max() < 1e-3
    assert (gs.alpha - ref.alpha).abs().max() < 1e-3
    assert (gs.depth - ref.depth).abs().max() < 1e-3 * ref.depth.abs().max()
    assert torch.equal(gs.visible, ref.visible)
    # Culled rows' means2d are undefined (the reference writes 0, gsplat the projection): compare drawn ones.
    vis = ref.visible
    assert vis.sum() > 30
    assert torch.allclose(gs.means2d[vis], ref.means2d[vis], atol=1e-3)
    for k in KEYS:
        rel = (g_gs[k] - g_ref[k]).norm() / g_ref[k].norm()
        assert rel < 1e-2, f"{k}: {rel:.2e}"
    assert (m_gs - m_ref).norm() / m_ref.norm() < 1e-2
