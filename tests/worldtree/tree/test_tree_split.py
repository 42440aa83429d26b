"""Split strategies on hand-made gradient and flow profiles, fall-backs, and the profile builders."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from worldtree.priors.flow import FlowPair
from worldtree.tree.split import (
    ProfileAccumulator,
    balanced_split,
    binary_split,
    build_intervals,
    choose_split,
    flow_profile,
)
from worldtree.tree.tpt import Interval


def brute_balance(w: np.ndarray, start: int, lo: int, hi: int) -> int:
    """Independent reference: try every allowed P, keep the smallest |left - right| (ties: nearest binary)."""
    binary = start + (len(w) - 1) // 2
    best = None
    for p in range(lo, hi + 1):
        k = p - start
        key = (abs(w[:k].sum() - w[k:].sum()), abs(p - binary), p)
        best = key if best is None or key < best else best
    return best[2]


def test_split_binary_is_floor_mid():
    assert binary_split(Interval(0, 159)) == 79
    assert binary_split(Interval(79, 159)) == 119
    assert choose_split("binary", Interval(0, 78)).point == 39


def test_split_gradient_slow_then_fast():
    # 40 slow frames (gradient 1) then 40 fast ones (gradient 3): half the total (160 / 2 = 80) is reached
    # at frame 40 + 40/3 = 53.33 -> left [0, 52] sums 40 + 13*3 = 79, [0, 53] sums 82; |79-81| = 2 < |82-78| = 4.
    w = np.r_[np.ones(40), np.full(40, 3.0)]
    c = choose_split("gradient", Interval(0, 79), w)
    assert c.fallback is None and c.point == 53
    assert c.point == brute_balance(w, 0, 5, 75)
    # Shifted interval: same local answer, global frames.
    c2 = choose_split("gradient", Interval(100, 179), torch.tensor(w))
    assert c2.point == 153


def test_split_flow_matches_brute_force_on_random_profiles():
    rng = np.random.default_rng(0)
    for _ in range(50):
        n = int(rng.integers(12, 90))
        start = int(rng.integers(0, 50))
        w = rng.gamma(0.5, size=n)
        c = choose_split("flow", Interval(start, start + n - 1), w)
        if c.fallback is None:
            assert c.point == brute_balance(w, start, start + 5, start + n - 5)


def test_split_uniform_profile_is_balanced_halves():
    # Even length: exact halves (80 + 80), one frame right of the binary point 79.
    assert choose_split("gradient", Interval(0, 159), np.ones(160)).point == 80
    # Odd length: two equally good points, the tie goes to the binary one.
    assert choose_split("gradient", Interval(79, 159), np.ones(81)).point == 119


@pytest.mark.parametrize(
    "profile, reason",
    [
        (np.zeros(40), "all-zero"),
        (np.r_[np.ones(20), np.nan, np.ones(19)], "non-finite"),
        (np.r_[np.ones(20), -1.0, np.ones(19)], "negative"),
        (np.r_[100.0, np.zeros(39)], "single spike"),  # one spike at the start
        (np.r_[np.zeros(39), 100.0], "single spike"),  # one spike at the end
        (np.r_[np.zeros(17), 5.0, np.zeros(22)], "single spike"),  # one spike anywhere balances nothing
        (np.r_[0.0, 1.0, 1.0, np.zeros(37)], "outside"),  # mass in frames 1-2: balance at P = 12 < 15
    ],
)
def test_split_degenerate_profiles_fall_back_to_binary(profile, reason):
    c = choose_split("gradient", Interval(10, 49), profile)
    assert c.point == 29 and c.fallback is not None and reason in c.fallback


def test_split_children_respect_minimum_and_missing_profile():
    # Mass just past the allowed edge -> fallback; mass at the edge -> used.
    iv = Interval(0, 29)
    w = np.zeros(30)
    w[4] = w[5] = 1.0  # perfect balance at P = 5, the first allowed point (range [5, 25])
    assert balanced_split(iv, w).point == 5
    w = np.zeros(30)
    w[2] = w[3] = 1.0  # perfect balance at P = 3 < 5 -> fallback to binary 14
    c = balanced_split(iv, w)
    assert c.point == 14 and "outside" in c.fallback
    c = choose_split("flow", iv, None)
    assert c.point == 14 and c.fallback == "no profile"
    with pytest.raises(ValueError):
        choose_split("median", iv)
    with pytest.raises(ValueError):
        choose_split("gradient", iv, np.ones(29))  # wrong length
    with pytest.raises(ValueError):
        choose_split("binary", Interval(0, 10))  # 11 frames: a leaf


def test_split_build_intervals_with_global_flow_profile():
    # Motion only in the last quarter: the root splits inside it, every node keeps >= 5 frames.
    prof = np.r_[np.full(120, 0.01), np.full(40, 1.0)]
    tree = build_intervals(160, 2, split="flow", profile=prof)
    p = tree.interval(3).start
    left_sum, right_sum = prof[:p].sum(), prof[p:].sum()
    assert abs(left_sum - right_sum) <= prof.max()
    assert p > 120
    assert all(tree.interval(j).length >= 5 for j in tree)


def test_split_profile_accumulator_means_per_visit():
    acc = ProfileAccumulator(4)
    for f, v in [(0, 1.0), (0, 3.0), (1, 4.0), (3, float("nan")), (3, torch.tensor(-2.0))]:
        acc.add(f, v)
    # frame 0: (1+3)/2, frame 1: 4, frame 3: |-2| (NaN skipped), frame 2 unseen -> mean of seen (2+4+2)/3.
    np.testing.assert_allclose(acc.profile(), [2.0, 4.0, 8.0 / 3.0, 2.0])
    assert acc.skipped == 1
    again = ProfileAccumulator(4)
    again.load_state_dict(acc.state_dict())
    np.testing.assert_allclose(again.profile(), acc.profile())
    assert not ProfileAccumulator(3).profile().any()


def test_split_flow_profile_dynamic_pixels_only():
    T, H, W = 3, 4, 5
    mask = np.zeros((T, H, W), bool)
    mask[0, :2] = True  # frame 0: top two rows dynamic
    mask[1, :, :1] = True
    f01 = np.zeros((H, W, 2), np.float32)
    f01[:2] = (3.0, 4.0)  # |f| = 5 on the dynamic rows
    f01[2:] = (100.0, 0.0)  # large static flow must not count
    f02 = np.zeros((H, W, 2), np.float32)
    f02[:2] = (6.0, 8.0)  # |f| = 10 over 2 frames -> 5 per frame
    f10 = np.full((H, W, 2), (0.0, 2.0), np.float32)
    valid = np.ones((H, W), bool)
    flows = {(0, 1): FlowPair(f01, valid), (0, 2): (f02, valid), (1, 0): FlowPair(f10, valid)}
    prof = flow_profile(flows, mask)
    np.testing.assert_allclose(prof, [5.0, 2.0, 0.0])
