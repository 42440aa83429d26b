"""``--depth auto`` in the tree builder: only nodes whose decision says so get children, branches differ,
the depth bound and the minimum interval still hold, and every node's decision is recorded."""

from __future__ import annotations

import json

from worldtree.tree.adaptive import AutoSplitConfig
from worldtree.tree.build import TreeConfig, grow_tree, node_output, read_node_input
from worldtree.tree.inherit import InheritConfig
from worldtree.tree.parallel import LayerRunner, NodeContext, ParallelConfig
from worldtree.tree.tpt import Interval

FAST_FROM = 20
"""Stand-in scene: frames from 20 on move fast, so a node holding any of them asks to be split."""


def fast_half_node(payload: dict, ctx: NodeContext) -> dict:
    state, depth = read_node_input(payload)
    iv = state.interval
    split = iv.end >= FAST_FROM
    dec = {"split": split, "reason": "fast frames" if split else "slow frames"}
    return node_output(state, None, {"auto_split": dec, "depth": depth})


def _grow(node_factory, tmp_path, max_depth: int, root_split: bool = True):
    root = node_factory(1, Interval(0, 39), num_dynamic=100)
    cfg = TreeConfig(depth=0, inherit=InheritConfig(caps=(60, 30)), auto=AutoSplitConfig(max_depth=max_depth))
    with LayerRunner(ParallelConfig(sequential=True, device="cpu"), fast_half_node) as r:
        return grow_tree(root, cfg, r, tmp_path, root_decision={"split": root_split, "reason": "root"})


def test_auto_splits_only_where_asked(node_factory, tmp_path):
    res = _grow(node_factory, tmp_path, max_depth=4)
    # Root [0, 39] -> 2 [0, 19] (slow: leaf), 3 [20, 39] -> 6 [20, 29], 7 [30, 39]: both under 12 frames.
    assert sorted(res.tree.intervals) == [1, 2, 3, 6, 7]
    assert res.tree.leaves() == [2, 6, 7]
    assert res.decisions[2]["applied"] is False and res.decisions[2]["reason"] == "slow frames"
    assert res.decisions[3]["applied"] is True
    assert res.decisions[6]["split"] is True and res.decisions[6]["applied"] is False
    assert "min_len" in res.decisions[6]["reason"]
    rec = json.loads((tmp_path / "tree.json").read_text())
    assert set(rec["auto"]) == {"1", "2", "3", "6", "7"}


def test_auto_respects_depth_bound_and_a_static_root(node_factory, tmp_path):
    res = _grow(node_factory, tmp_path / "a", max_depth=1)
    assert sorted(res.tree.intervals) == [1, 2, 3] and res.decisions[3]["applied"] is False
    res = _grow(node_factory, tmp_path / "b", max_depth=4, root_split=False)
    assert sorted(res.tree.intervals) == [1] and res.layers == []
