"""``--depth auto`` criterion: a node whose frames hold two incompatible motions is split, a static node and a
node whose one motion its model follows are not.

The stand-in node model is "one canonical space with one motion": frame 0 moved by the single integer image
shift that best explains each frame (found by brute force over shifts). It follows one translating object
exactly, but not two objects moving in opposite directions, which is what the criterion must detect.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from worldtree.tree.adaptive import (
    AutoSplitConfig,
    assess_fit,
    decide_child,
    decide_fit_split,
    decide_split,
    depth_conf_sums,
    moving_depth_conf,
    residual_stats,
    residual_sums,
    scaffold_motion_px,
    stats_of_sums,
)

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


# The video's camera: identity pose, unit focal length, so a point (x, y, 1) is seen at pixel (x, y).
K1 = torch.eye(3).expand(T, 3, 3)
POSE = torch.eye(4).expand(T, 4, 4)


def _scaffold(objects: list[tuple[int, int, int]]) -> torch.Tensor:
    """``[T, M, 3]`` scaffold nodes at the squares' centres (one node per square), depth 1."""
    t = torch.arange(T, dtype=torch.float32)[:, None]
    cols = torch.tensor([c0 + 3.0 for _, c0, _ in objects]) + t * torch.tensor([float(v) for *_, v in objects])
    rows = torch.tensor([r + 3.0 for r, _, _ in objects]).expand(T, -1)
    return torch.stack([cols, rows, torch.ones_like(cols)], -1)


def test_two_incompatible_motions_split():
    objects = [(4, 4, 1), (14, 40, -1)]
    v = _video(objects)
    motion = scaffold_motion_px(_scaffold(objects), K1, POSE)
    # 1 px per frame; the 5-frame averages are centred on frames 2..13, the middle one on frame 8 -> 6 px at most
    assert abs(motion - 6.0) < 1e-6
    d = decide_split(_one_motion_fit(v), _dynamic_mask(v), min_len=12, motion_px=motion)
    assert d.split, d.reason
    assert d.excess >= AutoSplitConfig().min_excess
    assert d.motion_px == motion and abs(d.motion_min_px - 0.10 * W) < 1e-9


def test_static_node_not_split():
    v = _video([(4, 4, 0)])
    motion = scaffold_motion_px(_scaffold([(4, 4, 0)]), K1, POSE)
    d = decide_split(_one_motion_fit(v), _dynamic_mask(v), min_len=12, motion_px=motion)
    assert not d.split
    assert d.reason.startswith("near-static")
    assert d.dynamic_fraction == 0.0 and motion == 0.0


def test_under_modelled_still_object_not_split():
    # The near-static failure: a (barely) moving object that the node has not reconstructed yet (its model
    # shows background there) has a large residual excess, but splitting time cannot help: its scaffold
    # hardly moves, so the node stays a leaf. Without the motion measurement it would be split.
    objects = [(4, 4, 0), (14, 30, 0)]
    v = _video(objects)
    background = torch.full_like(v, 0.5)
    residual = (background - v).abs().mean(-1)
    mask = (v - background).abs().amax(-1) > 0.05  # the priors mark the objects as dynamic
    pos = _scaffold(objects)
    pos[:, :, 0] += 0.1 * torch.arange(T, dtype=torch.float32)[:, None]  # 0.1 px per frame
    motion = scaffold_motion_px(pos, K1, POSE)
    assert abs(motion - 0.6) < 1e-5
    assert decide_split(residual, mask, min_len=12).split  # residual alone: split
    d = decide_split(residual, mask, min_len=12, motion_px=motion)
    assert not d.split and d.reason.startswith("near-static: scaffold motion"), d.reason
    assert d.excess >= AutoSplitConfig().min_excess


def test_scaffold_motion_equals_brute_force_projection():
    g = torch.Generator().manual_seed(4)
    Tn, M = 7, 9
    pos = torch.randn(Tn, M, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 4.0])
    Ks = torch.tensor([[50.0, 0.0, 30.0], [0.0, 55.0, 20.0], [0.0, 0.0, 1.0]]).repeat(Tn, 1, 1)
    Ks[:, 0, 0] += torch.arange(Tn, dtype=torch.float32)  # a zoom, to check each frame's own camera
    w2cs = torch.eye(4).repeat(Tn, 1, 1)
    w2cs[:, 0, 3] = torch.linspace(-0.5, 0.5, Tn)  # a moving camera: its motion is not the scene's
    pos[:, 2] = pos[Tn // 2, 2]  # node 2 does not move: 0 px however the camera moves
    per_node = []
    for m in range(M):
        best = 0.0
        for t in range(Tn):
            def pix(x, t=t):
                c = w2cs[t, :3, :3].double() @ x.double() + w2cs[t, :3, 3].double()
                return torch.stack([Ks[t, 0, 0] * c[0] / c[2] + Ks[t, 0, 2], Ks[t, 1, 1] * c[1] / c[2] + Ks[t, 1, 2]])

            best = max(best, float((pix(pos[t, m]) - pix(pos[Tn // 2, m])).norm()))
        per_node.append(best)
    assert per_node[2] < 1e-9
    expect = float(torch.quantile(torch.tensor(per_node, dtype=torch.float64), 0.9))
    got = scaffold_motion_px(pos, Ks, w2cs, smooth=1)
    assert abs(got - expect) < 1e-6 * max(1.0, expect)
    assert scaffold_motion_px(pos[:, :0], Ks, w2cs) == 0.0 and scaffold_motion_px(pos[:1], Ks[:1], w2cs[:1]) == 0.0


def test_scaffold_motion_ignores_frame_to_frame_jitter():
    # A still node that jitters by +-2 px from frame to frame (an optimised trajectory's noise) against one
    # moving steadily by 0.5 px per frame: unsmoothed, the jitter looks like motion; averaged over 5 frames
    # it nearly vanishes while the steady motion stays.
    t = torch.arange(T, dtype=torch.float32)
    jitter = torch.stack([10.0 + 2.0 * (-1.0) ** t, torch.full_like(t, 5.0), torch.ones_like(t)], -1)
    steady = torch.stack([20.0 + 0.5 * t, torch.full_like(t, 5.0), torch.ones_like(t)], -1)
    assert scaffold_motion_px(jitter[:, None], K1, POSE, quantile=1.0, smooth=1) == 4.0
    assert scaffold_motion_px(jitter[:, None], K1, POSE, quantile=1.0) <= 0.8 + 1e-6  # 4 px / 5 frames
    assert abs(scaffold_motion_px(steady[:, None], K1, POSE, quantile=1.0) - 0.5 * 6.0) < 1e-5


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


class _StubFit:
    """A trained fit as :func:`decide_fit_split` reads it: residuals on its own frames, its scaffold's
    trajectories ``[T, 1, 3]`` (one node, image-plane coordinates at depth 1) and its cameras."""

    def __init__(self, residual: torch.Tensor, pos: torch.Tensor):
        self._residual, self.scaffold, self.Ks = residual, type("S", (), {"pos": pos})(), K1
        self.rendered = 0

    def residuals(self) -> torch.Tensor:
        self.rendered += 1
        return self._residual

    def cameras(self) -> torch.Tensor:
        return POSE


def test_decide_fit_split_uses_the_fits_residual_and_scaffold_and_records_its_cost():
    # Two incompatible motions leave a large excess; whether the node splits then depends on how far its
    # scaffold moves on screen: a still scaffold keeps it a leaf, one crossing the image splits it.
    video = _video([(4, 4, 1), (14, 30, -1)])
    residual, mask = _one_motion_fit(video), _dynamic_mask(video)
    t = torch.arange(T, dtype=torch.float32)
    still = torch.stack([torch.full_like(t, 20.0), torch.full_like(t, 5.0), torch.ones_like(t)], -1)[:, None]
    moving = torch.stack([2.0 + 2.5 * t, torch.full_like(t, 5.0), torch.ones_like(t)], -1)[:, None]
    fit = _StubFit(residual, still)
    d = decide_fit_split(fit, mask, min_len=12, cfg=AutoSplitConfig())
    assert fit.rendered == 1 and not d.split and d.motion_px == 0.0
    assert d.reason.startswith("near-static: scaffold motion")
    d = decide_fit_split(_StubFit(residual, moving), mask, min_len=12, cfg=AutoSplitConfig())
    # 2.5 px per frame; the 5-frame averages are centred on frames 2..13, the middle one on frame 8, so the
    # farthest is 6 frames away: 15 px against a threshold of 10 % of W = 4.8 px.
    assert d.split and abs(d.motion_px - 2.5 * 6) < 1e-4 and abs(d.motion_min_px - 0.10 * W) < 1e-9
    assert d.test_cpu_s is not None and 0.0 <= d.test_cpu_s < float("inf")
    assert decide_split(residual, mask, min_len=12).test_cpu_s is None  # a residual given: nothing measured


def test_residual_sums_pool_to_the_stats_of_any_run_of_frames():
    g = torch.Generator().manual_seed(3)
    r = torch.rand(6, 5, 7, generator=g)
    m = torch.rand(6, 5, 7, generator=g) > 0.7
    r[2, 1, 1] = float("inf")  # ignored like residual_stats does
    sums = residual_sums(r, m)
    assert sums.shape == (6, 4) and sums.dtype == torch.float64
    for a, b in [(0, 6), (0, 3), (3, 6), (2, 2)]:
        rr, mm = r[a:b], m[a:b]
        ok = torch.isfinite(rr)
        dyn, sta = rr[mm & ok].double(), rr[~mm & ok].double()  # brute force over the pixels of those frames
        st = stats_of_sums(sums[a:b])
        assert abs(st["dynamic_error"] - (float(dyn.mean()) if len(dyn) else 0.0)) < 1e-12
        assert abs(st["static_error"] - (float(sta.mean()) if len(sta) else 0.0)) < 1e-12
        n = int(ok.sum())
        assert abs(st["dynamic_fraction"] - (len(dyn) / n if n else 0.0)) < 1e-12


def _half_still_half_moving(speed: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A square still over frames 0-7, moving ``speed`` px/frame along x over frames 8-15: the scaffold (one
    node at its centre, image-plane coordinates at depth 1), its dynamic mask, and a residual of 0.3 on its
    pixels over the moving frames and 0.01 everywhere else (the parent's one canonical space misses the
    moving half)."""
    t = torch.arange(T, dtype=torch.float32)
    x = 10.0 + speed * (t - 7).clamp(min=0)
    pos = torch.stack([x, torch.full_like(t, 8.0), torch.ones_like(t)], -1)[:, None]
    mask = torch.zeros(T, H, W, dtype=torch.bool)
    for k in range(T):
        c = int(x[k]) - 3
        mask[k, 5:11, c : c + 6] = True
    residual = torch.full((T, H, W), 0.01)
    residual[8:][mask[8:]] = 0.3
    return pos, mask, residual


def test_decide_child_trains_only_the_moving_half():
    pos, mask, residual = _half_still_half_moving(3.0)
    measured = {"sums": residual_sums(residual, mask), "Ks": K1, "image_size": [H, W]}
    cfg = AutoSplitConfig()
    calm = decide_child(pos, POSE, 0, measured, (0, 7), cfg)
    fast = decide_child(pos, POSE, 0, measured, (8, 15), cfg)
    assert not calm.train and calm.reason.startswith("not trained: near-static: scaffold motion")
    assert calm.motion_px == 0.0 and calm.frames == [0, 7]
    # 8 frames, 5-frame averages centred on local frames 2..5, the middle one on 4: at most 2 frames away at
    # 3 px per frame = 6 px, above 10 % of W = 4.8 px; the moving pixels' error 0.3 against 0.01.
    assert fast.train and fast.reason.startswith("trained: excess")
    assert abs(fast.motion_px - 6.0) < 1e-5 and abs(fast.motion_min_px - 0.1 * W) < 1e-9
    assert abs(fast.dynamic_error - 0.3) < 1e-6 and abs(fast.static_error - 0.01) < 1e-6
    assert abs(fast.excess - 0.29) < 1e-6
    # A parent that already fits the moving half (same error on moving and static pixels): not trained.
    fitted = {**measured, "sums": residual_sums(torch.full((T, H, W), 0.01), mask)}
    d = decide_child(pos, POSE, 0, fitted, (8, 15), cfg)
    assert not d.train and d.reason.startswith("not trained: motion fit")
    # Frames are global: the same parent starting at frame 100.
    assert decide_child(pos, POSE, 100, measured, (108, 115), cfg).motion_px == fast.motion_px
    with pytest.raises(ValueError):
        decide_child(pos, POSE, 0, measured, (8, 16), cfg)


def test_assess_fit_measures_once_for_the_split_and_the_children():
    pos, mask, residual = _half_still_half_moving(3.0)
    fit = _StubFit(residual, pos)
    a = assess_fit(fit, mask, min_len=12, cfg=AutoSplitConfig())
    assert fit.rendered == 1
    assert torch.equal(a.sums, residual_sums(residual, mask)) and a.image_size == (H, W)
    assert a.decision == dataclasses.replace(decide_split(residual, mask, 12, motion_px=a.decision.motion_px),
                                             test_cpu_s=a.decision.test_cpu_s)  # fmt: skip
    payload = a.to_payload()
    assert payload["sums"].dtype == torch.float64 and payload["image_size"] == [H, W]


@pytest.mark.parametrize(
    ("static_err", "dynamic_err", "split"),
    [
        (0.004, 0.009, True),  # smooth texture: excess 0.005 < 0.01 but >= half the static error (0.002)
        (0.004, 0.0055, False),  # excess 0.0015 < the 0.002 floor
        (0.030, 0.039, False),  # fine texture: excess 0.009 < min(0.01, 0.015)
        (0.030, 0.041, True),  # excess 0.011 >= 0.01
        (0.0, 0.0, False),  # an exact fit never splits
    ],
)
def test_excess_bar_is_relative_to_the_static_error_with_a_floor(static_err, dynamic_err, split):
    # Residuals constant per region: the pooled statistics are the given errors exactly.
    mask = torch.zeros(T, H, W, dtype=torch.bool)
    mask[:, 4:10, 4:20] = True
    residual = torch.where(mask, torch.tensor(dynamic_err), torch.tensor(static_err))
    d = decide_split(residual, mask, min_len=12, motion_px=100.0)
    assert d.split == split, d.reason
    assert abs(d.excess - (dynamic_err - static_err)) < 1e-6


def test_unmeasured_moving_depth_keeps_the_node_a_leaf():
    # Two incompatible motions split when the depth prior measures the moving pixels; where it only fills them
    # (confidence 0 there, as the classical depth) the node stays a leaf, whatever the static pixels' confidence.
    objects = [(4, 4, 1), (14, 40, -1)]
    v = _video(objects)
    residual, mask = _one_motion_fit(v), _dynamic_mask(v)
    motion = scaffold_motion_px(_scaffold(objects), K1, POSE)
    measured = torch.where(mask, torch.tensor(1.0), torch.tensor(0.0))
    filled = torch.where(mask, torch.tensor(0.0), torch.tensor(1.0))
    d = decide_split(residual, mask, min_len=12, motion_px=motion, depth_conf=measured)
    assert d.split and d.dynamic_depth_conf == 1.0, d.reason
    d = decide_split(residual, mask, min_len=12, motion_px=motion, depth_conf=filled)
    assert not d.split and d.reason.startswith("depth unmeasured") and d.dynamic_depth_conf == 0.0
    # The bar is the mean over the moving pixels: 0.6 on every one passes 0.5, 0.4 does not; 0 turns it off.
    assert decide_split(residual, mask, 12, motion_px=motion, depth_conf=torch.full_like(residual, 0.6)).split
    assert not decide_split(residual, mask, 12, motion_px=motion, depth_conf=torch.full_like(residual, 0.4)).split
    off = AutoSplitConfig(min_depth_conf=0.0)
    assert decide_split(residual, mask, 12, off, motion_px=motion, depth_conf=filled).split
    # Without a confidence the test is skipped (the decision of the earlier criterion).
    assert decide_split(residual, mask, 12, motion_px=motion).dynamic_depth_conf is None
    # Long children are exempt: with halves of 8 frames a bar of 8 frames lifts the test, one of 9 keeps it.
    assert decide_split(residual, mask, 12, AutoSplitConfig(depth_test_below=8), motion_px=motion,
                        depth_conf=filled).split  # fmt: skip
    assert not decide_split(residual, mask, 12, AutoSplitConfig(depth_test_below=9), motion_px=motion,
                            depth_conf=filled).split  # fmt: skip
    with pytest.raises(ValueError):
        AutoSplitConfig(min_depth_conf=1.5)
    with pytest.raises(ValueError):
        AutoSplitConfig(depth_test_below=-1)


def test_depth_conf_sums_pool_to_the_mean_over_any_run_of_frames():
    g = torch.Generator().manual_seed(5)
    conf = torch.rand(6, 5, 7, generator=g)
    conf[1, 2, 3] = float("nan")  # counts 0
    m = torch.rand(6, 5, 7, generator=g) > 0.6
    cs = depth_conf_sums(conf, m)
    assert cs.shape == (6,) and cs.dtype == torch.float64
    clean = torch.nan_to_num(conf, nan=0.0).double()
    sums = residual_sums(torch.zeros(6, 5, 7), m)
    for a, b in [(0, 6), (1, 4), (5, 6)]:
        brute = float(clean[a:b][m[a:b]].mean())  # over the dynamic pixels of those frames
        assert abs(float(cs[a:b].sum()) / float(sums[a:b, 1].sum()) - brute) < 1e-12
    with pytest.raises(ValueError):
        depth_conf_sums(conf[0], m[0])


def test_moving_depth_conf_is_the_masked_mean():
    g = torch.Generator().manual_seed(0)
    conf = torch.rand(3, 5, 7, generator=g)
    mask = torch.rand(3, 5, 7, generator=g) > 0.6
    expected = float(conf.double()[mask].mean())
    assert moving_depth_conf(conf, mask) == pytest.approx(expected, rel=1e-12)
    first = tuple(mask.nonzero()[0])
    conf[first] = float("nan")  # a non-finite confidence counts as none
    zeroed = conf.double().nan_to_num(0.0)
    assert moving_depth_conf(conf, mask) == pytest.approx(float(zeroed[mask].mean()), rel=1e-12)
    assert moving_depth_conf(conf, torch.zeros_like(mask)) is None  # nothing moves


def test_decide_child_reads_the_parents_depth_confidence():
    # The moving half's pixels are measured on frames 8-11 only: the child of frames 8-15 averages 0.5 (trained);
    # with nothing measured it is not; the parent's record without a confidence decides as before.
    pos, mask, residual = _half_still_half_moving(3.0)
    conf = torch.zeros(T, H, W)
    conf[8:12] = 1.0
    sums = residual_sums(residual, mask)
    measured = {"sums": sums, "Ks": K1, "image_size": [H, W], "conf_sums": depth_conf_sums(conf, mask)}
    cfg = AutoSplitConfig()
    fast = decide_child(pos, POSE, 0, measured, (8, 15), cfg)
    assert fast.train and abs(fast.dynamic_depth_conf - 0.5) < 1e-12
    filled = {**measured, "conf_sums": depth_conf_sums(torch.zeros(T, H, W), mask)}
    d = decide_child(pos, POSE, 0, filled, (8, 15), cfg)
    assert not d.train and d.reason.startswith("not trained: depth unmeasured") and d.dynamic_depth_conf == 0.0
    # A child of 8 frames is exempt under a bar of 8, not under one of 9.
    assert decide_child(pos, POSE, 0, filled, (8, 15), dataclasses.replace(cfg, depth_test_below=8)).train
    assert not decide_child(pos, POSE, 0, filled, (8, 15), dataclasses.replace(cfg, depth_test_below=9)).train
    legacy = {k: v for k, v in measured.items() if k != "conf_sums"}
    d = decide_child(pos, POSE, 0, legacy, (8, 15), cfg)
    assert d.train and d.dynamic_depth_conf is None
    fit = _StubFit(residual, pos)
    payload = assess_fit(fit, mask, 12, cfg, depth_conf=conf).to_payload()
    assert torch.equal(payload["conf_sums"], depth_conf_sums(conf, mask))
    assert "conf_sums" not in assess_fit(fit, mask, 12, cfg).to_payload()
