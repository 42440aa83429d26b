"""PSNR, whole-image and over a mask, batched in torch.

Both take images in the same units as ``peak`` (255 for uint8 values, 1 for [0, 1] values) and compute in
float64. A zero error gives ``+inf`` (as scikit-image does); an empty mask gives NaN. Callers decide how
those enter means (see docs/evaluation.md).
"""

from __future__ import annotations

import torch


def psnr_from_mse(mse: torch.Tensor, peak: float) -> torch.Tensor:
    """``10 log10(peak^2 / mse)`` elementwise; ``mse == 0`` -> ``+inf``, NaN stays NaN."""
    mse = mse.to(torch.float64)
    return 10.0 * torch.log10(peak**2 / mse)


def _squared_error(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """(pred - gt)^2 elementwise: exact int32 for uint8 inputs, else float64."""
    if pred.dtype == torch.uint8 and gt.dtype == torch.uint8:
        return (pred.to(torch.int32) - gt.to(torch.int32)).square()
    return (pred.to(torch.float64) - gt.to(torch.float64)).square()


def psnr(pred: torch.Tensor, gt: torch.Tensor, peak: float) -> torch.Tensor:
    """PSNR per image: ``pred``, ``gt`` [B, ...] -> [B] dB, MSE over every value of each image."""
    sq = _squared_error(pred, gt).flatten(1)
    return psnr_from_mse(sq.sum(1, dtype=torch.float64) / sq.shape[1], peak)


def masked_psnr(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor, peak: float) -> torch.Tensor:
    """PSNR over masked pixels: ``pred``, ``gt`` [B, H, W, C]; ``mask`` bool [B, H, W] -> [B] dB.

    ``mse = sum(m * (a - b)^2) / (C * sum(m))``: the mean over the C values of every masked pixel, which is
    both the authors' PSNR of the masked value vectors and DyCheck's masked mean. Empty mask -> NaN.
    """
    sq = _squared_error(pred, gt).sum(-1)  # [B, H, W]
    count = mask.flatten(1).sum(1).to(torch.float64) * pred.shape[-1]
    mse = (sq * mask).flatten(1).sum(1, dtype=torch.float64) / count.clamp_min(1.0)
    return torch.where(count > 0, psnr_from_mse(mse, peak), torch.full_like(mse, float("nan")))
