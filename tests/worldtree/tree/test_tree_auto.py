"""``--depth auto`` in the tree builder: only nodes whose decision says so get children, branches differ,
the depth bound and the minimum interval still hold, and every node's decision is recorded."""

from __future__ import annotations

import json

import torch

from worldtree.motion.scaffold import Scaffold, ScaffoldConfig
from worldtree.tree.adaptive import AutoSplitConfig
from worldtree.tree.build import TreeConfig, grow_tree, node_output, read_node_input
from worldtree.tree.inherit import InheritConfig
from worldtree.tree.node import NodeState
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


def leaf_node(payload: dict, ctx: NodeContext) -> dict:
    """A trained child that asks for no children of its own."""
    state, depth = read_node_input(payload)
    return node_output(state, None, {"auto_split": {"split": False, "reason": "leaf"}, "depth": depth})


def _root_moving_from(node_factory, first_moving: int | None) -> tuple[NodeState, dict]:
    """Root [0, 39] whose scaffold is still before ``first_moving`` and then moves 1 px per frame (None: still
    throughout); identity cameras and intrinsics, depth 1, so a node at (x, y, 1) is seen at pixel (x, y).
    Its measured fit: every frame's moving pixels have error 0.3, the static ones 0.01."""
    root = node_factory(1, Interval(0, 39), num_dynamic=100)
    T, M = 40, root.scaffold.M
    t = torch.arange(T, dtype=torch.float32)
    shift = torch.zeros(T) if first_moving is None else (t - first_moving + 1).clamp(min=0)
    pos = torch.zeros(T, M, 3)
    pos[..., 0] = torch.arange(M, dtype=torch.float32) * 0.05 + shift[:, None]
    pos[..., 2] = 1.0
    quat = torch.zeros(T, M, 4)
    quat[..., 0] = 1.0
    scf = Scaffold(pos, quat, torch.zeros(M), torch.ones(T, M, dtype=torch.bool), 1.0,
                   ScaffoldConfig(mix_identity=False))  # fmt: skip
    root = NodeState(1, root.interval, scf, root.dynamic, root.static, torch.eye(4).repeat(T, 1, 1))
    sums = torch.tensor([[0.3 * 10, 10.0, 0.01 * 134, 134.0]], dtype=torch.float64).repeat(T, 1)
    return root, {"sums": sums, "Ks": torch.eye(3).repeat(T, 1, 1), "image_size": [9, 16]}


def test_one_sided_split_trains_only_the_moving_half(node_factory, tmp_path):
    root, measured = _root_moving_from(node_factory, first_moving=20)
    cfg = TreeConfig(depth=0, inherit=InheritConfig(caps=(60, 30)), auto=AutoSplitConfig(max_depth=4))
    with LayerRunner(ParallelConfig(sequential=True, device="cpu"), leaf_node) as r:
        res = grow_tree(root, cfg, r, tmp_path, root_decision={"split": True, "reason": "root"},
                        root_measured=measured)  # fmt: skip
    # Binary split at 19: [0, 18] is still (0 px < 1.6 px), [19, 39] moves 20 px: only node 3 is trained.
    assert sorted(res.tree.intervals) == [1, 3] and res.tree.interval(3) == Interval(19, 39)
    assert [n.node for layer in res.layers for n in layer.nodes] == [3]
    assert not (tmp_path / "layer1" / "node2").exists()
    kids = res.decisions[1]["children"]
    assert res.decisions[1]["applied"] is True
    assert kids["2"]["train"] is False and "near-static: scaffold motion 0 px" in kids["2"]["reason"]
    assert kids["3"]["train"] is True and kids["3"]["motion_px"] >= kids["3"]["motion_min_px"] and abs(kids["3"]["motion_min_px"] - 1.6) < 1e-9
    # The root renders the calm half, node 3 the rest.
    assert [res.tree.covering(t) for t in range(40)] == [1] * 19 + [3] * 21
    assert res.tree.own_frames(1) == [Interval(0, 18)] and res.tree.rendering_nodes() == [1, 3]
    rec = json.loads((tmp_path / "tree.json").read_text())
    assert rec["auto"]["1"]["children"]["2"]["train"] is False and rec["tree"]["nodes"].keys() == {"1", "3"}


def test_split_whose_halves_the_parent_holds_leaves_a_leaf(node_factory, tmp_path):
    root, measured = _root_moving_from(node_factory, first_moving=None)
    cfg = TreeConfig(depth=0, inherit=InheritConfig(caps=(60, 30)), auto=AutoSplitConfig(max_depth=4))
    with LayerRunner(ParallelConfig(sequential=True, device="cpu"), leaf_node) as r:
        res = grow_tree(root, cfg, r, tmp_path, root_decision={"split": True, "reason": "root"},
                        root_measured=measured)  # fmt: skip
    assert sorted(res.tree.intervals) == [1] and res.layers == []
    assert res.decisions[1]["applied"] is False and "no child needs training" in res.decisions[1]["reason"]
    assert {d["train"] for d in res.decisions[1]["children"].values()} == {False}
