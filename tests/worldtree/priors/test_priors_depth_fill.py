"""Imported depth fitted robustly and merged with stereo: ``depth_import.fit_trim`` and ``merge="fill"``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from worldtree.imageio import write_image
from worldtree.infra.errors import UserError
from worldtree.priors import DepthConfig, PriorsConfig, compute_priors
from worldtree.priors.config import DepthImportConfig
from worldtree.priors.imported import (
    balanced_weights,
    fit_scale,
    fit_scale_shift,
    fit_scale_shift_robust,
    imported_to_depth,
)


def test_robust_fit_ignores_gross_outliers():
    rng = np.random.default_rng(0)
    x = rng.uniform(1.0, 3.0, 2000)
    y = 0.4 * x + 0.3 + rng.normal(0, 1e-3, x.size)
    y[:200] += rng.uniform(0.5, 2.0, 200)  # 10% gross errors, all on one side (occlusions)
    w = np.ones_like(x)
    a_ls, b_ls = fit_scale_shift(x, y, w)
    a, b = fit_scale_shift_robust(x, y, w, trim=2.5)
    assert abs(a - 0.4) < 2e-3 and abs(b - 0.3) < 5e-3
    # The plain fit is pulled up by about the outliers' mean share (10% x 1.25): the test tells them apart.
    assert a_ls * 2.0 + b_ls - 1.1 > 0.08
    assert fit_scale_shift_robust(x, y, w, trim=None) == (a_ls, b_ls)
    # Exact data: trimming never removes points at rounding level, the result is the exact line.
    a0, b0 = fit_scale_shift_robust(x, 2 * x - 1, w, trim=2.5)
    np.testing.assert_allclose([a0, b0], [2.0, -1.0], atol=1e-9)


def test_balanced_weights_give_every_value_range_the_same_mass():
    rng = np.random.default_rng(1)
    # 95 % of the pixels on a far wall (disparity ~1), 5 % spread over nearer surfaces (1..4).
    x = np.concatenate([rng.normal(1.0, 0.01, 9500), rng.uniform(1.0, 4.0, 500)])
    w = rng.uniform(0.5, 1.0, x.size)
    wb = balanced_weights(x, w, 5)
    lo, hi = np.percentile(x, [1, 99])
    idx = np.clip(((x - lo) / (hi - lo) * 5).astype(int), 0, 4)
    mass = np.bincount(idx, weights=wb, minlength=5)
    np.testing.assert_allclose(mass, np.full(5, w.sum() / 5), rtol=1e-9)
    # Inside a bin the confidence still orders the pixels.
    same = idx == idx[0]
    np.testing.assert_allclose(wb[same] / w[same], (wb[same] / w[same])[0])
    np.testing.assert_array_equal(balanced_weights(x, w, 0), w)
    assert not np.any(balanced_weights(x, np.zeros_like(w), 5))


def test_refit_without_moving_pixels_recovers_their_depth():
    """A frame whose reference depth on a near object is the wall behind it (stereo fills moving pixels
    from their surroundings): fitted with them, the object's depth is wrong; left out, it is exact."""
    H, W = 40, 60
    depth = np.full((1, H, W), 10.0)
    depth[0, 30:, :] = np.linspace(4.0, 9.0, W)[None]  # a floor: nearer static surfaces
    near = np.zeros((1, H, W), bool)
    near[0, 5:20, 10:30] = True
    depth[near] = 2.0  # the moving object, close to the camera
    disp = 0.7 / depth + 0.05  # relative disparity: exact up to scale and shift
    ref = depth.copy()
    ref[near] = 10.0  # what the static reference says there
    cfg = DepthImportConfig(kind="disparity", fit_scale_shift=True, fit_trim=None, fit_balance_bins=0)
    with_obj = imported_to_depth(disp, cfg, ref, np.ones_like(ref))
    without = imported_to_depth(disp, cfg, ref, np.ones_like(ref), exclude=near)
    np.testing.assert_allclose(without[near], 2.0, rtol=1e-6)
    assert abs(np.median(with_obj[near]) / 2.0 - 1) > 0.1


def test_scale_fit_is_the_least_squares_line_through_the_origin():
    rng = np.random.default_rng(3)
    x = rng.uniform(0.5, 2.0, 500)
    y = 1.7 * x + rng.normal(0, 0.05, x.size)
    w = rng.uniform(0.1, 1.0, x.size)
    a, b = fit_scale(x, y, w)
    # Independent: weighted least squares with one column by numpy's solver.
    ref = np.linalg.lstsq((np.sqrt(w) * x)[:, None], np.sqrt(w) * y, rcond=None)[0][0]
    assert b == 0.0 and a == pytest.approx(ref, rel=1e-12)
    assert fit_scale(x, y, np.zeros_like(w)) == (1.0, 0.0)
    assert fit_scale(np.zeros_like(x), y, w) == (1.0, 0.0)
    # Trimmed: 10 % gross errors on one side leave the scale where the clean points put it.
    y_bad = y.copy()
    y_bad[:50] += 3.0
    a_r, b_r = fit_scale_shift_robust(x, y_bad, w, trim=2.5, shift=False)
    assert b_r == 0.0 and abs(a_r - 1.7) < 0.01
    assert abs(fit_scale(x, y_bad, w)[0] - 1.7) > 0.1


def test_scale_without_shift_places_a_near_object_where_a_noisy_wall_flattens_the_line():
    """The static pixels span one wall (depth 8..12) and the network's disparity errs by 10 % per pixel
    (no shift): least squares with a shift flattens the slope (regression dilution) and puts an object at
    depth 3, nearer than anything fitted, about 40 % too far; a scale alone, the mean ratio, puts it within
    a few per cent."""
    rng = np.random.default_rng(0)
    H, W = 60, 90
    obj = np.zeros((1, H, W), bool)
    obj[0, 10:30, 20:40] = True
    z = np.where(obj, 3.0, np.tile(np.linspace(8.0, 12.0, W), (H, 1))[None])
    disp = 2.5 / z * (1.0 + rng.normal(0.0, 0.1, z.shape))
    ref = np.where(obj, 10.0, z)
    ratio = {}
    for shift in (True, False):
        cfg = DepthImportConfig(kind="disparity", fit_scale_shift=True, fit_shift=shift, fit_trim=2.5)
        d = imported_to_depth(disp, cfg, ref, np.ones_like(ref), exclude=obj)
        ratio[shift] = float(np.median(d[obj]) / 3.0)
    assert ratio[True] > 1.25
    assert abs(ratio[False] - 1.0) < 0.06


@pytest.fixture(scope="module")
def planar_scene_files(planar, tmp_path_factory):
    """The planar scene with exact masks and a relative disparity (0.5 / depth + 0.2) written as files."""
    sc, fr = planar
    root = tmp_path_factory.mktemp("fill")
    for t in range(len(fr["rgb"])):
        write_image(root / "masks" / f"{t:05d}.png", fr["mask"][t])
        (root / "disp").mkdir(exist_ok=True)
        np.save(root / "disp" / f"{t:05d}.npy", (0.5 / fr["depth"][t] + 0.2).astype(np.float32))
    return sc.to_scene(fr), fr, root


def test_fill_keeps_stereo_and_gives_moving_objects_the_imported_depth(planar_scene_files, tmp_path):
    scene, fr, root = planar_scene_files
    base = PriorsConfig(depth=DepthConfig(num_planes=32), masks_source=str(root / "masks"))
    classical = compute_priors(scene, base, tmp_path / "c")
    di = DepthImportConfig(kind="disparity", fit_scale_shift=True, merge="fill")
    pri = compute_priors(scene, dataclasses.replace(base, depth_source=str(root / "disp"), depth_import=di),
                         tmp_path / "c")  # fmt: skip
    mask = fr["mask"]
    keep = (classical.depth_conf >= 0.5) & ~mask
    # Stereo kept where it is a measurement.
    np.testing.assert_allclose(pri.depth[keep], classical.depth[keep], rtol=1e-6)
    # On the moving square the imported depth (fitted to stereo) is close to the truth; the classical prior
    # there is a fill from the wall around it, far off (the square is at 2.2, the wall at 4).
    rel = np.abs(pri.depth[mask] - fr["depth"][mask]) / fr["depth"][mask]
    rel_classical = np.abs(classical.depth[mask] - fr["depth"][mask]) / fr["depth"][mask]
    assert np.median(rel) < 0.05 and np.median(rel_classical) > 0.2
    assert np.all(pri.depth_conf[mask] == 1.0)
    assert "filled from" in pri.sources["depth"]
    # The refit a method makes with its own (refined) masks: without the moving pixels it is at least as close
    # on them as a fit that keeps them (their stereo reference is the wall).
    kept = np.abs(pri.depth_fill(np.zeros_like(mask))[mask] - fr["depth"][mask]) / fr["depth"][mask]
    refit = np.abs(pri.depth_fill(mask)[mask] - fr["depth"][mask]) / fr["depth"][mask]
    assert np.median(refit) < 0.05 and np.median(refit) <= np.median(kept) + 1e-3
    assert classical.depth_fill is None


def test_fill_needs_the_fit(planar_scene_files, tmp_path):
    scene, _, root = planar_scene_files
    cfg = PriorsConfig(
        depth_source=str(root / "disp"), depth_import=DepthImportConfig(kind="disparity", merge="fill")
    )
    with pytest.raises(UserError, match="fit_scale_shift=true"):
        compute_priors(scene, cfg, None)


def test_a_static_strip_the_import_misplaces_reads_as_moving_unless_stereo_keeps_it(planar_static, tmp_path):
    """A static scene whose imported disparity is exact except where stereo is unconfident (the end frames'
    strips no other camera matches), where it reads 2.5 times nearer. ``fill_static="import"`` puts it there,
    and the depth-consistency cue, testing the flow against it, marks those static pixels as moving (what
    the shipped MiDaS did to Balloon1's end strips); ``fill_static="classical"`` keeps the stereo depth there
    and the cue is the one computed against stereo."""
    from worldtree.priors.motion_cues import rigid_evidence_maps

    sc, fr = planar_static
    scene = sc.to_scene(fr)
    base = PriorsConfig(depth=DepthConfig(num_planes=32))
    classical = compute_priors(scene, base, tmp_path / "c")
    unconf = classical.depth_conf < 0.5
    assert 0.005 < unconf.mean() < 0.2  # the scene has such strips (end frames), and they are a small part
    disp = 0.5 / fr["depth"]
    disp = np.where(unconf, 2.5 * disp, disp).astype(np.float32)
    (tmp_path / "disp").mkdir()
    for t in range(len(disp)):
        np.save(tmp_path / "disp" / f"{t:05d}.npy", disp[t])
    Ks, w2cs = scene.Ks.double().numpy(), scene.w2cs.double().numpy()
    got = {}
    for mode in ("import", "classical"):
        di = DepthImportConfig(kind="disparity", fit_scale_shift=True, fit_shift=False, merge="fill",
                               fill_static=mode)  # fmt: skip
        got[mode] = compute_priors(
            scene, dataclasses.replace(base, depth_source=str(tmp_path / "disp"), depth_import=di), tmp_path / "c"
        )
    assert abs(np.median(got["import"].depth[unconf] / fr["depth"][unconf]) - 0.4) < 0.04
    assert np.all(got["import"].depth_conf[unconf] == 1.0)
    # "classical": the stereo depth and its own confidence on every static pixel.
    still = ~got["classical"].epi_mask
    np.testing.assert_array_equal(got["classical"].depth[still], classical.depth[still])
    np.testing.assert_array_equal(got["classical"].depth_conf[still], classical.depth_conf[still])
    mt = base.motion
    # Independent: the cue recomputed from each run's own flows against the stereo depth / the filled depth.
    filled = np.where(unconf, 0.4 * fr["depth"], classical.depth)
    for mode, depth in (("classical", classical.depth), ("import", filled)):
        want = rigid_evidence_maps(got[mode].flow, depth, Ks, w2cs, mt.rigid_tol_px, mt.rigid_rel_depth)
        # float32 rounding of the fit, and the import's 1 % spread around 0.4 in ``filled``
        close = np.abs(got[mode].motion_evidence["rigid"] - want) < 0.05
        assert close.mean() > 0.99, (mode, close.mean())
    strip_ev = {mode: float(got[mode].motion_evidence["rigid"][unconf].mean()) for mode in got}
    assert strip_ev["import"] > 0.3, strip_ev  # the filled strips read as moving ...
    assert strip_ev["classical"] < 0.1, strip_ev  # ... and not against stereo
    assert got["classical"].epi_mask.mean() < 0.01  # nothing moves
    assert got["classical"].epi_mask.mean() <= got["import"].epi_mask.mean()


def test_fill_static_classical_keeps_stereo_on_static_pixels_and_the_import_guides_the_tracks(
    planar_scene_files, tmp_path
):
    """With imported masks: the moving square takes the import, every static pixel the classical depth and
    confidence (the unconfident ones too), and the tracks and flow are those the import guided (as under
    ``fill_static="import"``: on the moving objects it is the only measurement)."""
    scene, fr, root = planar_scene_files
    base = PriorsConfig(depth=DepthConfig(num_planes=32), masks_source=str(root / "masks"))
    classical = compute_priors(scene, base, tmp_path / "c")
    got = {}
    for mode in ("import", "classical"):
        di = DepthImportConfig(kind="disparity", fit_scale_shift=True, merge="fill", fill_static=mode)
        got[mode] = compute_priors(
            scene, dataclasses.replace(base, depth_source=str(root / "disp"), depth_import=di), tmp_path / "c"
        )
    mask = fr["mask"]
    unconf = (classical.depth_conf < 0.5) & ~mask
    assert unconf.sum() > 20
    cls, imp = got["classical"], got["import"]
    np.testing.assert_array_equal(cls.depth[~mask], classical.depth[~mask])
    np.testing.assert_array_equal(cls.depth_conf[~mask], classical.depth_conf[~mask])
    assert not np.array_equal(imp.depth[unconf], classical.depth[unconf])  # the import filled them
    np.testing.assert_array_equal(cls.depth[mask], imp.depth[mask])
    rel = np.abs(cls.depth[mask] - fr["depth"][mask]) / fr["depth"][mask]
    assert np.median(rel) < 0.05
    np.testing.assert_array_equal(cls.tracks, imp.tracks)
    for k in imp.flow:
        np.testing.assert_array_equal(cls.flow[k].flow, imp.flow[k].flow)
    assert cls.sources["depth"].endswith("on dynamic pixels (refitted without them)")
