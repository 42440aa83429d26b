"""Preview images: colours mean what the documentation says."""

from __future__ import annotations

import numpy as np

from worldtree.priors.preview import colorize_depth, draw_tracks, overlay_mask, preview_frames


def test_depth_colours_near_warm_far_cold_and_low_confidence_dark():
    depth = np.full((10, 20), 10.0, np.float32)
    depth[:, :10] = 1.0  # left half near
    conf = np.ones_like(depth)
    conf[0, 0] = 0
    rgb = colorize_depth(depth, conf)
    near, far = rgb[5, 2].astype(int), rgb[5, 15].astype(int)
    assert near[0] > near[2] and far[2] > far[0]
    assert rgb[0, 0].sum() < rgb[1, 0].sum()


def test_overlay_and_tracks():
    img = np.full((10, 12, 3), 100, np.uint8)
    mask = np.zeros((10, 12), bool)
    mask[2:4, 2:4] = True
    out = overlay_mask(img, mask)
    assert out[3, 3, 0] > 150 and out[3, 3, 1] < 100 and (out[8, 8] == 100).all()
    assert overlay_mask(img, mask, np.zeros((10, 12))).shape == (10, 24, 3)
    tracks = np.array([[[5.0, 5.0]], [[6.0, 5.0]]], np.float32)
    vis = np.ones((2, 1), bool)
    drawn = draw_tracks(img, tracks, vis, np.array([True]), t=1)
    assert tuple(drawn[5, 6]) == (255, 40, 40)  # dynamic = red
    drawn = draw_tracks(img, tracks, vis, np.array([False]), t=1)
    assert tuple(drawn[5, 6]) == (40, 230, 40)  # static = green


def test_preview_frames():
    assert preview_frames(3) == [0, 1, 2]
    f = preview_frames(160, 6)
    assert f[0] == 0 and f[-1] == 159 and len(f) == 6
