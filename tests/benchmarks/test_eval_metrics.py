"""PSNR, SSIM and AVGE against scikit-image, brute-force window loops and closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio as sk_psnr
from skimage.metrics import structural_similarity as sk_ssim

from benchmarks.evaluation.metrics import avge, masked_psnr, psnr, ssim_box, ssim_box_1d, ssim_gaussian_masked


def _pair(rng, h, w, noise=25):
    gt = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    pred = np.clip(gt.astype(int) + rng.integers(-noise, noise + 1, gt.shape), 0, 255).astype(np.uint8)
    return pred, gt


def _chw(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a)).permute(2, 0, 1)[None]


@pytest.mark.parametrize(("h", "w"), [(7, 7), (9, 13), (31, 20), (64, 48)])
def test_psnr_ssim_equal_skimage(h, w):
    rng = np.random.default_rng(h * 100 + w)
    pred, gt = _pair(rng, h, w)
    p = torch.from_numpy(pred)[None]
    g = torch.from_numpy(gt)[None]
    assert psnr(p, g, 255.0).item() == pytest.approx(sk_psnr(gt, pred), abs=1e-9)
    assert ssim_box(_chw(pred), _chw(gt)).item() == pytest.approx(
        sk_ssim(gt, pred, channel_axis=-1), abs=1e-6
    )


def test_batched_equals_per_frame():
    rng = np.random.default_rng(1)
    pairs = [_pair(rng, 20, 30) for _ in range(5)]
    p = torch.stack([_chw(a)[0] for a, _ in pairs])
    g = torch.stack([_chw(b)[0] for _, b in pairs])
    got = ssim_box(p, g).numpy()
    ref = [sk_ssim(b, a, channel_axis=-1) for a, b in pairs]
    np.testing.assert_allclose(got, ref, atol=1e-6)


def _brute_ssim_box(a: np.ndarray, b: np.ndarray, win=7, data_range=255.0) -> float:
    """Per-window sample statistics, every complete window, every channel; plain loops."""
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    vals = []
    for c in range(a.shape[2]):
        for i in range(a.shape[0] - win + 1):
            for j in range(a.shape[1] - win + 1):
                x = a[i : i + win, j : j + win, c].astype(np.float64).ravel()
                y = b[i : i + win, j : j + win, c].astype(np.float64).ravel()
                mx, my = x.mean(), y.mean()
                vx, vy = x.var(ddof=1), y.var(ddof=1)
                cov = ((x - mx) * (y - my)).sum() / (x.size - 1)
                vals.append(((2 * mx * my + c1) * (2 * cov + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2)))
    return float(np.mean(vals))


def test_ssim_box_equals_brute_force_windows():
    rng = np.random.default_rng(2)
    pred, gt = _pair(rng, 12, 10, noise=60)
    brute = _brute_ssim_box(pred, gt)
    assert sk_ssim(gt, pred, channel_axis=-1) == pytest.approx(brute, abs=1e-12)  # the reference holds
    # uint8 inputs: window sums are exact integers, the final products float32 (docs: within 1e-6).
    assert ssim_box(_chw(pred), _chw(gt)).item() == pytest.approx(brute, abs=1e-6)


def test_constant_images_closed_form():
    a, b = 100, 140
    x = torch.full((1, 3, 16, 16), a, dtype=torch.uint8)
    y = torch.full((1, 3, 16, 16), b, dtype=torch.uint8)
    c1 = (0.01 * 255) ** 2
    # Zero variances: the contrast-structure term is C2 / C2 = 1.
    assert ssim_box(x, y).item() == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), abs=1e-7)
    # Every value off by 40: MSE = 1600.
    assert psnr(x, y, 255.0).item() == pytest.approx(10 * math.log10(255**2 / 1600), abs=1e-12)


def test_identical_images_give_inf_psnr_and_ssim_one():
    rng = np.random.default_rng(3)
    _, gt = _pair(rng, 16, 16)
    g = torch.from_numpy(gt)[None]
    assert psnr(g, g, 255.0).item() == math.inf
    assert ssim_box(_chw(gt), _chw(gt)).item() == pytest.approx(1.0, abs=1e-12)


def test_float_inputs_use_float_path():
    rng = np.random.default_rng(4)
    pred, gt = _pair(rng, 15, 15)
    a, b = pred / 255.0, gt / 255.0
    got = ssim_box(_chw(a), _chw(b), data_range=1.0).item()
    assert got == pytest.approx(sk_ssim(b, a, channel_axis=-1, data_range=1.0), abs=1e-9)


def test_ssim_1d_equals_skimage_on_concatenated_pairs():
    rng = np.random.default_rng(5)
    lengths = [7, 8, 30, 6, 100, 3]
    xs = [rng.integers(0, 256, n, dtype=np.uint8) for n in lengths]
    ys = [np.clip(x.astype(int) + rng.integers(-40, 41, x.shape), 0, 255).astype(np.uint8) for x in xs]
    values = torch.from_numpy(np.stack([np.concatenate(xs), np.concatenate(ys)]))
    got = ssim_box_1d(values, torch.tensor(lengths)).numpy()
    for n, x, y, v in zip(lengths, xs, ys, got, strict=True):
        if n < 7:
            assert math.isnan(v)  # scikit-image refuses vectors shorter than its window
            with pytest.raises(ValueError):
                sk_ssim(x, y)
        else:
            assert v == pytest.approx(sk_ssim(x, y), abs=1e-6)


def test_masked_psnr_is_psnr_of_masked_values():
    rng = np.random.default_rng(6)
    pred, gt = _pair(rng, 20, 25)
    mask = rng.random((20, 25)) > 0.5
    got = masked_psnr(
        torch.from_numpy(pred)[None], torch.from_numpy(gt)[None], torch.from_numpy(mask)[None], 255.0
    )
    assert got.item() == pytest.approx(sk_psnr(gt[mask], pred[mask]), abs=1e-9)
    # DyCheck's form on [0, 1]: -10 log10(sum(m (a-b)^2) / (3 sum m)).
    d = (pred / 255.0 - gt / 255.0) ** 2
    dy = -10 * math.log10((d * mask[..., None]).sum() / (3 * mask.sum()))
    assert got.item() == pytest.approx(dy, abs=1e-9)
    empty = torch.zeros(1, 20, 25, dtype=torch.bool)
    assert math.isnan(
        masked_psnr(torch.from_numpy(pred)[None], torch.from_numpy(gt)[None], empty, 255.0).item()
    )


def test_dycheck_ssim_unmasked_equals_skimage_gaussian():
    rng = np.random.default_rng(7)
    pred, gt = _pair(rng, 30, 41)
    a, b = pred / 255.0, gt / 255.0
    got = ssim_gaussian_masked(_chw(a), _chw(b)).item()
    ref = sk_ssim(
        a, b, channel_axis=-1, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0
    )
    assert got == pytest.approx(ref, abs=1e-9)


def _brute_dycheck_ssim(a: np.ndarray, b: np.ndarray, m: np.ndarray) -> float:
    """DyCheck's definition with explicit loops: a row pass then a column pass of partial convolution."""
    k, half = 11, 5
    g = np.exp(-0.5 * ((np.arange(k) - half) / 1.5) ** 2)
    g /= g.sum()

    def pconv(z, mask, axis):
        z = np.moveaxis(z, axis, -1)
        mask = np.moveaxis(mask, axis, -1)
        n = z.shape[-1] - k + 1
        out = np.zeros(z.shape[:-1] + (n,))
        cnt = np.zeros(mask.shape[:-1] + (n,))
        for j in range(n):
            cnt[..., j] = mask[..., j : j + k].sum(-1)
            out[..., j] = (z[..., j : j + k] * mask[..., j : j + k] * g).sum(-1)
        res = np.where(cnt != 0, out * k / np.where(cnt == 0, 1, cnt), 0)
        return np.moveaxis(res, -1, axis), np.moveaxis((cnt != 0).astype(float), -1, axis)

    maps = []
    for c in range(3):

        def blur(z, c=c):
            z1, m1 = pconv(z, m.astype(float), 1)
            return pconv(z1, m1, 0)[0]

        x, y = a[..., c], b[..., c]
        mx, my = blur(x), blur(y)
        sxx = np.maximum(0, blur(x * x) - mx * mx)
        syy = np.maximum(0, blur(y * y) - my * my)
        sxy = blur(x * y) - mx * my
        sxy = np.sign(sxy) * np.minimum(np.sqrt(sxx * syy), np.abs(sxy))
        c1, c2 = 0.01**2, 0.03**2
        maps.append(((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2)))
    return float(np.mean(maps))


def test_dycheck_masked_ssim_equals_brute_force():
    rng = np.random.default_rng(8)
    pred, gt = _pair(rng, 24, 27, noise=50)
    a, b = pred / 255.0, gt / 255.0
    m = np.zeros((24, 27), dtype=bool)
    m[3:15, 5:20] = rng.random((12, 15)) > 0.3  # windows with no, some and many masked pixels
    got = ssim_gaussian_masked(_chw(a), _chw(b), torch.from_numpy(m)[None]).item()
    assert got == pytest.approx(_brute_dycheck_ssim(a, b, m), abs=1e-9)


def test_avge_closed_forms_and_paper_rows():
    assert avge(20.0, 0.75, 0.1) == pytest.approx((0.01 * 0.5 * 0.1) ** (1 / 3), rel=1e-12)
    assert avge(math.inf, 0.5, 0.2) == 0.0
    assert math.isnan(avge(20.0, 0.9, math.nan))
    assert avge(30.0, 1.0 + 1e-16, 0.1) == 0.0  # SSIM rounding above 1 must not give NaN
    # The paper's NVIDIA-LS means: WorldTree PSNR 24.06, SSIM 0.804, LPIPS 0.100 -> AVGE 0.056;
    # mPSNR 18.55, mSSIM 0.692 with the same LPIPS -> mAVGE 0.092.
    assert round(float(avge(24.06, 0.804, 0.100)), 3) == 0.056
    assert round(float(avge(18.55, 0.692, 0.100)), 3) == 0.092
