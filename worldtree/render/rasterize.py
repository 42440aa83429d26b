"""The public rasterizer entry point: projection, then tile compositing, by the chosen backend."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from worldtree.render.backends import resolve_backend
from worldtree.render.projection import project_gaussians


@dataclass
class RenderOutput:
    """One rendered view and the per-Gaussian statistics densification needs."""

    rgb: Tensor  # [H, W, 3] composited colour over the background
    alpha: Tensor  # [H, W] accumulated opacity, 1 - final transmittance
    depth: Tensor  # [H, W] alpha-weighted camera z (world units), not divided by alpha
    means2d: Tensor  # [N, 2] projected centres in pixels; .grad = dL/dmean2d after backward
    radii: Tensor  # [N] int32 screen radius in pixels, 0 = culled
    visible: Tensor  # [N] bool, radii > 0
    backend: str  # backend that produced the image: "cpu", "reference" or "gsplat"


def rasterize(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    K: Tensor,
    w2c: Tensor,
    width: int,
    height: int,
    background: Tensor | None = None,
    backend: str = "auto",
    *,
    near: float = 0.01,
    eps2d: float = 0.3,
) -> RenderOutput:
    """Render Gaussians into one pinhole view, differentiably; see :mod:`worldtree.render` for the contract.

    means [N, 3], quats [N, 4] (w, x, y, z), log_scales [N, 3], opacities [N] in [0, 1], colors [N, 3],
    K [3, 3], w2c [4, 4] OpenCV world-to-camera, width/height in pixels, background [3] (None = black).
    All tensors must share one device; K, w2c and background are cast to the dtype of ``means``.
    """
    _check_shapes(means, quats, log_scales, opacities, colors, K, w2c, width, height, background)
    dev, dt = means.device, means.dtype
    K = K.to(device=dev, dtype=dt)
    w2c = w2c.to(device=dev, dtype=dt)
    bg = torch.zeros(3, device=dev, dtype=dt) if background is None else background.to(device=dev, dtype=dt)
    chosen = resolve_backend(backend, dev, dt)

    # Non-finite opacity or colour culls the Gaussian; the stand-in zeros keep its gradients zero and finite.
    # (Per colour column: isfinite(colors).all(-1) is a slow reduction over 3 values on the CPU.)
    keep = torch.isfinite(opacities)
    for j in range(colors.shape[1]):
        keep = keep & torch.isfinite(colors[:, j])
    if chosen == "cpu" and bool(keep.all()):
        # Nothing to replace (the usual case): where() would copy both tensors and add two nodes to the graph,
        # a few tenths of a millisecond per frame on the CPU (keep.all() costs no device sync there).
        opac, cols = opacities, colors
    else:
        opac = torch.where(keep, opacities, torch.zeros_like(opacities))
        cols = torch.where(keep[:, None], colors, torch.zeros_like(colors))
    if chosen == "gsplat":
        from worldtree.render.gsplat_backend import rasterize_gsplat

        rgb, alpha, depth, means2d, radii = rasterize_gsplat(
            means, quats, log_scales, opac, cols, K, w2c, width, height, bg, keep, near, eps2d
        )
        return RenderOutput(rgb, alpha, depth, means2d, radii, radii > 0, chosen)

    if chosen == "cpu":
        from worldtree.render.cpu_kernel import project_cpu
        from worldtree.render.cpu_kernel import rasterize_cpu as raster

        means2d, conics, depths, radii = project_cpu(
            means, quats, log_scales, K, w2c, width, height, near, eps2d, keep
        )
    else:
        from worldtree.render.reference import rasterize_reference as raster

        proj = project_gaussians(
            means, quats, log_scales, K, w2c, width, height, near=near, eps2d=eps2d, keep=keep
        )
        means2d, conics, depths, radii = proj.means2d, proj.conics, proj.depths, proj.radii
    if means2d.requires_grad:
        means2d.retain_grad()
    rgb, alpha, depth = raster(means2d, conics, opac, cols, depths, radii, bg, width, height)
    return RenderOutput(
        rgb=rgb,
        alpha=alpha,
        depth=depth,
        means2d=means2d,
        radii=radii,
        visible=radii > 0,
        backend=chosen,
    )


def _check_shapes(means, quats, log_scales, opacities, colors, K, w2c, width, height, background) -> None:
    n = means.shape[0] if means.dim() == 2 else -1
    expected = {
        "means": (means, (n, 3)),
        "quats": (quats, (n, 4)),
        "log_scales": (log_scales, (n, 3)),
        "opacities": (opacities, (n,)),
        "colors": (colors, (n, 3)),
        "K": (K, (3, 3)),
        "w2c": (w2c, (4, 4)),
    }
    if background is not None:
        expected["background"] = (background, (3,))
    for name, (t, shape) in expected.items():
        if not isinstance(t, Tensor) or tuple(t.shape) != shape:
            got = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(f"rasterize: {name} must have shape {list(shape)}, got {got}")
    if not means.is_floating_point():
        raise ValueError(f"rasterize: means must be floating point, got {means.dtype}")
    for name, t in (
        ("quats", quats),
        ("log_scales", log_scales),
        ("opacities", opacities),
        ("colors", colors),
    ):
        if t.dtype != means.dtype or t.device != means.device:
            raise ValueError(
                f"rasterize: {name} is {t.dtype} on {t.device} but means is {means.dtype} on {means.device}; "
                "pass every per-Gaussian tensor with one dtype and device"
            )
    if int(width) < 1 or int(height) < 1:
        raise ValueError(f"rasterize: width and height must be >= 1, got {width}x{height}")
