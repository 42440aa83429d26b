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
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from worldtree.pixels import unit_float

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


@dataclass(frozen=True)
class SsimTarget:
    """The SSIM statistics of a fixed target image, which do not change while a prediction is optimised.

    A training frame is compared with a new render at every step; its blurred mean and second moment are
    computed once per frame (:func:`ssim_target`) instead of once per step (5 of the 15 blurred channels of an
    RGB pair). Tensors are ``[B, C, H - w + 1, W - w + 1]``.
    """

    image: torch.Tensor
    """``[B, C, H, W]`` the target in channels-first layout (detached)."""
    mu: torch.Tensor
    """Gaussian-blurred target."""
    sq: torch.Tensor
    """Gaussian-blurred squared target."""
    window_size: int
    sigma: float


@torch.no_grad()
def ssim_target(img: torch.Tensor, window_size: int = SSIM_WINDOW, sigma: float = 1.5) -> SsimTarget:
    """:class:`SsimTarget` of a ``[(B,) H, W, C]`` target image (no gradient flows into the target)."""
    y = _to_nchw(img.detach())
    _check_window(y, window_size)
    g = _gauss_1d(window_size, sigma).to(device=y.device, dtype=y.dtype)
    n = y.shape[1]
    both = _blur(torch.cat([y, y * y], dim=1), g)
    return SsimTarget(y.contiguous(), both[:, :n].contiguous(), both[:, n:].contiguous(), window_size, sigma)


class SsimTargets:
    """:class:`SsimTarget` of each frame of a fixed ``[T, H, W, C]`` image stack, computed on first use and
    kept (about twice the stack's memory once every frame was used)."""

    def __init__(self, images: torch.Tensor, window_size: int = SSIM_WINDOW, sigma: float = 1.5):
        self.images, self.window_size, self.sigma = images, int(window_size), float(sigma)
        self._done: dict[int, SsimTarget] = {}

    def __getitem__(self, i: int) -> SsimTarget:
        i = int(i)
        if i not in self._done:
            self._done[i] = ssim_target(unit_float(self.images[i]), self.window_size, self.sigma)
        return self._done[i]

    def __len__(self) -> int:
        """Frames whose statistics are held."""
        return len(self._done)

    def clear(self) -> None:
        """Drop every frame's statistics (recomputed on the next use): a fit that has finished training keeps
        rendering for the stages after it, and at 160 frames of 480x270 the statistics are ~0.75 GB."""
        self._done.clear()


def _check_window(x: torch.Tensor, window_size: int) -> None:
    if x.shape[2] < window_size or x.shape[3] < window_size:
        raise ValueError(
            f"SSIM needs images of at least {window_size}x{window_size}, got {tuple(x.shape[2:])}"
        )


def _ssim_from_moments(mu_x, mu_y, sxx_raw, syy_raw, sxy_raw, data_range: float) -> torch.Tensor:
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    sxx = sxx_raw - mu_x * mu_x
    syy = syy_raw - mu_y * mu_y
    sxy = sxy_raw - mu_x * mu_y
    num = (2.0 * mu_x * mu_y + c1) * (2.0 * sxy + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (sxx + syy + c2)  # >= c1 * c2 > 0 up to rounding
    return num / den


def ssim_map(
    img1: torch.Tensor,
    img2: torch.Tensor | SsimTarget,
    window_size: int = SSIM_WINDOW,
    sigma: float = 1.5,
    data_range: float = 1.0,
) -> torch.Tensor:
    """SSIM map over the valid region: ``[B, C, H - w + 1, W - w + 1]`` for inputs ``[(B,) H, W, C]``.

    ``img2`` may be an :class:`SsimTarget` (a fixed target's cached statistics; its window and sigma are used):
    the same map, up to float rounding, with only the prediction's three channels blurred.
    """
    x = _to_nchw(img1)
    if isinstance(img2, SsimTarget):
        if img2.image.shape != x.shape:
            raise ValueError(
                f"SSIM of images with different shapes {tuple(x.shape)} vs {tuple(img2.image.shape)} (NCHW)"
            )
        y = img2.image.to(x.dtype)
        g = _gauss_1d(img2.window_size, img2.sigma).to(device=x.device, dtype=x.dtype)
        n = x.shape[1]
        own = _blur(torch.cat([x, x * x, x * y], dim=1), g)
        mu_y, sq_y = img2.mu.to(x.dtype), img2.sq.to(x.dtype)
        return _ssim_from_moments(own[:, :n], mu_y, own[:, n : 2 * n], sq_y, own[:, 2 * n :], data_range)
    if img1.shape != img2.shape:
        raise ValueError(f"SSIM of images with different shapes {tuple(img1.shape)} vs {tuple(img2.shape)}")
    y = _to_nchw(img2)
    _check_window(x, window_size)
    g = _gauss_1d(window_size, sigma).to(device=x.device, dtype=x.dtype)
    mu_x, mu_y = _blur(x, g), _blur(y, g)
    # One blurring pass for the three second moments keeps the graph small.
    n = x.shape[1]
    second = _blur(torch.cat([x * x, y * y, x * y], dim=1), g)
    return _ssim_from_moments(mu_x, mu_y, second[:, :n], second[:, n : 2 * n], second[:, 2 * n :], data_range)


def ssim(
    img1: torch.Tensor, img2: torch.Tensor | SsimTarget, window_size: int = SSIM_WINDOW, sigma: float = 1.5
) -> torch.Tensor:
    """Mean SSIM (scalar tensor) of two ``[(B,) H, W, C]`` images in [0, 1]; differentiable in both (in the
    first only when ``img2`` is a cached :class:`SsimTarget`)."""
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
