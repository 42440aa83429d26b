"""benchmarks.speed.twin_score: the geometry and scoring helpers in closed form, and the exact views it re-casts
from a tiny generated twin against the capture's own ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.speed.twin_score import (
    Truth,
    backproject,
    depth_errors,
    erode,
    format_table,
    masked_psnr,
    medians,
    project,
    screen_errors,
)

K = np.array([[100.0, 0, 50.0], [0, 100.0, 30.0], [0, 0, 1]])


def _cam(centre) -> np.ndarray:
    """World-to-camera of an axis-aligned camera (looking along +z) at ``centre``."""
    w = np.eye(4)
    w[:3, 3] = -np.asarray(centre, float)
    return w


def test_backproject_and_project_are_inverse_and_exact():
    px = np.array([[60.0, 30.0], [50.0, 10.0]])
    X = backproject(px, np.array([2.0, 4.0]), K, _cam([0, 0, 0]))
    np.testing.assert_allclose(X, [[0.2, 0.0, 2.0], [0.0, -0.8, 4.0]])
    # A camera 1 unit to the right sees the first point 100 * 1 / 2 = 50 px further left.
    uv, z = project(X, K, _cam([1, 0, 0]))
    np.testing.assert_allclose(uv[0], [10.0, 30.0])
    np.testing.assert_allclose(z, [2.0, 4.0])
    back = backproject(uv, z, K, _cam([1, 0, 0]))
    np.testing.assert_allclose(back, X, atol=1e-12)


def test_screen_error_of_a_doubled_depth_is_the_lost_parallax():
    """A point at depth z seen from a test camera ``b`` to the side moves ``f b / z`` px; drawn at ``2 z`` it
    moves half as far, so the error is ``f b / (2 z)``; with the true depth it is 0."""
    rng = np.random.default_rng(0)
    px = np.stack([rng.uniform(40, 60, 50), rng.uniform(20, 40, 50)], 1)
    z = np.full(50, 5.0)
    train, test = (K, _cam([0, 0, 0])), (K, _cam([0.5, 0, 0]))
    c, med, um, ug = screen_errors(px, 2 * z, train, test, z, train, test)
    assert c == pytest.approx(100 * 0.5 / (2 * 5.0))
    assert med == pytest.approx(5.0)
    np.testing.assert_allclose(ug[:, 0], px[:, 0] - 10.0)
    c0, med0, _, _ = screen_errors(px, z, train, test, z, train, test)
    assert c0 == pytest.approx(0.0, abs=1e-9) and med0 == pytest.approx(0.0, abs=1e-9)
    # The model's own world may differ by a similarity: a model 3x larger with its cameras 3x further apart
    # draws the same picture, and the error stays 0.
    tr3, te3 = (K, _cam([0, 0, 0])), (K, _cam([1.5, 0, 0]))
    c3, _, _, _ = screen_errors(px, 3 * z, tr3, te3, z, train, test)
    assert c3 == pytest.approx(0.0, abs=1e-9)


def test_depth_errors_median_relative_and_signed():
    gt = np.full((4, 5), 10.0)
    pred = gt.copy()
    m = np.zeros_like(gt, bool)
    m[:2] = True
    pred[0] = 12.0  # +20 % on half the mask
    pred[1, :3] = 7.0  # -30 %
    pred[1, 3:] = 11.0  # +10 %
    pred[2:] = 1e6  # outside the mask: ignored
    err, bias = depth_errors(pred, gt, m)
    assert err == pytest.approx(np.median([0.2] * 5 + [0.3] * 3 + [0.1] * 2))
    assert bias == pytest.approx(np.median([0.2] * 5 + [-0.3] * 3 + [0.1] * 2))
    pred[0, 0] = np.nan  # not drawn: left out
    assert depth_errors(pred, gt, m)[0] == pytest.approx(np.median([0.2] * 4 + [0.3] * 3 + [0.1] * 2))
    assert np.isnan(depth_errors(pred, gt, np.zeros_like(m))[0])


def test_masked_psnr_is_the_protocols():
    a = np.zeros((4, 4, 3), np.uint8)
    b = a.copy()
    b[:2] = 5
    m = np.zeros((4, 4), bool)
    m[:2] = True
    assert masked_psnr(a, b, m) == pytest.approx(10 * np.log10(255**2 / 25))
    assert masked_psnr(a, b) == pytest.approx(10 * np.log10(255**2 / 12.5))
    assert masked_psnr(a, b, ~m) == float("inf")
    assert np.isnan(masked_psnr(a, b, np.zeros_like(m)))


def test_erode_and_table():
    m = np.zeros((9, 9), bool)
    m[2:7, 2:7] = True
    assert erode(m, 1).sum() == 9 and erode(m, 2).sum() == 1 and erode(m, 0).sum() == 25
    rows = [{"frame": 0, "depth": 0.1, "screen": 2.0}, {"frame": 1, "depth": 0.3, "screen": float("nan")},
            {"frame": 2, "depth": 0.2}]  # fmt: skip
    med = medians(rows)
    assert med["depth"] == pytest.approx(0.2) and med["screen"] == pytest.approx(2.0)
    assert np.isnan(med["mpsnr"])
    text = format_table(rows)
    assert "20.0%" in text.splitlines()[-1] and "median" in text.splitlines()[-1]


def _tiny_rig(path):
    """A 12-camera two-row rig like Balloon1's (as tests/nvidia_ls/test_nvls_synth_twin.py), as LLFF."""
    import cv2

    from nvidia_ls import llff

    rng = np.random.default_rng(3)
    w2cs, xs = [], np.linspace(-5.0, 6.5, 6)
    for i in range(12):
        row, col = divmod(i, 6)
        centre = np.array([xs[col] if row == 0 else xs[5 - col], -0.9 + 2.0 * row, -1.0 + 2.8 * row])
        R = cv2.Rodrigues(rng.normal(0, 0.03, 3))[0]
        w = np.eye(4)
        w[:3, :3], w[:3, 3] = R, -R @ centre
        w2cs.append(w)
    Kr = np.array([[920.0, 0, 479.5], [0, 920.0, 269.5], [0, 0, 1]])
    bounds = np.stack([np.full(12, 40.0), np.linspace(60.0, 70.0, 12)], 1)
    np.save(path, llff.opencv_to_llff(np.stack(w2cs), np.stack([Kr] * 12), 540, 960, bounds))
    return path


def test_truth_recasts_the_captures_ground_truth(tmp_path):
    """The exact views twin_score scores against are the capture's own: depth and masks of a training frame
    and of the test camera at full size; on a half-size grid, the full-size values at the covered pixels."""
    from nvidia_ls.build import BuildConfig, build_scene
    from nvidia_ls.synth import SynthConfig, write_raw_scene
    from worldtree.imageio import read_mask

    rig = _tiny_rig(tmp_path / "rig.npy")
    cfg = SynthConfig(kind="twin", poses=rig, steps=12, width=64, height=36, supersample=1, depth=True)
    raw = write_raw_scene(tmp_path / "raw" / "Twin", cfg)
    scene = build_scene(
        raw, tmp_path / "scenes", BuildConfig(poses=raw / "gt" / "poses_bounds.npy", frames=12)
    )
    truth = Truth(raw, scene)
    assert truth.test_camera == 1
    for k in (3, 8):
        cam, t = truth.inp.frame_cams[k], truth.inp.frame_times[k]
        d, ids = truth.view(cam, t, 64, 36)
        gt = np.load(raw / "gt" / "depth" / f"{t:05d}" / f"cam{cam:02d}.npy")
        np.testing.assert_allclose(np.nan_to_num(d), gt, rtol=1e-4)
        np.testing.assert_array_equal(
            ids > 0, read_mask(raw / "gt" / "masks" / f"{t:05d}" / f"cam{cam:02d}.png")
        )
        assert (ids == 1).any()  # the ball is in view
        half_d, half_ids = truth.view(cam, t, 32, 18)
        # Half-size pixel (i, j) has its centre at full-size (2i + 0.5, 2j + 0.5): between four full-size
        # centres, so it equals none of them exactly but lies within their range where all four agree.
        blk = gt.reshape(18, 2, 32, 2)
        lo, hi = blk.min((1, 3)), blk.max((1, 3))
        same = (half_ids >= 0) & (hi - lo < 1e-3 * hi)
        assert same.sum() > 100
        np.testing.assert_allclose(half_d[same], gt.reshape(18, 2, 32, 2)[:, 0, :, 0][same], rtol=1e-3)
    d1, ids1 = truth.view(1, 5, 64, 36)
    np.testing.assert_array_equal(ids1 > 0, read_mask(raw / "gt" / "masks" / "00005" / "cam01.png"))


def test_smoothness_curve_sees_the_constant_velocity_ambiguity():
    """Cameras on a line at constant speed and a point at constant velocity: every depth scale k gives a
    straight path (0 for all k). A point swinging back and forth before a still camera: the path's
    acceleration scales with k, so the curve is k^2 times its value at 1 (its minimum at the smallest k)."""
    from benchmarks.speed.twin_depth_stages import smoothness_curve

    T = 6
    Ks = np.stack([K] * T)
    ks = np.array([0.5, 1.0, 2.0])
    cams = np.stack([_cam([0.3 * t, 0, 0]) for t in range(T)])
    X = np.stack([[1.0 - 0.2 * t, 0.1, 5.0 + 0.1 * t] for t in range(T)])
    uv, z = zip(*[project(X[t : t + 1], K, cams[t]) for t in range(T)], strict=True)
    tracks, depth = np.stack(uv), np.stack(z)
    vis = np.ones((T, 1), bool)
    np.testing.assert_allclose(smoothness_curve(tracks, vis, depth, Ks, cams, ks), 0.0, atol=1e-18)
    still = np.stack([_cam([0, 0, 0])] * T)
    Xs = np.stack([[0.4 * (-1) ** t, 0.0, 5.0] for t in range(T)])
    uv, z = zip(*[project(Xs[t : t + 1], K, still[t]) for t in range(T)], strict=True)
    c = smoothness_curve(np.stack(uv), vis, np.stack(z), Ks, still, ks)
    np.testing.assert_allclose(c / c[1], ks**2)
    vis[2] = False  # no run of three consecutive frames through frame 2: only frames 3, 4, 5 count
    assert smoothness_curve(np.stack(uv), vis, np.stack(z), Ks, still, ks)[1] == pytest.approx(c[1] / 4)
