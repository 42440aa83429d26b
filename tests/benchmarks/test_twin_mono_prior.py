"""benchmarks.speed.twin_mono_prior: the network-like disparity is an affine map of the exact inverse depth
when its errors are off, and a moving region's bias is applied to that region only."""

from __future__ import annotations

import cv2
import numpy as np

from benchmarks.speed.twin_mono_prior import write


def _scene(root):
    (root / "gt_priors" / "depth").mkdir(parents=True)
    (root / "gt_priors" / "masks").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for t in range(3):
        z = rng.uniform(2.0, 9.0, (20, 30)).astype(np.float32)
        m = np.zeros((20, 30), np.uint8)
        m[2:6, 3 + t : 8 + t] = 255
        np.save(root / "gt_priors" / "depth" / f"{t:05d}.npy", z)
        cv2.imwrite(str(root / "gt_priors" / "masks" / f"{t:05d}.png"), m)
    return root


def _affine_residual(x, y):
    A = np.stack([x.ravel(), np.ones(x.size)], 1)
    coef, *_ = np.linalg.lstsq(A, y.ravel(), rcond=None)
    return np.abs(A @ coef - y.ravel()).max() / np.abs(y).max(), coef


def test_errors_off_gives_an_affine_map_of_inverse_depth(tmp_path):
    scene = _scene(tmp_path / "s")
    write(scene, tmp_path / "d", seed=3, field=0.0, noise=0.0, object_error=0.0)
    for t in range(3):
        z = np.load(scene / "gt_priors" / "depth" / f"{t:05d}.npy").astype(np.float64)
        d = np.load(tmp_path / "d" / f"{t:05d}.npy").astype(np.float64)
        res, (a, _) = _affine_residual(1.0 / z, d)
        assert res < 1e-5 and a > 0


def test_object_bias_moves_only_the_object(tmp_path):
    scene = _scene(tmp_path / "s")
    write(scene, tmp_path / "d", seed=3, field=0.0, noise=0.0, object_error=0.3)
    z = np.load(scene / "gt_priors" / "depth" / "00000.npy").astype(np.float64)
    d = np.load(tmp_path / "d" / "00000.npy").astype(np.float64)
    obj = cv2.imread(str(scene / "gt_priors" / "masks" / "00000.png"), cv2.IMREAD_UNCHANGED) > 0
    res_bg, (a, b) = _affine_residual(1.0 / z[~obj], d[~obj])
    assert res_bg < 1e-5
    ratio = (d[obj] - b) / (a / z[obj])  # 1 + the region's bias, the same at every pixel of it
    assert np.ptp(ratio) < 1e-4 and 0.0 < abs(ratio[0] - 1.0) <= 0.3 + 1e-6
