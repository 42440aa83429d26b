"""Linking of track pieces across gaps (worldtree.priors.track_linking) on synthetic sequences with a known
answer: the true trajectories are written down in closed form, the pieces cut from them."""

import dataclasses

import numpy as np
import pytest

from worldtree.priors.config import MotionConfig
from worldtree.priors.track_linking import link_pieces, patch_ncc

H, W, T = 72, 96, 10
F, Z = 50.0, 5.0  # focal (px) and the depth of every point (scene units)


def _cameras(jump_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Ping-pong rig: the camera moves sideways every frame so that a point at depth Z jumps ``jump_px``."""
    Ks = np.tile(np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]], np.float64), (T, 1, 1))
    w2cs = np.tile(np.eye(4), (T, 1, 1))
    w2cs[:, 0, 3] = (np.arange(T) % 2) * jump_px * Z / F  # x_img = F (X + tx) / Z + cx
    return Ks, w2cs


def _textured_frames(objects, cam_px: np.ndarray, seed: int = 0) -> np.ndarray:
    """Frames [T, H, W, 3]: a static random background shifted by the camera, each object a random 9x9 patch
    pasted with its centre at its integer position ``(x(t), y(t))``; ``objects`` = [(x [T], y [T])]."""
    rng = np.random.default_rng(seed)
    bg = rng.random((H, W + 40))
    patches = [rng.random((9, 9)) for _ in objects]
    out = np.zeros((T, H, W, 3), np.float32)
    for t in range(T):
        s = int(round(cam_px[t]))
        img = bg[:, 20 - s : 20 - s + W].copy()
        for (x, y), p in zip(objects, patches, strict=True):
            cx, cy = int(x[t]), int(y[t])
            img[cy - 4 : cy + 5, cx - 4 : cx + 5] = p
        out[t] = img[..., None]
    return out


def _pieces(paths, spans):
    """Tracks [T, N, 2] / [T, N]: piece n follows ``paths[k]`` over frames ``spans[n] = (k, first, last)``."""
    xy = np.zeros((T, len(spans), 2), np.float32)
    vis = np.zeros((T, len(spans)), bool)
    for n, (k, a, b) in enumerate(spans):
        xy[a : b + 1, n, 0] = paths[k][0][a : b + 1]
        xy[a : b + 1, n, 1] = paths[k][1][a : b + 1]
        vis[a : b + 1, n] = True
    return xy, vis


def test_pieces_of_one_trajectory_are_joined_across_camera_jumps_only_with_the_camera_removed():
    # One point moving 2 px/frame on its own while the rig jumps 6 px every frame; cut into frames 0-3 and 6-9.
    Ks, w2cs = _cameras(6.0)
    cam_px = (np.arange(T) % 2) * 6.0
    x = 30 + 2.0 * np.arange(T) + cam_px
    y = np.full(T, 24.0)
    images = _textured_frames([(x, y)], cam_px)
    xy, vis = _pieces([(x, y)], [(0, 0, 3), (0, 6, 9)])
    depth = np.full((T, H, W), Z, np.float32)
    cfg = MotionConfig(track_link_gap=3)
    out_xy, out_vis, st = link_pieces(xy, vis, cfg, images, depth, Ks, w2cs)
    assert st.links == 1 and st.pieces == 2 and list(st.parts) == [2, 0]
    assert out_vis[:, 0].sum() == 8 and not out_vis[:, 1].any()
    np.testing.assert_allclose(out_xy[out_vis[:, 0], 0, 0], x[out_vis[:, 0]], atol=1e-5)
    # In the image alone the last step (2 -> 3) moved 2 + 6 = 8 px: continued that way the start at 6 is
    # missed by 24 px, beyond the tolerance 2 + 0.5 * 8 * 3 = 14.
    _, v_img, st_img = link_pieces(xy, vis, dataclasses.replace(cfg, track_link_camera=False), images)
    assert st_img.links == 0 and v_img[:, 1].sum() == 4
    # A gap longer than track_link_gap is not bridged.
    _, v_short, _ = link_pieces(xy, vis, dataclasses.replace(cfg, track_link_gap=2), images, depth, Ks, w2cs)
    assert v_short[:, 1].sum() == 4


def test_crossing_objects_are_not_linked_to_each_other():
    # Object 1 moves right, object 2 moves down and passes, at frame 4, exactly where object 1 would be.
    # Object 1 is hidden at frame 4 (object 2 is drawn in front), lost at 5 and found again from frame 6.
    t = np.arange(T, dtype=np.float64)
    x1, y1 = 12 + 6.0 * t, np.full(T, 30.0)
    x2, y2 = np.full(T, 36.0), 6 + 6.0 * t
    assert (x1[4], y1[4]) == (x2[4], y2[4])
    images = _textured_frames([(x1, y1), (x2, y2)], np.zeros(T))
    xy, vis = _pieces([(x1, y1), (x2, y2)], [(0, 0, 3), (0, 6, 9), (1, 4, 9)])
    cfg = MotionConfig(track_link_gap=3)
    out_xy, out_vis, st = link_pieces(xy, vis, cfg, images)
    # Both starts lay on the continued motion; object 2's was refused for its motion.
    assert st.candidates == 2 and st.rejected_velocity == 1 and st.links == 1
    assert out_vis[:, 0].sum() == 8 and not out_vis[:, 1].any()
    np.testing.assert_allclose(out_xy[out_vis[:, 0], 0, 0], x1[out_vis[:, 0]])
    assert out_vis[:, 2].sum() == 6  # object 2 stays its own track


def test_appearance_refuses_a_look_alike_motion_of_another_object():
    # Object 2 moves exactly as object 1 would have, from where object 1's piece ends, but it is another
    # texture: only the appearance check can tell.
    t = np.arange(T, dtype=np.float64)
    x1, y1 = 20 + 3.0 * t, np.full(T, 24.0)
    x2, y2 = 20 + 3.0 * t, np.full(T, 24.0)
    frames = _textured_frames([(x1, y1)], np.zeros(T), seed=1)
    other = _textured_frames([(x2, y2)], np.zeros(T), seed=2)
    images = np.concatenate([frames[:4], other[4:]])
    xy, vis = _pieces([(x1, y1), (x2, y2)], [(0, 0, 3), (1, 5, 9)])
    cfg = MotionConfig(track_link_gap=3)
    _, v, st = link_pieces(xy, vis, cfg, images)
    assert st.links == 0 and st.rejected_appearance == 1 and v[:, 1].sum() == 5
    _, v_any, st_any = link_pieces(xy, vis, dataclasses.replace(cfg, track_link_ncc=-1.0), images)
    assert st_any.links == 1 and v_any[:, 0].sum() == 9


def test_patch_ncc_matches_a_direct_computation():
    rng = np.random.default_rng(3)
    a = rng.random((20, 20)).astype(np.float32)
    b = (0.5 * a + 0.2 + 0.05 * rng.random((20, 20))).astype(np.float32)
    got = patch_ncc(a, np.array([[10.0, 9.0]]), b, np.array([[10.0, 9.0]]), 3)[0]
    pa, pb = a[6:13, 7:14].astype(np.float64), b[6:13, 7:14].astype(np.float64)
    want = np.corrcoef(pa.ravel(), pb.ravel())[0, 1]
    assert got == pytest.approx(want, abs=1e-5)
    flat = np.full((20, 20), 0.4, np.float32)
    assert np.isnan(patch_ncc(a, np.array([[10.0, 9.0]]), flat, np.array([[10.0, 9.0]]), 3)[0])
