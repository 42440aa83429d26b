"""Motion discovery: one test per cue on synthetic data with a known answer, the fusion, and track chaining."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from worldtree.priors import dynamic_masks as dm
from worldtree.priors import motion_cues as cues
from worldtree.priors.config import EpiConfig, MotionConfig
from worldtree.priors.dynamic_tracks import chain_dynamic_tracks
from worldtree.priors.epipolar import fundamental_from_poses, sampson_distance
from worldtree.priors.flow import FlowPair, rigid_flow

H, W = 48, 64


def _texture(rng, h, w):
    # Smooth random texture (values in [0.2, 0.8]): enough structure for every cue, no aliasing.
    small = rng.uniform(0.2, 0.8, (h // 4 + 1, w // 4 + 1, 3))
    return np.kron(small, np.ones((4, 4, 1)))[:h, :w].astype(np.float32)


def _moving_square(T=8, size=12, step=4, seed=0):
    """A textured square sliding right over a textured background (static camera): frames, true masks."""
    rng = np.random.default_rng(seed)
    bg, fg = _texture(rng, H, W), _texture(rng, size, size)[..., ::-1] * 0.3 + 0.6
    frames = np.repeat(bg[None], T, 0).copy()
    masks = np.zeros((T, H, W), bool)
    for t in range(T):
        x0, y0 = 6 + step * t, 18
        frames[t, y0 : y0 + size, x0 : x0 + size] = fg
        masks[t, y0 : y0 + size, x0 : x0 + size] = True
    return frames, masks, bg


def _iou(a, b):
    return (a & b).sum() / max((a | b).sum(), 1)


def _fuse_cfg():
    # No opening / size filter from EpiConfig so that the test measures the cue, not the cleaning.
    return EpiConfig(open_px=0, min_area_frac=0.0)


# ------------------------------------------------------------------------------------------------ residual cue
def test_static_scene_residual_gives_empty_masks():
    rng = np.random.default_rng(3)
    bg = _texture(rng, H, W)
    frames = np.stack([bg + rng.normal(0, 0.01, bg.shape).astype(np.float32) for _ in range(5)])
    renders = np.repeat(bg[None], 5, 0)  # a static model that explains the scene up to sensor noise
    ev = dm.residual_evidence_maps(frames, renders, None, MotionConfig())
    out = dm.fuse({"residual": ev}, {}, MotionConfig(), _fuse_cfg())
    assert not out.mask.any()
    assert float(out.confidence.max()) < 0.5


def test_moving_object_found_from_residual_cue_alone():
    frames, masks, _ = _moving_square()
    # The best static model of a video by L1 is its per-pixel temporal median: computed independently here.
    renders = np.repeat(np.median(frames, 0)[None], len(frames), 0)
    ev = dm.residual_evidence_maps(frames, renders, None, MotionConfig())
    out = dm.fuse({"residual": ev}, {}, MotionConfig(), _fuse_cfg())
    m = out.mask
    for t in range(len(frames)):
        assert _iou(m[t], masks[t]) > 0.6, t
    assert (m & masks).sum() / masks.sum() > 0.95  # recall
    # Nothing beyond the residual's 1 px blur around the object (2 px margin).
    near = np.stack([cv2.dilate(k.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0 for k in masks])
    assert not (m & ~near).any()


def test_residual_evidence_floor_and_ramp():
    r = np.zeros((20, 20), np.float32)
    r[5, 5] = 0.5  # one outlier far above the floor and the robust noise
    r[10, 10] = 0.01  # an outlier in robust units but under the absolute floor
    ev = cues.residual_evidence(r, z_low=3, z_high=6, floor=0.04)
    assert ev[5, 5] == 1.0 and ev[10, 10] == 0.0 and ev[0, 0] == 0.0


# ------------------------------------------------------------------------------------------------ epipolar cue
def test_epipolar_evidence_ramp_is_linear_between_half_and_one_and_a_half_thresholds():
    err = np.array([0.0, 0.75, 1.5, 2.25, 3.0])
    ev = cues.epipolar_evidence(err, threshold_px=1.5)
    np.testing.assert_allclose(ev, [0.0, 0.0, 0.5, 1.0, 1.0], atol=1e-6)


# ------------------------------------------------------------------------------------------------ depth cue
def _two_cameras():
    K = np.array([[60.0, 0, (W - 1) / 2], [0, 60.0, (H - 1) / 2], [0, 0, 1]])
    w0, w1 = np.eye(4), np.eye(4)
    w1[:3, 3] = [-0.2, 0.0, 0.0]  # camera 1 is 0.2 units to the right: horizontal epipolar lines
    return K, w0, w1


def test_depth_consistency_sees_motion_along_the_epipolar_line():
    K, w0, w1 = _two_cameras()
    depth = np.full((H, W), 4.0)
    f = rigid_flow(depth, K, w0, K, w1)
    moved = np.zeros((H, W), bool)
    moved[20:30, 25:40] = True
    f[moved, 0] += 4.0  # 4 px along the (horizontal) epipolar line: an object moving sideways
    fp = FlowPair(f.astype(np.float32), np.ones((H, W), bool))
    # The epipolar test is blind to it (independent check with the fundamental matrix) ...
    py, px = np.mgrid[0:H, 0:W].astype(np.float64)
    x1 = np.stack([px, py], -1)
    F = fundamental_from_poses(K, w0, K, w1)
    assert sampson_distance(F, x1, x1 + f).max() < 1e-3
    # ... the depth-consistency cue is not.
    res, par = cues.rigid_residual(fp, depth, K, w0, K, w1)
    np.testing.assert_allclose(res[moved], 4.0, atol=1e-3)
    np.testing.assert_allclose(res[~moved], 0.0, atol=1e-3)
    # Parallax: baseline * focal / depth = 0.2 * 60 / 4 = 3 px (closed form).
    np.testing.assert_allclose(par, 3.0, atol=1e-3)
    ev = cues.rigid_evidence(res, par, tol_px=0.5, rel_depth_tol=0.3)  # tol = 0.5 + 0.9 = 1.4 px
    assert (ev[moved] == 1.0).all() and (ev[~moved] == 0.0).all()


def test_depth_consistency_tolerates_depth_errors_in_proportion_to_parallax():
    K, w0, w1 = _two_cameras()
    true = np.full((H, W), 4.0)
    f = rigid_flow(true, K, w0, K, w1)
    fp = FlowPair(f.astype(np.float32), np.ones((H, W), bool))
    off = true * 1.15  # 15% depth error on a static scene: not motion
    ev = cues.rigid_evidence(*cues.rigid_residual(fp, off, K, w0, K, w1), tol_px=0.2, rel_depth_tol=0.3)
    assert ev.max() == 0.0


# ------------------------------------------------------------------------------------------------ temporal cue
def test_temporal_agreement_halves_a_blip_and_keeps_a_consistent_detection():
    T = 3
    ev = np.zeros((T, H, W), np.float32)
    ev[:, 10:20, 10:20] = 1.0  # seen in every frame (a static flow carries it along)
    ev[1, 30:35, 40:45] = 1.0  # seen in frame 1 only
    zero = FlowPair(np.zeros((H, W, 2), np.float32), np.ones((H, W), bool))
    flows = {(i, j): zero for i in range(T) for j in range(T) if abs(i - j) == 1}
    out = cues.temporal_agreement(ev, flows, self_weight=0.5)
    np.testing.assert_allclose(out[1, 10:20, 10:20], 1.0)
    np.testing.assert_allclose(out[1, 30:35, 40:45], 0.5)
    masks = dm.fuse({"e": ev}, flows, MotionConfig(), _fuse_cfg()).mask
    assert masks[1, 15, 15] and not masks[1, 32, 42]


def test_noisy_or_closed_form():
    a, b = np.array([0.5, 0.0, 1.0]), np.array([0.5, 0.3, 0.2])
    np.testing.assert_allclose(dm.noisy_or([a, b]), 1 - (1 - a) * (1 - b))


# ------------------------------------------------------------------------------------------------ tracks
def _translating_flows(T, velocity, broken=()):
    """Exact flow of a square of 16x16 px moving by ``velocity`` px per frame; pairs (t, t+1) in ``broken``
    are invalid everywhere (a camera change the flow could not follow), gap-3 pairs always valid."""
    masks = np.zeros((T, H, W), bool)
    for t in range(T):
        x0 = 4 + int(round(velocity * t))
        masks[t, 16:32, x0 : x0 + 16] = True
    flows = {}
    for i in range(T):
        for g in (1, 3):
            for j in (i + g, i - g):
                if not 0 <= j < T:
                    continue
                f = np.zeros((H, W, 2), np.float32)
                f[masks[i], 0] = velocity * (j - i)
                valid = masks[i].copy()
                if g == 1 and ((min(i, j), max(i, j)) in broken):
                    valid[:] = False
                flows[(i, j)] = FlowPair(f, valid)
    return flows, masks


def test_chained_tracks_bridge_a_camera_change_with_the_larger_gap():
    T = 9
    flows, masks = _translating_flows(T, 2.0, broken={(3, 4)})
    cfg = dataclasses.replace(MotionConfig(), track_seed_every=100, track_mask_dilate_px=0)
    tr = chain_dynamic_tracks(flows, masks, cfg)
    assert tr.num_tracks > 0
    life = tr.visible.sum(0)
    # Every seed of frame 0 goes on past the broken step 3 -> 4 (via 3 -> 6 or 1 -> 4, ...) to the end.
    assert (tr.visible[-1]).all()
    assert np.median(life) >= T - 2
    # Positions follow the true motion: x(t) = x(seed) + 2 t wherever visible.
    for n in range(tr.num_tracks):
        ts = np.flatnonzero(tr.visible[:, n])
        np.testing.assert_allclose(tr.xy[ts, n, 0] - tr.xy[ts[0], n, 0], 2.0 * (ts - ts[0]), atol=1e-4)


def test_chained_track_pieces_are_linked_across_a_break():
    T = 8
    # Steps 3 -> 4 broken at every gap: no chain crosses it. Without velocity linking the pieces before and
    # after stay apart; with it, pieces whose motion continues across the break are joined.
    flows, masks = _translating_flows(T, 2.0, broken={(3, 4)})
    for i, j in list(flows):
        if min(i, j) <= 3 < max(i, j):
            flows[(i, j)] = FlowPair(flows[(i, j)].flow, np.zeros((H, W), bool))
    cfg = dataclasses.replace(MotionConfig(), track_seed_every=4, track_mask_dilate_px=0, track_link_gap=0)
    tr = chain_dynamic_tracks(flows, masks, cfg)
    assert not (tr.visible[3] & tr.visible[4]).any()
    tr_v = chain_dynamic_tracks(flows, masks, dataclasses.replace(cfg, track_link_gap=3))
    joined = tr_v.visible[0] & tr_v.visible[T - 1]
    assert joined.sum() > 0
    for n in np.flatnonzero(joined):
        ts = np.flatnonzero(tr_v.visible[:, n])
        np.testing.assert_allclose(tr_v.xy[ts, n, 0] - tr_v.xy[ts[0], n, 0], 2.0 * (ts - ts[0]), atol=1e-4)
    # With the steps 3 -> 4 working again (backwards only, as when the forward flow failed the photometric
    # check), pieces seeded at frame 4 chain back and meet the ends of the frame-0 pieces: linked into one.
    flows2, _ = _translating_flows(T, 2.0)
    for i, j in list(flows2):
        if i <= 3 < j:
            flows2[(i, j)] = FlowPair(flows2[(i, j)].flow, np.zeros((H, W), bool))
    tr2 = chain_dynamic_tracks(flows2, masks, cfg)
    both = tr2.visible[0] & tr2.visible[T - 1]
    assert both.sum() >= 0.5 * tr2.visible[0].sum() > 0
    for n in np.flatnonzero(both):
        ts = np.flatnonzero(tr2.visible[:, n])
        np.testing.assert_allclose(tr2.xy[ts, n, 0] - tr2.xy[ts[0], n, 0], 2.0 * (ts - ts[0]), atol=1e-4)


def test_empty_masks_give_no_dynamic_track():
    flows, masks = _translating_flows(5, 2.0)
    tr = chain_dynamic_tracks(flows, np.zeros_like(masks), MotionConfig())
    assert tr.num_tracks == 0 and tr.xy.shape == (5, 0, 2)


def test_velocity_linking_joins_pieces_across_a_short_gap_only_where_motion_continues():
    from worldtree.priors.track_linking import link_pieces

    T = 10
    xy = np.zeros((T, 3, 2), np.float32)
    vis = np.zeros((T, 3), bool)
    # Piece 0: x = 10 + 2 t for t = 0..3. Piece 1 starts at t = 6 where that motion continues (x = 22).
    # Piece 2 starts at t = 6 too, 15 px off the continued motion.
    for t in range(4):
        xy[t, 0], vis[t, 0] = (10 + 2 * t, 20), True
    for t in range(6, T):
        xy[t, 1], vis[t, 1] = (10 + 2 * t, 20), True
        xy[t, 2], vis[t, 2] = (10 + 2 * t, 35), True
    cfg = MotionConfig(track_link_gap=3, track_link_px=2.0)
    out_xy, out_vis, _ = link_pieces(xy, vis, cfg)  # no images, no depth: image velocity, no appearance
    assert out_vis[:, 0].sum() == 8 and not out_vis[:, 1].any()  # 0 and 1 joined into column 0
    assert out_vis[:, 2].sum() == 4  # 2 left alone
    np.testing.assert_allclose(out_xy[out_vis[:, 0], 0, 0], 10 + 2 * np.flatnonzero(out_vis[:, 0]))
    # A gap longer than max_gap is not bridged.
    _, v2, _ = link_pieces(xy, vis, dataclasses.replace(cfg, track_link_gap=1))
    assert v2[:, 1].sum() == 4


def test_chained_step_refused_where_the_point_changes_its_look():
    # The square's texture is replaced at frame 5 (a flow that lands on another surface): with the step check
    # no chained point reaches frame 5; without it every point goes on.
    T = 8
    flows, masks = _translating_flows(T, 2.0)
    rng = np.random.default_rng(4)
    tex, other = rng.random((16, 16)), rng.random((16, 16))
    images = np.full((T, H, W, 3), 0.5, np.float32)
    for t in range(T):
        x0 = 4 + 2 * t
        images[t, 16:32, x0 : x0 + 16] = (other if t == 5 else tex)[..., None]
    cfg = dataclasses.replace(MotionConfig(), track_seed_every=100, track_mask_dilate_px=0, track_link_gap=0)
    off = chain_dynamic_tracks(flows, masks, dataclasses.replace(cfg, track_step_ncc=-1.0), images)
    on = chain_dynamic_tracks(flows, masks, dataclasses.replace(cfg, track_step_ncc=0.5), images)
    assert off.num_tracks == on.num_tracks > 0
    assert off.visible[5].all() and not on.visible[5].any()
    # The gap-3 step 4 -> 7 skips the changed frame: the points carry on, at the true positions.
    assert on.visible[7].all()
    np.testing.assert_allclose(on.xy[7] - on.xy[0], np.tile([[14.0, 0.0]], (on.num_tracks, 1)), atol=1e-4)


def test_chained_step_on_a_texture_too_faint_to_compare_is_kept_with_a_texture_floor():
    # The same change of look at frame 5, on a faint texture (grey std ~0.006): NCC there is noise. With
    # track_step_min_std above that the check is skipped and the points go on; with 0 it still stops most.
    T = 8
    flows, masks = _translating_flows(T, 2.0)
    rng = np.random.default_rng(5)
    tex, other = 0.5 + 0.02 * rng.random((16, 16)), 0.5 + 0.02 * rng.random((16, 16))
    images = np.full((T, H, W, 3), 0.5, np.float32)
    for t in range(T):
        x0 = 4 + 2 * t
        images[t, 16:32, x0 : x0 + 16] = (other if t == 5 else tex)[..., None]
    cfg = dataclasses.replace(
        MotionConfig(), track_seed_every=100, track_mask_dilate_px=0, track_link_gap=0, track_step_ncc=0.5
    )
    strict = chain_dynamic_tracks(flows, masks, cfg, images)
    floor = chain_dynamic_tracks(flows, masks, dataclasses.replace(cfg, track_step_min_std=0.02), images)
    assert floor.num_tracks > 0 and floor.visible[5].all()
    # Strict: most points stop (those at the square's edge keep the edge's look and may pass).
    assert strict.visible[5].mean() < 0.5


def test_residual_map_reads_uint8_frames_as_v_over_255():
    """Frames are held as uint8 (worldtree.pixels): the static-model residual must read them as v / 255,
    exactly as the float frames they replace."""
    from worldtree.priors.motion_cues import residual_map

    rng = np.random.default_rng(0)
    u8 = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
    render = rng.random((12, 16, 3), dtype=np.float32)
    as_float = u8.astype(np.float32) / np.float32(255.0)
    np.testing.assert_array_equal(residual_map(u8, render), residual_map(as_float, render))
    expected = np.abs(as_float - render).mean(-1)  # unblurred: the plain mean absolute difference
    np.testing.assert_allclose(residual_map(u8, render, blur_px=0), expected, rtol=0, atol=1e-7)
