"""Differentiable Gaussian rasterizer: one public function, several backends.

Contract (shared with the trainer; the implementation lives in this package's modules):

    rasterize(means, quats, log_scales, opacities, colors, K, w2c, width, height,
              background=None, backend="auto") -> RenderOutput

    means      [N, 3]  world positions
    quats      [N, 4]  rotations, (w, x, y, z), any norm (normalised inside)
    log_scales [N, 3]  log of the per-axis standard deviations (world units)
    opacities  [N]     activated opacities in [0, 1]
    colors     [N, 3]  RGB in [0, 1]
    K          [3, 3]  pixel intrinsics;  w2c [4, 4] OpenCV world-to-camera (differentiable)
    background [3]     RGB, default black

    RenderOutput.rgb [H, W, 3], .alpha [H, W], .depth [H, W] (alpha-weighted camera z, not normalised),
    .means2d [N, 2] (pixels; after backward, .means2d.grad holds dL/dmean2d for densification),
    .radii [N] (int pixels, 0 = culled), .visible [N] bool, .backend str
"""
