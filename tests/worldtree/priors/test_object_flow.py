"""Object-motion flow inside the dynamic masks: template matching of mask components, and the chained tracks
it lets live through fast motion (``worldtree.priors.object_flow``)."""

from __future__ import annotations

import cv2
import numpy as np

from worldtree.priors.api import add_chained_tracks
from worldtree.priors.config import FlowConfig, MotionConfig, PriorsConfig
from worldtree.priors.flow import compute_flows
from worldtree.priors.object_flow import match_component, object_flows

H, W = 90, 160
SIDE = 20  # the square's side, px
T = 12
RADIUS = 30.0  # the square's centre runs on a circle of this radius (px) around the image centre
STEP = 2 * np.arcsin(10.0 / RADIUS)  # angle per frame: a chord of 20 px, i.e. 20 px of motion per frame


def _texture(rng, h, w, cell=3):
    # Smooth random grey texture in [0.1, 0.9]: cells of `cell` px, cubic-interpolated (DIS and NCC see detail,
    # no aliasing).
    small = rng.uniform(0.1, 0.9, (h // cell + 2, w // cell + 2)).astype(np.float32)
    big = cv2.resize(small, (small.shape[1] * cell, small.shape[0] * cell), interpolation=cv2.INTER_CUBIC)
    return np.clip(big[:h, :w], 0.0, 1.0)


def _positions():
    """Top-left corners [T, 2] (x, y), integer px: 20 px per frame on a circle (stays inside 160x90)."""
    a = STEP * np.arange(T)
    c = np.stack([W / 2 + RADIUS * np.cos(a), H / 2 + RADIUS * np.sin(a)], -1)
    return np.round(c - SIDE / 2).astype(np.int64)


def _scene(flat: bool = False, seed: int = 0):
    """A textured (or flat) square translating 20 px per frame over a textured static background (static
    camera): frames [T, H, W, 3] float, exact masks [T, H, W], top-left corners [T, 2]."""
    rng = np.random.default_rng(seed)
    bg = _texture(rng, H, W)
    fg = np.full((SIDE, SIDE), 0.5, np.float32) if flat else _texture(rng, SIDE, SIDE, cell=2)
    pos = _positions()
    frames = np.repeat(bg[None], T, 0).copy()
    masks = np.zeros((T, H, W), bool)
    for t, (x, y) in enumerate(pos):
        frames[t, y : y + SIDE, x : x + SIDE] = fg
        masks[t, y : y + SIDE, x : x + SIDE] = True
    return np.repeat(frames[..., None], 3, -1), masks, pos


def _chain(frames, masks, on: bool, stats=None):
    cfg = PriorsConfig(motion=MotionConfig(object_flow=on))
    flows = compute_flows(frames, cfg.flow)  # static camera, no depth: DIS starts from zero, as on real rigs
    xy0, vis0, dyn0 = np.zeros((T, 0, 2), np.float32), np.zeros((T, 0), bool), np.zeros(0, bool)
    xy, vis, dyn, n, _ = add_chained_tracks(xy0, vis0, dyn0, flows, masks, cfg, frames, stats=stats)
    return xy, vis


def _drift(xy, vis, pos):
    """Largest error [N] px of each track against the square's known motion from its first visible frame."""
    out = np.zeros(xy.shape[1])
    for n in range(xy.shape[1]):
        ts = np.flatnonzero(vis[:, n])
        true = xy[ts[0], n] + (pos[ts] - pos[ts[0]])
        out[n] = np.linalg.norm(xy[ts, n] - true, axis=-1).max()
    return out


def test_component_displacement_found_within_a_pixel():
    frames, masks, pos = _scene()
    gray = frames[..., 0]
    x, y = pos[0]
    for u in (1, 3):  # 20 px and, at gap 3, ~51 px
        inside_u = cv2.dilate(masks[u].astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
        m = match_component(
            gray[0], gray[u], np.ones((SIDE, SIDE), bool), (x, y, SIDE, SIDE), np.zeros(2), 32 * u, inside_u,
            min_score=0.6, min_inside=0.5,
        )  # fmt: skip
        assert m.reason == "matched" and m.score > 0.95
        np.testing.assert_allclose(m.displacement, pos[u] - pos[0], atol=1.0)


def test_object_flow_follows_the_square_inside_the_mask_only():
    frames, masks, pos = _scene()
    flows = compute_flows(frames, FlowConfig())
    stats: dict = {}
    out = object_flows(flows, masks, frames, MotionConfig(object_flow=True), FlowConfig(), stats=stats)
    assert stats["object_flow_matched"] > 0
    f = out[(0, 1)]
    err = np.linalg.norm(f.flow[masks[0]] - (pos[1] - pos[0]), axis=-1)
    # Template + DIS + the residual choice: nearly all of the square within 1 px (the old DIS flow: almost none).
    assert np.mean(err < 1.0) > 0.8
    assert np.mean(np.linalg.norm(flows[(0, 1)].flow[masks[0]] - (pos[1] - pos[0]), axis=-1) < 1.0) < 0.3
    # Far from the square (outside the dilated components) the pair is the old one, untouched.
    far = cv2.dilate(masks[0].astype(np.uint8), np.ones((15, 15), np.uint8)) == 0
    np.testing.assert_array_equal(f.flow[far], flows[(0, 1)].flow[far])
    np.testing.assert_array_equal(f.valid[far], flows[(0, 1)].valid[far])
    assert out is not flows and flows[(0, 1)] is not f  # the given flows are not modified


def test_chained_tracks_live_and_follow_fast_motion_only_with_object_flow():
    frames, masks, pos = _scene()
    stats: dict = {}
    xy_on, vis_on = _chain(frames, masks, True, stats)
    xy_off, vis_off = _chain(frames, masks, False)
    assert stats["object_flow_matched"] > 0 and xy_on.shape[1] > 0
    life_on = np.median(vis_on.sum(0))
    drift_on = _drift(xy_on, vis_on, pos)
    # Most of the 12 frames, on the true motion (2 px: sub-pixel matches carried over up to 11 steps).
    assert life_on >= 8
    assert np.median(drift_on) < 2.0
    # Without it DIS cannot follow 20 px per frame: tracks are much shorter or off the motion.
    good_off = (
        (vis_off.sum(0) >= 8) & (_drift(xy_off, vis_off, pos) < 2.0) if xy_off.shape[1] else np.zeros(0)
    )
    good_on = (vis_on.sum(0) >= 8) & (drift_on < 2.0)
    assert good_on.sum() >= 3 * max(1, good_off.sum())


def test_static_scene_gives_no_tracks_and_no_error():
    frames, masks, _ = _scene()
    empty = np.zeros_like(masks)
    stats: dict = {}
    xy, vis = _chain(frames, empty, True, stats)
    assert xy.shape == (T, 0, 2) and vis.shape == (T, 0)
    assert stats["object_flow_components"] == 0 and stats["object_flow_matched"] == 0


def test_flat_object_is_refused_not_matched():
    frames, masks, pos = _scene(flat=True)
    gray = frames[..., 0]
    x, y = pos[0]
    m = match_component(
        gray[0], gray[1], np.ones((SIDE, SIDE), bool), (x, y, SIDE, SIDE), np.zeros(2), 32, masks[1], 0.6, 0.5
    )
    assert m.displacement is None and m.reason == "flat"
    stats: dict = {}
    flows = compute_flows(frames, FlowConfig())
    cfg = MotionConfig(object_flow=True, track_mask_dilate_px=0)  # the template is the flat square alone
    out = object_flows(flows, masks, frames, cfg, FlowConfig(), stats=stats)
    assert stats["object_flow_matched"] == 0 and stats["object_flow_refused_flat"] > 0
    assert all(out[k] is flows[k] for k in flows)


def test_window_outside_the_image_and_a_low_score_are_refused():
    frames, masks, pos = _scene()
    gray = frames[..., 0]
    x, y = pos[0]
    tpl = np.ones((SIDE, SIDE), bool)
    # A prediction far off the image: the window clipped to the image is smaller than the template.
    m = match_component(
        gray[0], gray[1], tpl, (x, y, SIDE, SIDE), np.array([500.0, 0.0]), 16, masks[1], 0.6, 0.5
    )
    assert m.reason == "window"
    # The square's texture replaced in frame 1 (another object): no position scores 0.6.
    other = gray[1].copy()
    x1, y1 = pos[1]
    other[y1 : y1 + SIDE, x1 : x1 + SIDE] = _texture(np.random.default_rng(9), SIDE, SIDE, cell=2)
    m = match_component(gray[0], other, tpl, (x, y, SIDE, SIDE), np.zeros(2), 32, masks[1], 0.6, 0.5)
    assert m.displacement is None and m.reason == "score"
    # A mask of frame u nowhere near the search window: no candidate position.
    m = match_component(
        gray[0], gray[1], tpl, (x, y, SIDE, SIDE), np.zeros(2), 4, np.zeros((H, W), bool), 0.6, 0.5
    )
    assert m.reason == "mask"
