"""The `worldtree` protocol: the NVIDIA evaluation of the WorldTree / MoSca / DynamicNeRF authors, quirks kept.

Their script reads images with OpenCV (BGR order, uint8) and never converts to RGB, so LPIPS sees BGR
images and the masked-SSIM vectors interleave B, G, R; both are reproduced. Formulas: docs/evaluation.md.
"""

from __future__ import annotations

from typing import Any

import torch

from benchmarks.evaluation.metrics.protocols import Protocol, lpips_input
from benchmarks.evaluation.metrics.psnr import masked_psnr, psnr
from benchmarks.evaluation.metrics.ssim import ssim_box, ssim_box_1d

# Value written outside the mask in both images before masked LPIPS (white).
FILL = 255


class WorldTreeProtocol(Protocol):
    name = "worldtree"
    version = "1"
    summary = (
        "authors' NVIDIA protocol: uint8, PSNR (peak 255), scikit-image default SSIM, LPIPS-alex v0.1 on BGR; "
        "masked: PSNR/SSIM of the masked values, LPIPS of white-filled images"
    )
    # scikit-image needs >= 7 samples for its 7-sample window: 3 pixels x 3 channels.
    min_mask_pixels = 3
    min_side = 7

    def settings(self) -> dict[str, Any]:
        return {
            "quantisation": "uint8",
            "psnr": "10*log10(255^2/MSE), MSE over all H*W*3 values",
            "ssim": "skimage.metrics.structural_similarity defaults: 7x7 uniform window, sample covariance, "
            "K1=0.01, K2=0.03, data_range=255, channel mean",
            "lpips": "AlexNet v0.1, input x/127.5-1 in BGR channel order (OpenCV-read, as the authors)",
            "mask_fill": FILL,
            "mpsnr": "PSNR of the vector of masked values (3 per masked pixel)",
            "mssim": "skimage SSIM defaults on the 1-D vectors of masked values, raster order, B,G,R per pixel "
            "(7-sample window, sample covariance, data_range=255)",
            "mlpips": "LPIPS of both images with pixels outside the mask set to 255",
            "empty_mask": "masked metrics NaN",
        }

    def _score(self, pred, gt, mask, lpips) -> dict[str, torch.Tensor]:
        p = pred.permute(0, 3, 1, 2)
        g = gt.permute(0, 3, 1, 2)
        out = {"psnr": psnr(pred, gt, 255.0), "ssim": ssim_box(p, g, 255.0)}
        if lpips is not None:
            out["lpips"] = lpips.distance(lpips_input(p.flip(1)), lpips_input(g.flip(1)))
        if mask is None:
            return out
        out["mpsnr"] = masked_psnr(pred, gt, mask, 255.0)
        # Masked values in the order the authors' `img_bgr[mask3]` produces them.
        values = torch.stack([gt.flip(-1)[mask].reshape(-1), pred.flip(-1)[mask].reshape(-1)])
        out["mssim"] = ssim_box_1d(values, mask.flatten(1).sum(1) * 3, 255.0)
        if lpips is not None:
            m = mask[:, None]
            pw = torch.where(m, p, torch.full_like(p, FILL))
            gw = torch.where(m, g, torch.full_like(g, FILL))
            out["mlpips"] = lpips.distance(lpips_input(pw.flip(1)), lpips_input(gw.flip(1)))
        return out
