"""The fits of benchmarks.speed.mono_fit_check against closed forms: each model recovers the data it describes."""

import numpy as np
import pytest

from benchmarks.speed.mono_fit_check import fit_models, log_error, main, split_static

H, W = 30, 40


def _scene(seed=0):
    rng = np.random.default_rng(seed)
    y = 1.0 / rng.uniform(0.5, 2.0, (H, W))  # reference inverse depth
    fit = np.ones((H, W), bool)
    fit[10:20, 15:25] = False  # a hole, as the moving region leaves
    return y, fit


def test_affine_data_is_recovered_by_the_affine_model_only():
    y, fit = _scene()
    a, b = 0.02, 0.4
    x = (y - b) / a  # y = a x + b exactly
    x = np.where(x > 0, x, 1e-3)
    ok = x > 1e-3
    preds = fit_models(x, y, fit & ok)
    assert np.allclose(preds["affine"][ok], y[ok], rtol=1e-9)
    assert log_error(preds["scale"], y, ok) > 0.05  # a shift a scale cannot absorb


def test_proportional_data_is_recovered_by_scale_and_affine():
    y, fit = _scene(1)
    x = 37.0 * y
    preds = fit_models(x, y, fit)
    for name in ("scale", "affine", "field1", "field2"):
        assert log_error(preds[name], y, np.ones_like(fit)) < 1e-9, name


def test_a_smooth_multiplicative_field_is_recovered_inside_the_hole():
    y, fit = _scene(2)
    vv, uu = np.mgrid[0:H, 0:W]
    u, v = (uu - W / 2) / W, (vv - H / 2) / H
    x = y / np.exp(0.3 + 0.8 * u - 0.5 * v)  # log(y / x) is linear in (u, v)
    preds = fit_models(x, y, fit)
    hole = ~fit
    assert log_error(preds["field1"], y, hole) < 1e-9
    assert log_error(preds["field2"], y, hole) < 1e-6
    assert log_error(preds["scale"], y, hole) > 0.01


def test_robust_fit_ignores_gross_outliers():
    y, fit = _scene(3)
    x = 5.0 * y
    x_bad = x.copy()
    x_bad[:3, :] *= 4.0  # 10 % of the pixels wildly off
    preds = fit_models(x_bad, y, fit)
    rest = np.ones_like(fit)
    rest[:3, :] = False
    assert log_error(preds["affine"], y, rest) < 1e-6
    assert log_error(preds["scale"], y, rest) < 1e-6


def test_too_few_fit_pixels_is_an_error():
    y, _ = _scene()
    fit = np.zeros((H, W), bool)
    fit[0, :5] = True
    with pytest.raises(ValueError, match="usable fit pixels"):
        fit_models(y, y, fit)


def test_log_error_closed_form_and_empty_mask():
    y = np.full((2, 2), 2.0)
    pred = np.array([[2.0 * np.e, 2.0], [2.0 / np.e, 2.0]])
    assert log_error(pred, y, np.ones((2, 2), bool)) == pytest.approx(0.5)
    assert np.isnan(log_error(pred, y, np.zeros((2, 2), bool)))


def test_split_static_against_brute_force_distances():
    dyn = np.zeros((H, W), bool)
    dyn[12:15, 18:21] = True
    valid = np.ones((H, W), bool)
    valid[0, 0] = False
    fit, held = split_static(dyn, valid, dilate=1, holdout=5, margin=2)
    ys, xs = np.nonzero(dyn)
    for i in range(H):
        for j in range(W):
            d = np.sqrt(((ys - i) ** 2 + (xs - j) ** 2).min())
            # dilation by one 4-connected step: the cross neighbours only
            cross = ((np.abs(ys - i) + np.abs(xs - j)) <= 1).any()
            static = valid[i, j] and not cross and 2 <= j < W - 2
            assert fit[i, j] == (static and d > 5), (i, j)
            assert held[i, j] == (static and d <= 5), (i, j)


def test_cli_names_a_missing_maps_folder(tmp_path):
    with pytest.raises(SystemExit, match="--maps"):
        main([str(tmp_path), "--maps", str(tmp_path / "nope")])


def test_depth_spread_map_two_layers_closed_form():
    import torch

    from benchmarks.speed.mono_fit_check import depth_spread_map

    class Frame:  # the one method depth_spread_map reads
        def render_list(self):
            means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]])
            quats = torch.tensor([[1.0, 0, 0, 0]] * 2)
            return means, quats, torch.full((2, 3), -1.0), torch.tensor([0.6, 0.5]), torch.ones(2, 3)

    K = np.array([[20.0, 0, 4.0], [0, 20.0, 4.0], [0, 0, 1]])
    rel, alpha = depth_spread_map(Frame(), K, np.eye(4), 9, 9)
    w1, w2 = 0.6, 0.4 * 0.5  # front-to-back weights at the centre pixel
    mean = (2 * w1 + 3 * w2) / (w1 + w2)
    std = np.sqrt((4 * w1 + 9 * w2) / (w1 + w2) - mean**2)
    assert alpha[4, 4] == pytest.approx(w1 + w2, abs=1e-6)
    assert rel[4, 4] == pytest.approx(std / mean, rel=1e-6)
