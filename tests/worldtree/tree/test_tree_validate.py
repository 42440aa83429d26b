"""Held-out validation of tree children: which frames are held out, which child is kept, and the tree
dropping a rejected child so that its parent renders its frames."""

from __future__ import annotations

import json
import math

import pytest
import torch

from worldtree.tree.build import TreeConfig, grow_tree
from worldtree.tree.inherit import InheritConfig
from worldtree.tree.parallel import LayerRunner, ParallelConfig
from worldtree.tree.tpt import Interval, TemporalPartitionTree
from worldtree.tree.validate import HoldoutConfig, holdout_frames, keep_child


@pytest.mark.parametrize("n", [3, 5, 6, 10, 11, 20, 40])
@pytest.mark.parametrize("frac", [0.1, 0.2, 0.5])
def test_holdout_frames_are_interior_distinct_and_the_asked_share(n, frac):
    f = holdout_frames(n, frac)
    assert f == sorted(set(f))
    assert all(1 <= i <= n - 2 for i in f)  # never an end frame
    want = min(max(1, round(n * frac)), n - 2)
    assert len(f) == want
    # Spread: no two held-out frames closer than about the even spacing allows.
    if len(f) > 1:
        assert min(b - a for a, b in zip(f, f[1:], strict=False)) >= math.floor((n - 2) / len(f)) - 1


def test_holdout_frames_none_for_short_nodes_or_zero_share():
    assert holdout_frames(2, 0.5) == [] and holdout_frames(1, 0.2) == [] and holdout_frames(10, 0.0) == []


def _imgs(values):
    return [torch.full((4, 5, 3), float(v)) for v in values]


def test_keep_child_compares_held_out_l1_with_the_parent_closed_form():
    target = _imgs([0.5, 0.5])
    # Child off by 0.1 everywhere, parent by 0.2: L1 0.1 vs 0.2, PSNR 20 dB vs 13.98 dB.
    v = keep_child(_imgs([0.6, 0.4]), _imgs([0.7, 0.3]), target, [3, 6])
    assert v.keep and v.frames == [3, 6]
    assert v.child_l1 == pytest.approx(0.1, abs=1e-6) and v.parent_l1 == pytest.approx(0.2, abs=1e-6)
    assert v.child_psnr == pytest.approx(20.0, abs=1e-4)
    assert v.parent_psnr == pytest.approx(-10 * math.log10(0.04), abs=1e-4)


def test_an_over_fitting_child_is_rejected():
    # The child drew its own frames perfectly but the held-out ones worse than the parent, which saw them.
    target = _imgs([0.2, 0.8, 0.4])
    parent = [t + 0.05 for t in target]
    child = [t + 0.08 for t in target]
    v = keep_child(child, parent, target, [2, 5, 8])
    assert not v.keep and v.reason.startswith("rejected")


def test_keep_child_margin_and_ties():
    target = _imgs([0.5])
    # Equal errors: not kept (the child must do better, not as well).
    assert not keep_child(_imgs([0.6]), _imgs([0.6]), target, [1]).keep
    # 10 % better kept at margin 0.05, not at margin 0.2.
    assert keep_child(_imgs([0.59]), _imgs([0.6]), target, [1], margin=0.05).keep
    assert not keep_child(_imgs([0.59]), _imgs([0.6]), target, [1], margin=0.2).keep


def test_keep_child_rejects_non_finite_renders_and_keeps_without_frames():
    target = _imgs([0.5])
    assert not keep_child([torch.full((4, 5, 3), float("nan"))], _imgs([0.6]), target, [1]).keep
    assert keep_child([], [], [], []).keep


def test_holdout_config_ranges():
    with pytest.raises(ValueError, match="frac"):
        HoldoutConfig(frac=1.0)
    with pytest.raises(ValueError, match="margin"):
        HoldoutConfig(margin=-0.1)


def test_remove_leaf_gives_the_frames_back_to_the_parent():
    tree = TemporalPartitionTree(40, 12)
    tree.add_children(1, 20)
    tree.remove_leaf(3)
    assert tree.own_frames(1) == [Interval(20, 39)] and tree.covering(30) == 1 and tree.covering(5) == 2
    with pytest.raises(ValueError):
        tree.remove_leaf(1)
    tree.add_children(2, 10)
    with pytest.raises(ValueError, match="children"):
        tree.remove_leaf(2)


def test_grow_tree_drops_rejected_children(node_factory, tmp_path):
    root = node_factory(1, Interval(0, 59), num_dynamic=200)
    cfg = TreeConfig(depth=2, inherit=InheritConfig(caps=(80, 40)))
    fn = "benchmarks.fixtures.toy_nodes:reject_right_node"
    with LayerRunner(ParallelConfig(sequential=True, device="cpu"), fn) as r:
        res = grow_tree(root, cfg, r, tmp_path)
    # Right children (3, then 5) are rejected; node 2 is kept and split again; node 4 kept.
    assert res.rejected == [3, 5]
    assert sorted(res.states) == [1, 2, 4]
    assert res.tree.rendering_nodes() == [1, 2, 4]
    assert res.tree.covering(45) == 1 and res.tree.covering(20) == 2 and res.tree.covering(3) == 4
    rec = json.loads((tmp_path / "tree.json").read_text())
    assert rec["rejected"] == [3, 5] and "3" not in rec["tree"]["nodes"]
