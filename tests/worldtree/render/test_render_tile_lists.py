"""The compiled kernel's tile lists: a Gaussian is listed in a tile only where some pixel of it can composite.

The kernel bins by the reach box (the pixels where alpha >= 1/255 is possible) instead of the 3-sigma bounding
square; the Gaussians it leaves out must be ones that no pixel of the tile would composite. Checked against a
brute-force float64 evaluation of alpha at every pixel, and the images and gradients against the reference.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from worldtree.render import cpu_kernel, rasterize
from worldtree.render.projection import TILE, project_gaussians, tile_rect

pytestmark = pytest.mark.skipif(not cpu_kernel.available(), reason="C++ rasterizer did not build here")

GRAD_KEYS = ("means", "quats", "log_scales", "opacities", "colors", "w2c", "background")


def _faint_scene(make_scene, dtype):
    """Opacities from 0.002 (below 1/255: never composited) to 1 and stretched shapes: the reach box is often
    much smaller than the bounding square."""
    p, w, h = make_scene(n=400, width=70, height=53, seed=21, log_scale=-2.3, spread=0.7, dtype=dtype)
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        p["opacities"].copy_(
            torch.exp(torch.empty(400, dtype=dtype).uniform_(np.log(0.002), 0.0, generator=g))
        )
        p["log_scales"][:, 0] -= 1.0  # thin along one axis
    return p, w, h


def _lists(p, w, h):
    """(listed pairs, bounding-square pairs, pairs a pixel needs) as sets of (tile, Gaussian)."""
    proj = project_gaussians(p["means"], p["quats"], p["log_scales"], p["K"], p["w2c"], w, h)
    m2d, con, radii = proj.means2d.detach(), proj.conics.detach(), proj.radii
    opac, cols, z = p["opacities"].detach(), p["colors"].detach(), proj.depths.detach()
    out = cpu_kernel._load().forward(
        m2d.contiguous(), con.contiguous(), opac, cols, z.contiguous(), radii.to(torch.int32),
        p["background"].detach(), w, h, 1,
    )  # fmt: skip
    ids, start, count = out[5], out[6], out[7]
    tw = (w + TILE - 1) // TILE
    listed = {(t, int(ids[s + k])) for t in range(len(start)) for s, c in [(int(start[t]), int(count[t]))]
              for k in range(c)}  # fmt: skip
    x0, x1, y0, y1 = tile_rect(m2d, radii, w, h)
    square = {(ty * tw + tx, g) for g in range(len(radii)) if radii[g] > 0
              for ty in range(int(y0[g]), int(y1[g])) for tx in range(int(x0[g]), int(x1[g]))}  # fmt: skip
    # Brute force, float64: a pixel composites Gaussian g when power <= 0 and min(0.99, o exp(power)) >= 1/255.
    m, c, o = m2d.double().numpy(), con.double().numpy(), opac.double().numpy()
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    needed = set()
    for g in np.flatnonzero(radii.numpy() > 0):
        dx, dy = xx - m[g, 0], yy - m[g, 1]
        power = -0.5 * (c[g, 0] * dx * dx + c[g, 2] * dy * dy) - c[g, 1] * dx * dy
        alpha = np.minimum(0.99, o[g] * np.exp(power))
        for i, j in zip(*np.nonzero((power <= 0) & (alpha >= 1.0 / 255.0)), strict=True):
            needed.add(((i // TILE) * tw + j // TILE, int(g)))
    return listed, square, needed


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_lists_hold_every_needed_pair_and_drop_others(make_scene, dtype):
    p, w, h = _faint_scene(make_scene, dtype)
    listed, square, needed = _lists(p, w, h)
    assert needed <= listed  # no pixel loses a Gaussian it composites
    assert listed <= square  # nothing outside the bounding square is added
    # The saving is real on this scene (faint and thin Gaussians), and the faintest are never listed.
    assert len(listed) < 0.8 * len(square)
    faint = set(torch.nonzero(p["opacities"].detach() < 1.0 / 255.0).flatten().tolist())
    assert faint and not any(g in faint for _, g in listed)


def test_shorter_lists_keep_images_and_gradients(make_scene):
    """float64: the kernel with its shorter lists equals the reference (which lists by the square) tightly."""
    p, w, h = _faint_scene(make_scene, torch.float64)
    res = {}
    for backend in ("reference", "cpu"):
        for k in GRAD_KEYS:
            p[k].grad = None
        out = rasterize(width=w, height=h, backend=backend, **p)
        g = torch.Generator().manual_seed(4)
        loss = (out.rgb * torch.rand(out.rgb.shape, generator=g, dtype=torch.float64)).sum()
        loss = loss + (out.alpha * torch.rand(out.alpha.shape, generator=g, dtype=torch.float64)).sum()
        loss = loss + 0.3 * (out.depth * torch.rand(out.depth.shape, generator=g, dtype=torch.float64)).sum()
        loss.backward()
        res[backend] = (out, {k: p[k].grad.clone() for k in GRAD_KEYS})
    (ref, g_ref), (cpu, g_cpu) = res["reference"], res["cpu"]
    assert ref.alpha.mean() > 0.2
    for name in ("rgb", "alpha", "depth"):
        assert (getattr(cpu, name) - getattr(ref, name)).abs().max() < 1e-12, name
    for k, gr in g_ref.items():
        assert gr.norm() > 0, k
        assert torch.allclose(g_cpu[k], gr, rtol=1e-9, atol=1e-12), k
