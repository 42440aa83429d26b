"""``--depth auto`` criterion: a node whose frames hold two incompatible motions is split, a static node and a
node whose one motion its model follows are not.

The stand-in node model is "one canonical space with one motion": frame 0 moved by the single integer image
shift that best explains each frame (found by brute force over shifts). It follows one translating object
exactly, but not two objects moving in opposite directions, which is what the criterion must detect.
"""

from __future__ import annotations

import torch

from worldtree.tree.adaptive import AutoSplitConfig, decide_split, residual_stats

T, H, W = 16, 24, 48


def _video(objects: list[tuple[int, int, int]]) -> torch.Tensor:
    """[T, H, W, 3] grey background with 6x6 squares ``(row, col0, velocity px/frame)``."""
    v = torch.full((T, H, W, 3), 0.5)
    for t in range(T):
        for row, col0, vel in objects:
            c = col0 + vel * t
            v[t, row : row + 6, c : c + 6] = torch.tensor([1.0, 0.2, 0.1])
    return v


def _one_motion_fit(video: torch.Tensor) -> torch.Tensor:
    """Per-pixel L1 residual [T, H, W] of the best single-shift model of each frame from frame 0."""
    res = []
    for t in range(T):
        best = None
        for s in range(-T, T + 1):
            pred = torch.roll(video[0], shifts=s, dims=1)
            r = (pred - video[t]).abs().mean(-1)
            if best is None or r.sum() < best.sum():
                best = r
        res.append(best)
    return torch.stack(res)


def _dynamic_mask(video: torch.Tensor) -> torch.Tensor:
    """Pixels that differ from the per-pixel temporal median (a motion mask computed from the frames)."""
    med = video.median(dim=0).values
    return (video - med).abs().amax(-1) > 0.05


def test_two_incompatible_motions_split():
    v = _video([(4, 4, 1), (14, 40, -1)])
    d = decide_split(_one_motion_fit(v), _dynamic_mask(v), min_len=12)
    assert d.split, d.reason
    assert d.excess >= AutoSplitConfig().min_excess


def test_static_node_not_split():
    v = _video([(4, 4, 0)])
    d = decide_split(_one_motion_fit(v), _dynamic_mask(v), min_len=12)
    assert not d.split
    assert d.reason.startswith("near-static")
    assert d.dynamic_fraction == 0.0


def test_one_followed_motion_not_split():
    v = _video([(4, 4, 1)])
    d = decide_split(_one_motion_fit(v), _dynamic_mask(v), min_len=12)
    assert not d.split
    assert d.reason.startswith("motion fit")


def test_short_node_is_a_leaf_whatever_its_error():
    v = _video([(4, 4, 1), (14, 40, -1)])
    d = decide_split(_one_motion_fit(v)[:8], _dynamic_mask(v)[:8], min_len=12)
    assert not d.split and d.reason.startswith("interval")


def test_residual_stats_by_hand():
    r = torch.zeros(2, 2, 2)
    r[0, 0, 0], r[1, 1, 1], r[0, 1, 1] = 0.4, 0.2, 0.1
    m = torch.zeros(2, 2, 2, dtype=torch.bool)
    m[0, 0, 0] = m[1, 1, 1] = True
    st = residual_stats(r, m)
    assert abs(st["dynamic_error"] - 0.3) < 1e-6  # float32 inputs
    assert abs(st["static_error"] - 0.1 / 6) < 1e-6  # float32 inputs
    assert abs(st["dynamic_fraction"] - 0.25) < 1e-6  # float32 inputs
    r[0, 0, 1] = float("nan")  # ignored, not propagated
    assert all(torch.isfinite(torch.tensor(list(residual_stats(r, m).values()))))
