"""Algorithm 1 end to end with a stand-in node trainer: intervals, chains, splits, modes agree."""

from __future__ import annotations

import json

import pytest
import torch

from worldtree.tree.build import TreeConfig, grow_tree, read_node_input
from worldtree.tree.inherit import InheritConfig
from worldtree.tree.node import load_payload
from worldtree.tree.parallel import LayerRunner, ParallelConfig
from worldtree.tree.split import build_intervals
from worldtree.tree.tpt import Interval


def test_tree_build_binary_depth2_sequential_and_parallel_agree(node_factory, tmp_path):
    root = node_factory(1, Interval(0, 59), num_dynamic=400)
    cfg = TreeConfig(depth=2, inherit=InheritConfig(caps=(150, 60)))
    with LayerRunner(ParallelConfig(sequential=True, device="cpu"), "benchmarks.fixtures.toy_nodes:perturb_node") as r:
        seq = grow_tree(root, cfg, r, tmp_path / "seq", seed=5)
    with LayerRunner(
        ParallelConfig(device="cpu", max_workers=2, threads_total=2), "benchmarks.fixtures.toy_nodes:perturb_node"
    ) as r:
        par = grow_tree(root, cfg, r, tmp_path / "par", seed=5)
    assert seq.tree.intervals == build_intervals(60, 2).intervals == par.tree.intervals
    assert sorted(seq.states) == list(range(1, 8))
    assert [rep.depth for rep in par.layers] == [1, 2] and [len(rep.nodes) for rep in par.layers] == [2, 4]
    for j in range(2, 8):
        a, b = seq.states[j], par.states[j]
        assert torch.equal(a.dynamic.means, b.dynamic.means), j
        assert [x.node for x in a.chain] == seq.tree.chain(j)
        for x, y in zip(a.chain, b.chain, strict=True):
            assert torch.equal(x.dynamic.means, y.dynamic.means)
    # Node 5 started (its input file) with a copy of node 2 as trained by node 2, and of the root copy as
    # trained by node 2; both trainable, so node 5's own training moved them again.
    start5, _ = read_node_input(load_payload(tmp_path / "seq" / "layer2" / "node5" / "input.pt"))
    assert torch.equal(start5.chain[0].dynamic.means, seq.states[2].dynamic.means)
    assert torch.equal(start5.chain[1].dynamic.means, seq.states[2].chain[0].dynamic.means)
    assert not torch.equal(start5.chain[1].dynamic.means, root.dynamic.means)
    assert not torch.equal(seq.states[5].chain[0].dynamic.means, start5.chain[0].dynamic.means)
    assert len(seq.states[2].dynamic) == 150 and len(seq.states[4].dynamic) <= 60
    rec = json.loads((tmp_path / "par" / "tree.json").read_text())
    assert rec["tree"]["nodes"]["7"] == [44, 59]  # [29, 59]: P = 88 // 2 = 44 and len(rec["layers"]) == 2
    assert seq.stats[6] == {"num_dynamic": len(seq.states[6].dynamic), "depth": 2}


def test_tree_build_gradient_split_uses_the_parents_profile(node_factory, tmp_path):
    root = node_factory(1, Interval(0, 59), num_dynamic=200)
    cfg = TreeConfig(depth=2, split="gradient", inherit=InheritConfig(caps=(80, 40)))
    # Root profile: all the gradient in frames 40..59 -> root splits at 50.
    prof = torch.zeros(60, dtype=torch.float64)
    prof[40:] = 1.0
    with LayerRunner(ParallelConfig(sequential=True, device="cpu"), "benchmarks.fixtures.toy_nodes:perturb_node") as r:
        res = grow_tree(root, cfg, r, tmp_path, root_profile=prof)
    assert res.tree.interval(2) == Interval(0, 49) and res.splits[1].fallback is None
    # Children return the rising profile w[k] = k + 1: node 2 ([0, 49], n = 50) balances where
    # S(k) = k (k + 1) / 2 is closest to 1275 / 2: k = 35 (630) vs 36 (666) -> P = 35.
    n = 50
    total = n * (n + 1) / 2
    best = min(range(1, n), key=lambda k: abs(k * (k + 1) - total))
    assert best == 35 and res.tree.interval(4) == Interval(0, 34)


def test_tree_build_rejects_a_non_root(node_factory, tmp_path):
    with LayerRunner(ParallelConfig(sequential=True, device="cpu"), "benchmarks.fixtures.toy_nodes:perturb_node") as r:
        with pytest.raises(ValueError):
            grow_tree(node_factory(2, Interval(0, 29)), TreeConfig(), r, tmp_path)
    with pytest.raises(ValueError):
        TreeConfig(split="median")
