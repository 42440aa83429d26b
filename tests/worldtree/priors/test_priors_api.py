"""compute_priors: one interface, recorded sources, cache reuse and invalidation, per-frame resume."""

from __future__ import annotations

import dataclasses
import json
import threading

import cv2
import numpy as np
import pytest

from worldtree.infra.errors import UserError
from worldtree.priors import DepthConfig, EpiConfig, PriorsConfig, compute_priors
from worldtree.priors import api as api_mod
from worldtree.priors.imported import write_flo

FAST = PriorsConfig(depth=DepthConfig(num_planes=32))


def _write_masks(folder, masks):
    """``masks`` ``[T, H, W]`` bool as one PNG per frame in ``folder`` (created); returns ``folder``."""
    from worldtree.imageio import write_image

    folder.mkdir()
    for t, m in enumerate(masks):
        write_image(folder / f"{t:05d}.png", m)
    return folder


@pytest.fixture(scope="module")
def scene(planar):
    sc, fr = planar
    return sc.to_scene(fr)


@pytest.fixture(scope="module")
def static_scene(planar_static):
    sc, fr = planar_static
    return sc.to_scene(fr)


@pytest.fixture(scope="module")
def computed(scene, tmp_path_factory):
    cache = tmp_path_factory.mktemp("cache")
    return compute_priors(scene, FAST, cache), cache


def test_shapes_sources_and_record(computed, scene, planar):
    pri, cache = computed
    T, H, W = scene.num_frames, scene.height, scene.width
    assert pri.depth.shape == pri.depth_conf.shape == pri.epi_error.shape == pri.epi_mask.shape == (T, H, W)
    N = pri.tracks.shape[1]
    assert pri.tracks.shape == (T, N, 2) and pri.track_vis.shape == (T, N) and pri.track_dynamic.shape == (N,)
    assert all(f.flow.shape == (H, W, 2) and f.valid.shape == (H, W) for f in pri.flow.values())
    assert pri.sources["depth"] == "classical" and pri.sources["tracks"] == "classical"
    rec = json.loads((cache / "priors.json").read_text())
    assert rec["sources"] == pri.sources and rec["frames"] == T and rec["config"]["depth"]["num_planes"] == 32
    tens = pri.torch()
    assert tens["depth"].shape == (T, H, W) and tens["track_dynamic"].shape == (N,)
    # The proof bounds of the issue on this small scene.
    _, fr = planar
    gt = fr["mask"]
    assert (pri.epi_mask & gt).sum() / (pri.epi_mask | gt).sum() > 0.5
    static = ~gt
    assert np.mean(np.abs(pri.depth - fr["depth"])[static] / fr["depth"][static]) < 0.1
    # Moving pixels carry no depth confidence; dynamic tracks exist and start on the moving square mostly.
    assert not pri.depth_conf[pri.epi_mask].any()
    assert pri.track_dynamic.sum() > 10


def test_second_run_reuses_cache(computed, scene, monkeypatch):
    pri, cache = computed

    def boom(*a, **k):
        raise AssertionError("recomputed although cached")

    monkeypatch.setattr(api_mod.depth_mod, "frame_depth", boom)
    monkeypatch.setattr(api_mod.flow, "compute_pair", boom)
    monkeypatch.setattr(api_mod.tracks, "track_video", boom)
    monkeypatch.setattr(api_mod.epipolar, "epipolar_error_maps", boom)
    again = compute_priors(scene, FAST, cache)
    np.testing.assert_array_equal(again.depth, pri.depth)
    np.testing.assert_array_equal(again.tracks, pri.tracks)
    np.testing.assert_array_equal(again.epi_error, pri.epi_error)
    np.testing.assert_array_equal(again.flow[(0, 1)].flow, pri.flow[(0, 1)].flow)


def test_changed_setting_recomputes_only_what_depends_on_it(computed, scene, monkeypatch):
    pri, cache = computed
    calls = {"depth": 0, "epi": 0}
    real_epi = api_mod.epipolar.epipolar_error_maps

    def no_depth(*a, **k):
        calls["depth"] += 1
        raise AssertionError("depth does not depend on the EPI settings")

    def count_epi(*a, **k):
        calls["epi"] += 1
        return real_epi(*a, **k)

    monkeypatch.setattr(api_mod.depth_mod, "frame_depth", no_depth)
    monkeypatch.setattr(api_mod.epipolar, "epipolar_error_maps", count_epi)
    cfg = dataclasses.replace(FAST, epi=EpiConfig(threshold_px=3.0))
    compute_priors(scene, cfg, cache)
    assert calls == {"depth": 0, "epi": 1}


def test_changed_images_change_the_key(scene, tmp_path):
    from worldtree.priors.cache import inputs_fingerprint

    imgs = np.zeros((2, 4, 4, 3), np.uint8)
    K = np.stack([np.eye(3)] * 2)
    P = np.stack([np.eye(4)] * 2)
    a = inputs_fingerprint(imgs, K, P)
    imgs2 = imgs.copy()
    imgs2[1, 2, 2, 0] = 1
    P2 = P.copy()
    P2[1, 0, 3] = 1e-6
    assert len({a, inputs_fingerprint(imgs2, K, P), inputs_fingerprint(imgs, K, P2)}) == 3


def test_interrupted_depth_resumes_per_frame(scene, tmp_path, monkeypatch):
    real = api_mod.depth_mod.frame_depth
    done = []

    def flaky(t, *a, **k):
        if len(done) == 3:
            raise KeyboardInterrupt
        done.append(t)
        return real(t, *a, **k)

    monkeypatch.setattr(api_mod.depth_mod, "frame_depth", flaky)
    with pytest.raises(KeyboardInterrupt):
        compute_priors(scene, dataclasses.replace(FAST, threads=1), tmp_path)
    assert done == [0, 1, 2]
    folder = next(tmp_path.glob("depth-*"))
    assert sorted(p.name for p in folder.glob("*.npz")) == ["00000.npz", "00001.npz", "00002.npz"]
    assert not (folder / "COMPLETE").exists()
    assert not list(folder.glob("*.tmp"))
    resumed = []

    def count(t, *a, **k):
        resumed.append(t)
        return real(t, *a, **k)

    monkeypatch.setattr(api_mod.depth_mod, "frame_depth", count)
    compute_priors(scene, FAST, tmp_path)
    assert resumed == list(range(3, scene.num_frames))
    assert (folder / "COMPLETE").exists()


def test_near_static_scene_has_no_dynamic_pixels_or_tracks(static_scene):
    # The reference code crashes on an all-false EPI mask; here it is simply empty.
    pri = compute_priors(static_scene, FAST, None)
    assert not pri.epi_mask.any()
    assert pri.track_dynamic.shape == (pri.tracks.shape[1],) and not pri.track_dynamic.any()
    assert pri.tracks.shape[1] > 50


def test_imported_sources(scene, computed, tmp_path):
    pri, _ = computed
    T, H, W = scene.num_frames, scene.height, scene.width
    ddir = tmp_path / "depth"
    ddir.mkdir()
    for t in range(T):
        np.save(ddir / f"{t:05d}.npy", 1.0 / pri.depth[t])  # disparity
    gt = np.zeros((T, H, W), bool)
    gt[:, 10:30, 20:50] = True
    mdir = _write_masks(tmp_path / "masks", gt)
    fdir = tmp_path / "flow"
    fdir.mkdir()
    for (i, j), fp in pri.flow.items():
        if abs(i - j) == 1:
            write_flo(fdir / f"{i:05d}_{j:05d}.flo", fp.flow)
    np.savez(tmp_path / "tracks.npz", tracks=pri.tracks, visibility=pri.track_vis)
    cfg = dataclasses.replace(
        FAST,
        depth_source=str(ddir),
        # Values as in the files (the fit to the cameras' scale has its own tests in test_depth_scale.py).
        depth_import=dataclasses.replace(FAST.depth_import, kind="disparity", fit_global_scale=False),
        tracks_source=str(tmp_path / "tracks.npz"),
        flow_source=str(fdir),
        masks_source=str(mdir),
    )
    got = compute_priors(scene, cfg, None)
    assert got.sources["depth"].startswith("imported:") and "disparity" in got.sources["depth"]
    assert got.sources["tracks"] == f"imported:{tmp_path / 'tracks.npz'}"
    assert got.sources["flow"].startswith("imported:") and got.sources["masks"].startswith("imported:")
    np.testing.assert_allclose(got.depth, pri.depth, rtol=1e-5)
    np.testing.assert_array_equal(got.epi_mask, gt)
    assert set(got.flow) == {k for k in pri.flow if abs(k[0] - k[1]) == 1}
    np.testing.assert_array_equal(got.tracks, pri.tracks)
    # Dynamic tracks now follow the imported masks.
    inside = gt[0][np.clip(np.round(pri.tracks[..., 1]).astype(int), 0, H - 1),
                   np.clip(np.round(pri.tracks[..., 0]).astype(int), 0, W - 1)]  # fmt: skip
    assert ((inside & pri.track_vis).sum(0) >= 2).tolist() == got.track_dynamic.tolist()


def test_bad_import_fails_before_computing(scene, tmp_path, monkeypatch):
    def boom(*a, **k):
        raise AssertionError("computed before validating the imports")

    monkeypatch.setattr(api_mod.depth_mod, "frame_depth", boom)
    with pytest.raises(UserError, match="no such file"):
        compute_priors(scene, dataclasses.replace(FAST, tracks_source=str(tmp_path / "x.npz")), tmp_path)
    with pytest.raises(UserError, match="not a folder"):
        compute_priors(scene, dataclasses.replace(FAST, masks_source=str(tmp_path / "m")), tmp_path)
    with pytest.raises(UserError, match="not a folder"):
        compute_priors(scene, dataclasses.replace(FAST, flow_source=str(tmp_path / "f")), tmp_path)


def test_same_priors_for_any_thread_count_and_caller_opencv_threads(scene):
    """Frames spread over 1 or 3 threads, and OpenCV left at 3 or 1 threads by the caller: the same priors
    to the bit, and the caller's OpenCV setting is given back."""
    before = cv2.getNumThreads()
    try:
        cv2.setNumThreads(3)
        one = compute_priors(scene, dataclasses.replace(FAST, threads=1), None)
        assert cv2.getNumThreads() == 3
        cv2.setNumThreads(1)
        three = compute_priors(scene, dataclasses.replace(FAST, threads=3), None)
        assert cv2.getNumThreads() == 1
    finally:
        cv2.setNumThreads(before)
    assert one.identical(three)


def test_interrupted_depth_on_threads_keeps_whole_frames_in_order(scene, tmp_path, monkeypatch):
    """On a pool, a failing frame stops the run; what is saved is a prefix of the frames, each complete, and
    the rerun computes the rest only."""
    real = api_mod.depth_mod.frame_depth
    lock = threading.Lock()

    def flaky(t, *a, **k):
        if t == 4:
            raise KeyboardInterrupt
        return real(t, *a, **k)

    monkeypatch.setattr(api_mod.depth_mod, "frame_depth", flaky)
    cfg = dataclasses.replace(FAST, threads=3)
    with pytest.raises(KeyboardInterrupt):
        compute_priors(scene, cfg, tmp_path)
    folder = next(tmp_path.glob("depth-*"))
    assert sorted(p.name for p in folder.glob("*.npz")) == [f"{t:05d}.npz" for t in range(4)]
    assert not list(folder.glob("*.tmp"))
    resumed = []

    def count(t, *a, **k):
        with lock:
            resumed.append(t)
        return real(t, *a, **k)

    monkeypatch.setattr(api_mod.depth_mod, "frame_depth", count)
    compute_priors(scene, cfg, tmp_path)
    assert sorted(resumed) == list(range(4, scene.num_frames))
    assert (folder / "COMPLETE").exists()


def test_identical_sees_one_changed_value(computed):
    pri, _ = computed
    assert pri.identical(pri)
    other = dataclasses.replace(pri, depth=pri.depth.copy())
    other.depth[0, 0, 0] = np.nextafter(other.depth[0, 0, 0], np.float32(np.inf))
    assert not pri.identical(other)
    k = next(iter(pri.flow))
    flows = dict(pri.flow)
    flows[k] = api_mod.FlowPair(pri.flow[k].flow, ~pri.flow[k].valid)
    assert not pri.identical(dataclasses.replace(pri, flow=flows))


def _neighbour_flows(pri, folder):
    """Write the gap-1 pairs of ``pri``'s flow as a folder of .flo files (what DynamicNeRF ships)."""
    folder.mkdir()
    for (i, j), fp in pri.flow.items():
        if abs(i - j) == 1:
            write_flo(folder / f"{i:05d}_{j:05d}.flo", fp.flow)
    return folder


def test_imported_flow_gets_the_gaps_it_lacks_from_dis(scene, computed, tmp_path, monkeypatch):
    pri, _ = computed
    fdir = _neighbour_flows(pri, tmp_path / "flow")
    fill = dataclasses.replace(FAST.flow, import_missing="classical")
    cfg = dataclasses.replace(FAST, flow_source=str(fdir), flow=fill)
    cache = tmp_path / "cache"
    got = compute_priors(scene, cfg, cache)
    gaps = {abs(i - j) for i, j in got.flow}
    assert gaps == set(FAST.flow.offsets) == {1, 3}
    assert "classical DIS for the" in got.sources["flow"] and "(gaps 3)" in got.sources["flow"]
    for (i, j), fp in pri.flow.items():  # the classical run computed every pair itself, with the same depth
        if abs(i - j) == 3:
            np.testing.assert_array_equal(got.flow[(i, j)].flow, fp.flow)
            np.testing.assert_array_equal(got.flow[(i, j)].valid, fp.valid)
    # The default leaves the folder's pairs alone.
    plain = compute_priors(scene, dataclasses.replace(FAST, flow_source=str(fdir)), None)
    assert {abs(i - j) for i, j in plain.flow} == {1} and "DIS" not in plain.sources["flow"]
    # The filled pairs are cached as the classical flow: a classical run on that cache recomputes only the
    # pairs the import had.
    calls = []
    real = api_mod.flow.compute_pair

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(api_mod.flow, "compute_pair", counting)
    classical = compute_priors(scene, FAST, cache)
    assert len(calls) == scene.num_frames - 1  # the gap-1 pairs
    np.testing.assert_array_equal(classical.flow[(0, 3)].flow, pri.flow[(0, 3)].flow)
    assert len(classical.flow) == len(pri.flow)


def test_imported_masks_keep_the_sweeps_depth_unless_asked_to_fill(scene, planar, tmp_path):
    _, fr = planar
    gt = fr["mask"]
    # An imported all-empty mask leaves the classical depth as the plane sweep made it: the reference.
    empty = _write_masks(tmp_path / "empty", np.zeros_like(gt))
    raw = compute_priors(scene, dataclasses.replace(FAST, masks_source=str(empty)), None)
    cfg = dataclasses.replace(FAST, masks_source=str(_write_masks(tmp_path / "gt", gt)))
    kept = compute_priors(scene, cfg, None)
    filled = compute_priors(
        scene, dataclasses.replace(cfg, depth=dataclasses.replace(FAST.depth, fill_imported_masks=True)), None
    )
    np.testing.assert_array_equal(kept.depth, raw.depth)
    assert not kept.depth_conf[gt].any() and not filled.depth_conf[gt].any()
    np.testing.assert_array_equal(kept.depth_conf[~gt], raw.depth_conf[~gt])
    np.testing.assert_array_equal(filled.depth[~gt], raw.depth[~gt])
    assert np.abs(filled.depth[gt] - raw.depth[gt]).max() > 0
