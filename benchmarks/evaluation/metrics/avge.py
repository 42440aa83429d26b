"""AVGE (mip-NeRF's average error): geometric mean of ``10^(-PSNR/10)``, ``sqrt(1 - SSIM)`` and LPIPS."""

from __future__ import annotations

import numpy as np


def avge(psnr, ssim, lpips):
    """AVGE of arrays or scalars (broadcast) -> float64 array; NaN in any input gives NaN.

    ``10^(-PSNR/10)`` is the MSE on [0, 1]; PSNR = +inf gives 0. ``1 - SSIM`` is clamped at 0 so that a
    rounding SSIM of 1 + 1e-16 cannot give a NaN square root. The cube root is the real one (``np.cbrt``),
    so the value is defined for any sign of LPIPS (LPIPS v0.1 heads are non-negative, random test weights
    need not be).
    """
    psnr, ssim, lpips = (np.asarray(v, dtype=np.float64) for v in (psnr, ssim, lpips))
    with np.errstate(over="ignore", invalid="ignore"):
        mse = np.power(10.0, -psnr / 10.0)
        return np.cbrt(mse * np.sqrt(np.clip(1.0 - ssim, 0.0, None)) * lpips)
