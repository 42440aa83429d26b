"""CUDA backend through gsplat's ``rasterization`` (optional dependency: ``pip install 'worldtree-bench[cuda]'``).

gsplat projects and composites in its own CUDA kernels (with pose gradients through ``viewmats``); this module
only maps conventions:

- pixel centres: this package puts pixel (i, j) at (u, v) = (j, i) (OpenCV); gsplat at (j + 0.5, i + 0.5), so
  the principal point is shifted by +0.5 px on the way in and ``means2d`` by -0.5 px on the way out;
- scales = exp(log_scales), quaternions (w, x, y, z) normalised, eps2d and near plane passed through;
- depth: render mode "RGB+D" (alpha-weighted z, not normalised); the background is composited here as
  ``rgb + (1 - alpha) bg``, which equals gsplat's own background term and keeps d/d background simple;
- Gaussians with non-finite parameters are removed before the call and reported as culled.

Known differences from the CPU backends (gsplat's classic mode): alpha is capped at 0.999 instead of 0.99 and
compositing stops when T <= 1e-4 instead of T < 1e-4. Untested on this project's CPU-only CI (see
tests/worldtree/render/test_render_gsplat.py, skipped without CUDA).
"""

from __future__ import annotations

import torch
from torch import Tensor


def rasterize_gsplat(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    K: Tensor,
    w2c: Tensor,
    width: int,
    height: int,
    background: Tensor,
    keep: Tensor,
    near: float,
    eps2d: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Render on CUDA with gsplat: rgb [H,W,3], alpha [H,W], depth [H,W], means2d [N,2], radii [N] int32.

    ``keep`` [N] bool: Gaussians to pass to gsplat (the caller's finiteness test). ``means2d.grad`` is filled
    during backward with dL/dmean2d (pixels) through a hook, as for the other backends.
    """
    import gsplat

    n = means.shape[0]
    finite = (
        keep
        & torch.isfinite(means).all(-1)
        & torch.isfinite(quats).all(-1)
        & torch.isfinite(log_scales).all(-1)
        & (quats.norm(dim=-1) > 1e-8)
    )
    idx = torch.nonzero(finite).squeeze(1)
    if len(idx) == 0:  # nothing to draw; gsplat is not asked to handle empty inputs
        bg_img = background.expand(int(height), int(width), 3) + 0.0 * means.sum()
        zeros = torch.zeros(int(height), int(width), dtype=means.dtype, device=means.device)
        return (
            bg_img,
            zeros,
            zeros.clone(),
            torch.zeros(n, 2, dtype=means.dtype, device=means.device),
            (torch.zeros(n, dtype=torch.int32, device=means.device)),
        )
    Kg = K.clone()
    Kg[0, 2] = Kg[0, 2] + 0.5
    Kg[1, 2] = Kg[1, 2] + 0.5
    q = quats[idx]
    renders, alphas, meta = gsplat.rasterization(
        means=means[idx],
        quats=q / q.norm(dim=-1, keepdim=True),
        scales=torch.exp(log_scales[idx]),
        opacities=opacities[idx],
        colors=colors[idx],
        viewmats=w2c[None],
        Ks=Kg[None],
        width=int(width),
        height=int(height),
        near_plane=float(near),
        eps2d=float(eps2d),
        packed=False,
        tile_size=16,
        render_mode="RGB+D",
        rasterize_mode="classic",
    )
    alpha = alphas[0, ..., 0]
    rgb = renders[0, ..., :3] + (1.0 - alpha)[..., None] * background
    depth = renders[0, ..., 3]

    radii_sub = meta["radii"][0]
    if radii_sub.dim() == 2:  # gsplat >= 1.5 reports per-axis radii [N, 2]
        radii_sub = radii_sub.max(dim=-1).values
    radii = torch.zeros(n, dtype=torch.int32, device=means.device)
    radii[idx] = radii_sub.to(torch.int32)

    m2d_g = meta["means2d"]  # [1, M, 2], in gsplat's pixel convention, on the autograd path
    means2d = torch.zeros(n, 2, dtype=means.dtype, device=means.device)
    means2d[idx] = m2d_g[0].detach() - 0.5
    if m2d_g.requires_grad:
        means2d.requires_grad_(True)

        def _to_full(g: Tensor) -> None:
            full = torch.zeros_like(means2d)
            full[idx] = g[0].to(full.dtype)
            means2d.grad = full if means2d.grad is None else means2d.grad + full

        m2d_g.register_hook(_to_full)
    return rgb, alpha, depth, means2d, radii
