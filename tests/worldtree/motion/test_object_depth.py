"""A moving ball's depth from its drawn outline (size + path), against the ball's known geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.worldtree.motion.ball_scene import RADIUS, H, K, W, draw, rig, straight_path
from worldtree.motion.object_depth import ObjectDepthConfig, Piece, link_pieces, mask_pieces, object_depths


def test_a_ball_on_a_straight_line_is_placed_at_its_depth():
    T = 20
    w2cs = rig(T)
    masks, z, uv = draw(straight_path(T), w2cs)
    depth, objects = object_depths(masks, K.expand(T, 3, 3), w2cs, ObjectDepthConfig())
    assert len(objects) == 1 and objects[0]["placed"] and objects[0]["fit"] > 0.95  # pixel outlines: not exactly 1
    for k in range(T):
        u, v = int(round(uv[k, 0, 0])), int(round(uv[k, 0, 1]))
        front = z[k, 0] - RADIUS  # the ball's surface along the ray through its centre
        assert depth[k, v, u] == pytest.approx(front, rel=0.05)  # issue 28: within 5 %
    assert (depth[~masks] == 0).all()  # nothing outside the outline is touched


def test_an_object_that_turns_faster_than_the_cameras_is_not_placed():
    T = 20
    w2cs = rig(T)
    t = torch.arange(T, dtype=torch.float64)
    # a small loop every 3 frames: its own acceleration is larger than the cameras'
    centre = torch.stack(
        [0.25 * torch.cos(2.1 * t), 0.12 * torch.sin(2.1 * t), 1.7 + 0.2 * torch.sin(1.3 * t)], -1
    )
    masks, _, _ = draw(centre[:, None], w2cs)
    depth, objects = object_depths(masks, K.expand(T, 3, 3), w2cs, ObjectDepthConfig())
    assert objects and not any(o["placed"] for o in objects)
    assert (depth == 0).all()


def test_two_balls_that_cross_keep_their_own_chains():
    """While two outlines are drawn as one piece neither chain takes it; each resumes when they part."""
    T = 16
    w2cs = torch.eye(4, dtype=torch.float64).expand(T, 4, 4)
    t = torch.arange(T, dtype=torch.float64)
    a = torch.stack([-0.5 + 0.06 * t, torch.zeros(T), torch.full((T,), 2.0)], -1)
    b = torch.stack([0.4 - 0.05 * t, torch.full((T,), 0.02), torch.full((T,), 1.4)], -1)
    masks, z, _ = draw(torch.stack([a, b], 1), w2cs)
    cfg = ObjectDepthConfig()
    pieces = [mask_pieces(m, cfg.min_area)[1] for m in masks.numpy()]
    merged = [k for k, p in enumerate(pieces) if len(p) == 1]
    assert merged, "the balls should overlap in some frames"
    chains = link_pieces(pieces, math.hypot(H, W), cfg)
    assert len(chains) == 2
    for ch in chains:
        assert not set(ch.frames) & set(merged)
        # one ball per chain: the areas follow one ball's depth (b is nearer, so larger)
        areas = np.array([p.area for p in ch.pieces])
        assert areas.max() / areas.min() < 1.3


def test_pieces_below_the_area_floor_and_at_the_border_are_marked():
    mask = np.zeros((20, 30), bool)
    mask[5:9, 5:9] = True  # 16 px inside
    mask[0:3, 20:23] = True  # 9 px at the top border
    mask[15, 15] = True  # 1 px: noise
    _, pieces = mask_pieces(mask, min_area=6)
    assert sorted((p.area, p.border) for p in pieces) == [(9.0, True), (16.0, False)]
    inside = next(p for p in pieces if not p.border)
    assert isinstance(inside, Piece) and np.allclose(inside.centroid, [6.5, 6.5])


def test_settings_are_checked():
    with pytest.raises(ValueError, match="min_frames"):
        ObjectDepthConfig(min_frames=2)
    with pytest.raises(ValueError, match="min_fit"):
        ObjectDepthConfig(min_fit=1.5)
