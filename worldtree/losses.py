"""Photometric losses: L1, differentiable SSIM and their 3DGS mix ``(1 - lambda) L1 + lambda (1 - SSIM)``.

Images are channel-last, as the rasterizer returns them: ``[H, W, C]`` or ``[B, H, W, C]``, float in [0, 1].

SSIM uses an 11x11 Gaussian window (sigma 1.5, K1 0.01, K2 0.03, population covariances) and averages the SSIM
map over the "valid" region only (pixels whose window lies inside the image) and over channels. This is
exactly ``skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
data_range=1, channel_axis=-1)``, which crops the same border before averaging; it differs slightly from the
3DGS training code, which zero-pads and averages the whole map.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

SSIM_WINDOW = 11
"""Side of the training SSIM window (pixels); training images must be at least this large."""


@functools.lru_cache(maxsize=8)
def _gauss_1d(size: int, sigma: float) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return (g / g.sum()).float()


def _to_nchw(img: torch.Tensor) -> torch.Tensor:
    if img.ndim == 3:
        img = img[None]
    if img.ndim != 4:
        raise ValueError(f"expected [H, W, C] or [B, H, W, C] images, got shape {tuple(img.shape)}")
    return img.permute(0, 3, 1, 2)


def _blur(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable 'valid' Gaussian filter of ``x [B, C, H, W]`` per channel."""
    c = x.shape[1]
    k = g.numel()
    gx = g.view(1, 1, 1, k).expand(c, 1, 1, k)
    gy = g.view(1, 1, k, 1).expand(c, 1, k, 1)
    return F.conv2d(F.conv2d(x, gx, groups=c), gy, groups=c)


def ssim_map(
    img1: torch.Tensor,
    img2: torch.Tensor,
    window_size: int = SSIM_WINDOW,
    sigma: float = 1.5,
    data_range: float = 1.0,
) -> torch.Tensor:
    """SSIM map over the valid region: ``[B, C, H - w + 1, W - w + 1]`` for inputs ``[(B,) H, W, C]``."""
    if img1.shape != img2.shape:
        raise ValueError(f"SSIM of images with different shapes {tuple(img1.shape)} vs {tuple(img2.shape)}")
    x, y = _to_nchw(img1), _to_nchw(img2)
    if x.shape[2] < window_size or x.shape[3] < window_size:
        raise ValueError(
            f"SSIM needs images of at least {window_size}x{window_size}, got {tuple(x.shape[2:])}"
        )
    g = _gauss_1d(window_size, sigma).to(device=x.device, dtype=x.dtype)
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    mu_x, mu_y = _blur(x, g), _blur(y, g)
    # One blurring pass for the three second moments keeps the graph small.
    n = x.shape[1]
    second = _blur(torch.cat([x * x, y * y, x * y], dim=1), g)
    sxx = second[:, :n] - mu_x * mu_x
    syy = second[:, n : 2 * n] - mu_y * mu_y
    sxy = second[:, 2 * n :] - mu_x * mu_y
    num = (2.0 * mu_x * mu_y + c1) * (2.0 * sxy + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (sxx + syy + c2)  # >= c1 * c2 > 0 up to rounding
    return num / den


def ssim(
    img1: torch.Tensor, img2: torch.Tensor, window_size: int = SSIM_WINDOW, sigma: float = 1.5
) -> torch.Tensor:
    """Mean SSIM (scalar tensor) of two ``[(B,) H, W, C]`` images in [0, 1]; differentiable in both."""
    return ssim_map(img1, img2, window_size, sigma).mean()


def l1(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean absolute error; with ``mask [(B,) H, W]`` (bool or weights) the mean over masked pixels."""
    err = (pred - target).abs()
    if mask is None:
        return err.mean()
    w = mask.to(err.dtype)[..., None].expand_as(err)
    return (err * w).sum() / w.sum().clamp_min(1e-8)


def photometric_loss(
    pred: torch.Tensor, target: torch.Tensor, lambda_dssim: float = 0.2
) -> tuple[torch.Tensor, dict[str, float]]:
    """3DGS image loss ``(1 - lambda) * L1 + lambda * (1 - SSIM)`` and its parts as floats for logging."""
    l1_term = l1(pred, target)
    if lambda_dssim > 0:
        s = ssim(pred, target)
        loss = (1.0 - lambda_dssim) * l1_term + lambda_dssim * (1.0 - s)
        parts = {"l1": float(l1_term.detach()), "ssim": float(s.detach())}
    else:
        loss = l1_term
        parts = {"l1": float(l1_term.detach())}
    return loss, parts


def psnr(pred: torch.Tensor, target: torch.Tensor) -> float:
    """PSNR in dB for images in [0, 1] (for progress logs; the benchmark scores with benchmarks.evaluation)."""
    mse = float(((pred.detach() - target.detach()) ** 2).mean())
    return float("inf") if mse <= 0 else -10.0 * torch.log10(torch.tensor(mse)).item()
