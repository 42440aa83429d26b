"""Differentiable SSIM against scikit-image; the photometric loss against its formula."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from worldtree.losses import SsimTargets, l1, photometric_loss, psnr, ssim, ssim_map, ssim_target


def _sk(a: np.ndarray, b: np.ndarray) -> float:
    return structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1, channel_axis=-1
    )


@pytest.mark.parametrize("shape", [(36, 64, 3), (11, 11, 3), (23, 17, 1), (40, 29, 3)])
def test_ssim_equals_skimage(shape):
    rng = np.random.default_rng(sum(shape))
    a = rng.random(shape)
    b = np.clip(a + 0.3 * rng.standard_normal(shape), 0, 1)
    for x, y in ((a, b), (a, rng.random(shape)), (a, a * 0.5 + 0.2)):
        got = float(ssim(torch.from_numpy(x).float(), torch.from_numpy(y).float()))
        assert abs(got - _sk(x, y)) < 1e-4


def test_batched_ssim_is_mean_of_singles():
    rng = np.random.default_rng(3)
    a, b = rng.random((3, 20, 24, 3)), rng.random((3, 20, 24, 3))
    got = float(ssim(torch.from_numpy(a).float(), torch.from_numpy(b).float()))
    assert abs(got - np.mean([_sk(a[i], b[i]) for i in range(3)])) < 1e-4


def test_ssim_identity_and_gradient():
    x = torch.rand(12, 13, 1, dtype=torch.float64)
    assert abs(float(ssim(x, x)) - 1.0) < 1e-12
    y = torch.rand(12, 13, 1, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: ssim(x, t), (y,), eps=1e-6, atol=1e-6)


def test_ssim_rejects_small_or_mismatched_images():
    with pytest.raises(ValueError):
        ssim(torch.rand(10, 30, 3), torch.rand(10, 30, 3))
    with pytest.raises(ValueError):
        ssim(torch.rand(12, 12, 3), torch.rand(12, 13, 3))


def test_photometric_loss_formula_and_finite_on_constant_images():
    rng = np.random.default_rng(5)
    a, b = rng.random((20, 20, 3)), rng.random((20, 20, 3))
    ta, tb = torch.from_numpy(a).float(), torch.from_numpy(b).float()
    loss, parts = photometric_loss(ta, tb, lambda_dssim=0.2)
    expect = 0.8 * np.abs(a - b).mean() + 0.2 * (1 - _sk(a, b))
    assert abs(float(loss) - expect) < 1e-5
    assert abs(parts["l1"] - np.abs(a - b).mean()) < 1e-6
    z = torch.zeros(20, 20, 3, requires_grad=True)
    loss0, _ = photometric_loss(z, torch.zeros(20, 20, 3))
    loss0.backward()
    assert torch.isfinite(loss0) and torch.isfinite(z.grad).all()
    only_l1, parts1 = photometric_loss(ta, tb, lambda_dssim=0.0)
    assert set(parts1) == {"l1"} and abs(float(only_l1) - np.abs(a - b).mean()) < 1e-6


def test_masked_l1_and_psnr():
    a, b = torch.zeros(4, 4, 3), torch.ones(4, 4, 3)
    m = torch.zeros(4, 4, dtype=torch.bool)
    m[0, 0] = True
    b2 = b.clone()
    b2[1:] = 0
    assert float(l1(a, b2, m)) == 1.0
    assert float(l1(a, b2, torch.zeros(4, 4, dtype=torch.bool))) == 0.0
    assert abs(psnr(a, torch.full((4, 4, 3), 0.1)) - 20.0) < 1e-4
    assert psnr(a, a) == float("inf")


def test_cached_target_equals_skimage_and_the_uncached_map_and_gradient():
    rng = np.random.default_rng(11)
    a, b = rng.random((27, 35, 3)), rng.random((27, 35, 3))
    x = torch.from_numpy(a).double().requires_grad_(True)
    y = torch.from_numpy(b).double()
    target = ssim_target(y)
    got = ssim(x, target)
    assert abs(float(got.detach()) - _sk(a, b)) < 1e-6  # the window weights are float32 (as the plain path)
    torch.testing.assert_close(ssim_map(x, target), ssim_map(x, y), rtol=0, atol=1e-12)
    (g_cached,) = torch.autograd.grad(got, [x])
    (g_plain,) = torch.autograd.grad(ssim(x, y), [x])
    torch.testing.assert_close(g_cached, g_plain, rtol=0, atol=1e-12)
    # float32, as training uses it: equal within float rounding
    xf, yf = x.detach().float(), y.float()
    torch.testing.assert_close(ssim_map(xf, ssim_target(yf)), ssim_map(xf, yf), rtol=0, atol=1e-5)


def test_frame_targets_are_computed_once_and_checked():
    frames = torch.rand(3, 16, 18, 3)
    cache = SsimTargets(frames)
    assert cache[1] is cache[1]
    torch.testing.assert_close(cache[2].image[0].permute(1, 2, 0), frames[2])
    with pytest.raises(ValueError):
        ssim(torch.rand(16, 17, 3), cache[0])
    with pytest.raises(ValueError):
        ssim_target(torch.rand(10, 30, 3))
    kept = cache[2]
    assert len(cache) == 3
    cache.clear()  # dropped, then recomputed alike on the next use
    assert len(cache) == 0
    again = cache[2]
    assert again is not kept and len(cache) == 1
    torch.testing.assert_close(again.mu, ssim_target(frames[2]).mu, rtol=0, atol=0)
