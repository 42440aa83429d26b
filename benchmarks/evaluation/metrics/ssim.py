"""SSIM variants used by the protocols, batched in torch, computed in float64.

- :func:`ssim_box`: scikit-image ``structural_similarity`` with its defaults (7x7 uniform window, sample
  covariance, K1 0.01, K2 0.03, mean over the window-complete interior, channels averaged).
- :func:`ssim_box_1d`: the same defaults on 1-D vectors (a 7-sample window), as scikit-image computes
  for a 1-D input; used for the authors' masked SSIM of flattened masked values.
- :func:`ssim_gaussian_masked`: DyCheck's SSIM (11-tap Gaussian, sigma 1.5, population covariance,
  'valid' borders, mask applied as a separable partial convolution).
"""

from __future__ import annotations

import math

import torch

K1 = 0.01
K2 = 0.03


def _window_sums(x: torch.Tensor, k: int, dim: int) -> torch.Tensor:
    """Sums over every complete length-``k`` window along ``dim`` ('valid': size shrinks by k - 1).

    Shifted adds rather than a cumulative sum: partial sums never exceed the window total, so sums of
    integer values below 2^24 stay exact in float32.
    """
    n = x.shape[dim] - k + 1
    acc = x.narrow(dim, 0, n).clone()
    for i in range(1, k):
        acc += x.narrow(dim, i, n)
    return acc


def _ssim_from_sums(sx, sy, sxx, syy, sxy, n: int, data_range: float) -> torch.Tensor:
    """scikit-image's SSIM map (sample covariance) from window sums over ``n`` samples.

    Written as ``(2 P + C1 n^2)(2 (n Sxy - P) + C2 n (n-1)) / ((Q + C1 n^2)(n (Sxx + Syy) - Q + C2 n (n-1)))``
    with ``P = Sx Sy``, ``Q = Sx^2 + Sy^2``: scikit-image's ``(2 ux uy + C1)(2 vxy + C2) / ...`` with both
    factors multiplied by ``n^2`` and ``n (n - 1)``. Integer sums (from uint8 images) keep every difference
    exact in integers, so the float32 products that follow err by a few 1e-8 relative per position;
    float sums are combined in float64.
    """
    c1 = (K1 * data_range) ** 2 * n * n
    c2 = (K2 * data_range) ** 2 * n * (n - 1)
    p = sx * sy
    q = sx * sx + sy * sy
    dxy = n * sxy - p
    dsum = n * (sxx + syy) - q
    if not sx.dtype.is_floating_point:
        p, q, dxy, dsum = (t.to(torch.float32) for t in (p, q, dxy, dsum))
    return ((2 * p + c1) * (2 * dxy + c2)) / ((q + c1) * (dsum + c2))


def _moment_sums(x: torch.Tensor, y: torch.Tensor, n: int, sums) -> list[torch.Tensor]:
    """Window sums (over ``n`` samples) of x, y, x^2, y^2, xy.

    uint8 inputs: summed in float32, exact because every partial sum is an integer below 2^24, then
    turned into int32 (int64 if ``n`` is large enough for ``2 n^2 255^2`` to overflow int32). Other
    inputs: float64.
    """
    exact = x.dtype == torch.uint8 and y.dtype == torch.uint8 and n * 255**2 < 2**24
    work = torch.float32 if exact else torch.float64
    xf, yf = x.to(work), y.to(work)
    s = sums(torch.stack([xf, yf, xf * xf, yf * yf, xf * yf]))
    if exact:
        s = s.round().to(torch.int32 if 2 * n * n * 255**2 < 2**31 else torch.int64)
    return list(s)


def ssim_box(x: torch.Tensor, y: torch.Tensor, data_range: float = 255.0, win: int = 7) -> torch.Tensor:
    """scikit-image default SSIM per image: ``x``, ``y`` [B, C, H, W] (H, W >= win) -> [B].

    Equals ``structural_similarity(a, b, channel_axis=-1, data_range=data_range)`` for each pair: box
    window ``win`` x ``win``, covariances scaled by ``N / (N - 1)`` with ``N = win^2``, the map averaged
    over the positions whose window lies inside the image (scikit-image's crop of ``(win - 1) // 2``), then
    averaged over channels. uint8 inputs are summed exactly (integers); float inputs in float64.
    """
    if min(x.shape[-2:]) < win:
        raise ValueError(f"image {tuple(x.shape[-2:])} is smaller than the {win}x{win} SSIM window")
    n = win * win
    s = _moment_sums(x, y, n, lambda z: _window_sums(_window_sums(z, win, -1), win, -2))
    return _ssim_from_sums(*s, n, data_range).mean(dim=(2, 3), dtype=torch.float64).mean(1)


def ssim_box_1d(
    values: torch.Tensor, lengths: torch.Tensor, data_range: float = 255.0, win: int = 7
) -> torch.Tensor:
    """scikit-image default SSIM of 1-D vector pairs, batched as one concatenation.

    ``values`` [2, N]: row 0 the first vectors, row 1 the second, all pairs concatenated; ``lengths`` [B]
    (int) the length of each pair's vectors, summing to N. Returns [B]: per pair, the mean over the
    ``length - win + 1`` complete windows of scikit-image's SSIM map (``N = win`` samples, sample
    covariance). A pair shorter than ``win`` gives NaN (scikit-image refuses it).
    """
    lengths = lengths.to(torch.long).cpu()
    out = torch.full((len(lengths),), float("nan"), dtype=torch.float64)
    total = int(lengths.sum())
    if total < win:
        return out
    s = _moment_sums(values[0], values[1], win, lambda z: _window_sums(z, win, -1))
    smap = _ssim_from_sums(*s, win, data_range).to(torch.float64).cpu()
    # Keep windows that start and end in the same pair; average them per pair.
    seg = torch.repeat_interleave(torch.arange(len(lengths)), lengths)
    start_seg, end_seg = seg[: total - win + 1], seg[win - 1 :]
    keep = start_seg == end_seg
    sums = torch.zeros(len(lengths), dtype=torch.float64).index_add_(0, start_seg[keep], smap[keep])
    counts = (lengths - win + 1).clamp_min(0)
    ok = counts > 0
    out[ok] = sums[ok] / counts[ok]
    return out


def gaussian_taps(size: int = 11, sigma: float = 1.5) -> list[float]:
    """Normalised 1-D Gaussian weights ``exp(-0.5 ((i - size // 2) / sigma)^2)`` for odd ``size``."""
    half = size // 2
    w = [math.exp(-0.5 * ((i - half) / sigma) ** 2) for i in range(size)]
    total = sum(w)
    return [v / total for v in w]


def _weighted_window_sums(z: torch.Tensor, taps: list[float], dim: int) -> torch.Tensor:
    """``sum_i taps[i] * z[j + i]`` along ``dim`` for every complete window ('valid' convolution)."""
    n = z.shape[dim] - len(taps) + 1
    acc = z.narrow(dim, 0, n) * taps[0]
    for i in range(1, len(taps)):
        acc.add_(z.narrow(dim, i, n), alpha=taps[i])
    return acc


class _PartialBlur:
    """DyCheck's separable partial convolution for one mask, mask counts computed once.

    A pass along ``dim`` gives ``conv(z * m, taps) * len(taps) / conv(m, ones)`` where the count is
    non-zero, else 0, and hands ``count != 0`` to the next pass as its mask. The renormalisation divides
    by the COUNT of masked samples in the window (not by their Gaussian weight), as DyCheck does.
    """

    def __init__(self, m: torch.Tensor, taps: list[float]) -> None:
        k = len(taps)
        self.taps = taps
        self.m1 = m
        c1 = _window_sums(m, k, -1)
        self.scale1 = torch.where(c1 != 0, k / c1.clamp_min(1e-30), torch.zeros_like(c1))
        self.m2 = (c1 != 0).to(m.dtype)
        c2 = _window_sums(self.m2, k, -2)
        self.scale2 = torch.where(c2 != 0, k / c2.clamp_min(1e-30), torch.zeros_like(c2))

    def __call__(self, z: torch.Tensor) -> torch.Tensor:
        z1 = _weighted_window_sums(z * self.m1, self.taps, -1) * self.scale1
        return _weighted_window_sums(z1 * self.m2, self.taps, -2) * self.scale2


def ssim_gaussian_masked(
    x: torch.Tensor,
    y: torch.Tensor,
    mask: torch.Tensor | None = None,
    data_range: float = 1.0,
    size: int = 11,
    sigma: float = 1.5,
) -> torch.Tensor:
    """DyCheck SSIM: ``x``, ``y`` [B, C, H, W] in [0, data_range]; ``mask`` [B, H, W] bool or None -> [B].

    Each local mean is a partial convolution: first along W with the mask, then along H with the
    binarised count of the first pass as the mask. Variances are clipped to >= 0 and the covariance's
    magnitude to ``sqrt(var_x var_y)``; the map (population covariance, C1 = (0.01 R)^2,
    C2 = (0.03 R)^2) is averaged over every 'valid' position and channel, including positions whose window
    holds no masked pixel (they score 1). ``mask=None`` is an all-ones mask: plain Gaussian SSIM.
    """
    if min(x.shape[-2:]) < size:
        raise ValueError(f"image {tuple(x.shape[-2:])} is smaller than the {size}x{size} SSIM window")
    x = x.to(torch.float64)
    y = y.to(torch.float64)
    m = torch.ones_like(x[:, :1]) if mask is None else mask.to(torch.float64)[:, None]
    blur = _PartialBlur(m, gaussian_taps(size, sigma))

    mu0, mu1, e00, e11, e01 = blur(torch.stack([x, y, x * x, y * y, x * y]))
    s00 = (e00 - mu0 * mu0).clamp_min(0.0)
    s11 = (e11 - mu1 * mu1).clamp_min(0.0)
    s01 = e01 - mu0 * mu1
    s01 = torch.sign(s01) * torch.minimum(torch.sqrt(s00 * s11), s01.abs())
    c1 = (K1 * data_range) ** 2
    c2 = (K2 * data_range) ** 2
    ssim_map = ((2 * mu0 * mu1 + c1) * (2 * s01 + c2)) / ((mu0 * mu0 + mu1 * mu1 + c1) * (s00 + s11 + c2))
    return ssim_map.flatten(1).mean(1)
