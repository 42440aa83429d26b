"""Differentiable Gaussian rasterizer: one public function, several backends.

Contract (shared with the trainer; the implementation lives in this package's modules):

    rasterize(means, quats, log_scales, opacities, colors, K, w2c, width, height,
              background=None, backend="auto", *, near=0.01, eps2d=0.3) -> RenderOutput

    means      [N, 3]  world positions
    quats      [N, 4]  rotations, (w, x, y, z), any norm (normalised inside)
    log_scales [N, 3]  log of the per-axis standard deviations (world units)
    opacities  [N]     activated opacities in [0, 1]
    colors     [N, 3]  RGB in [0, 1]
    K          [3, 3]  pixel intrinsics (OpenCV: pixel (i, j) has its centre at u=j, v=i; skew ignored)
    w2c        [4, 4]  OpenCV world-to-camera (x right, y down, z forward); differentiable
    background [3]     RGB, default black; differentiable
    backend    "auto" | "cpu" (compiled C++/OpenMP) | "reference" (pure PyTorch) | "gsplat" (CUDA)
    near       world units; Gaussians with camera z <= near are culled
    eps2d      px^2 added to the 2D covariance diagonal (screen-space dilation)

    RenderOutput.rgb [H, W, 3], .alpha [H, W], .depth [H, W] (alpha-weighted camera z, not normalised),
    .means2d [N, 2] (pixels; after backward, .means2d.grad holds dL/dmean2d for densification),
    .radii [N] (int32 pixels, 0 = culled), .visible [N] bool, .backend str (the backend that ran)

Gradients reach means, quats, log_scales, opacities, colors, background and w2c. Culled Gaussians (behind the
near plane, off-screen, degenerate 2D covariance, non-finite parameters) contribute nothing and receive
exactly zero gradients. Image formation and formulas: docs/rendering.md.
"""

from worldtree.render.rasterize import RenderOutput, rasterize

__all__ = ["RenderOutput", "rasterize"]
