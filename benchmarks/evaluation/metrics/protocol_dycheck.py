"""The `dycheck` protocol: DyCheck / Shape of Motion / MoSca scores (masked by co-visibility or dynamic masks).

Images are quantised to uint8 first, then scored on [0, 1] in RGB order. Formulas: docs/evaluation.md.
"""

from __future__ import annotations

from typing import Any

import torch

from benchmarks.evaluation.metrics.protocols import Protocol
from benchmarks.evaluation.metrics.psnr import masked_psnr, psnr
from benchmarks.evaluation.metrics.ssim import ssim_gaussian_masked


def masked_map_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``sum(v * m) / sum(m)`` per frame: ``values`` [B, H, W], ``mask`` bool [B, H, W] -> [B]; empty -> NaN."""
    m = mask.to(torch.float64)
    count = m.flatten(1).sum(1)
    total = (values.to(torch.float64) * m).flatten(1).sum(1)
    return torch.where(count > 0, total / count.clamp_min(1.0), torch.full_like(total, float("nan")))


class DycheckProtocol(Protocol):
    name = "dycheck"
    version = "1"
    summary = (
        "DyCheck / Shape of Motion: uint8-quantised, [0,1] RGB; Gaussian 11x11 SSIM with partial-convolution "
        "mask; LPIPS-alex v0.1 map of black-masked images averaged over the mask"
    )

    min_side = 11

    def settings(self) -> dict[str, Any]:
        return {
            "quantisation": "uint8, then /255",
            "psnr": "-10*log10(mean((a-b)^2)) on [0,1]",
            "ssim": "Gaussian 11 taps sigma 1.5, K1=0.01, K2=0.03, data_range=1, population covariance, "
            "'valid' borders, variances clipped >=0, |cov| <= sqrt(var_a var_b), mean of the map",
            "lpips": "AlexNet v0.1 spatial map (layer maps bilinearly upsampled, align_corners=False), "
            "input 2x-1 in RGB order, mean over the image",
            "mpsnr": "-10*log10(sum(m (a-b)^2) / (3 sum m))",
            "mssim": "as ssim, each local mean a separable partial convolution (W then H; count-renormalised); "
            "map mean over all valid positions",
            "mlpips": "LPIPS map of a*m and b*m (black outside the mask), sum(map*m)/sum(m)",
            "empty_mask": "masked metrics NaN",
        }

    def _score(self, pred, gt, mask, lpips) -> dict[str, torch.Tensor]:
        x = pred.permute(0, 3, 1, 2).to(torch.float64) / 255.0
        y = gt.permute(0, 3, 1, 2).to(torch.float64) / 255.0
        out = {"psnr": psnr(pred, gt, 255.0), "ssim": ssim_gaussian_masked(x, y, None, 1.0)}
        if lpips is not None:
            out["lpips"] = lpips.distance_map((2 * x - 1).float(), (2 * y - 1).float()).mean(dim=(1, 2))
        if mask is None:
            return out
        out["mpsnr"] = masked_psnr(pred, gt, mask, 255.0)
        out["mssim"] = ssim_gaussian_masked(x, y, mask, 1.0)
        if lpips is not None:
            m = mask[:, None].to(torch.float64)
            lmap = lpips.distance_map((2 * x * m - 1).float(), (2 * y * m - 1).float())
            out["mlpips"] = masked_map_mean(lmap, mask)
        return out
