"""TPT indices, intervals, minimum length and the deepest-covering-node lookup."""

from __future__ import annotations

import pytest

from worldtree.tree.split import build_intervals
from worldtree.tree.tpt import (
    Interval,
    TemporalPartitionTree,
    ancestors,
    children,
    depth_of,
    layer_indices,
    min_child_len,
    parent,
)


def test_tree_bfs_indices():
    assert [depth_of(j) for j in range(1, 16)] == [0, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3, 3, 3, 3, 3]
    assert children(1) == (2, 3) and children(5) == (10, 11)
    assert parent(2) == parent(3) == 1 and parent(11) == 5
    assert list(layer_indices(2)) == [4, 5, 6, 7]
    # Paper: C_j = {floor(j / 2^a), a = 1 .. log2 j}.
    for j in range(1, 64):
        expected = [j // 2**a for a in range(1, depth_of(j) + 1)]
        assert ancestors(j) == expected
    assert ancestors(13) == [6, 3, 1]
    with pytest.raises(ValueError):
        parent(1)
    with pytest.raises(ValueError):
        depth_of(0)


def test_tree_intervals_t160_depth2_by_hand():
    # [0,159]: P = 159 // 2 = 79 -> [0,78], [79,159]; [0,78]: P = 39 -> [0,38], [39,78];
    # [79,159]: P = 238 // 2 = 119 -> [79,118], [119,159].
    tree = build_intervals(160, 2)
    got = {j: (iv.start, iv.end) for j, iv in tree.intervals.items()}
    assert got == {
        1: (0, 159),
        2: (0, 78),
        3: (79, 159),
        4: (0, 38),
        5: (39, 78),
        6: (79, 118),
        7: (119, 159),
    }
    assert tree.depth == 2 and tree.leaves() == [4, 5, 6, 7] and tree.layer(1) == [2, 3]
    assert tree.chain(6) == [3, 1]


def test_tree_children_partition_parent():
    for T in (1, 2, 11, 12, 13, 23, 24, 25, 100, 160, 165):
        tree = build_intervals(T, 6)
        for j in tree:
            if 2 * j in tree:
                a, b = tree.interval(2 * j), tree.interval(2 * j + 1)
                p = tree.interval(j)
                assert (a.start, b.end) == (p.start, p.end) and a.end + 1 == b.start
                assert a.length >= 1 and b.length >= 1
            else:
                assert 2 * j + 1 not in tree


def test_tree_minimum_interval_is_the_nodes_own_length():
    # A node with < 12 frames is a leaf; a node with >= 12 frames is split (binary: 12 -> 5 + 7).
    assert len(build_intervals(11, 3)) == 1
    t12 = build_intervals(12, 3)
    assert t12.intervals[2] == Interval(0, 4) and t12.intervals[3] == Interval(5, 11)
    assert t12.leaves() == [2, 3]
    # 160 frames: depth 4 exists (9-11 frames), nothing deeper (paper's depth study stops at 4).
    t = build_intervals(160, 8)
    assert t.depth == 4
    assert {t.interval(j).length for j in t.layer(4)} <= {9, 10, 11}
    assert all(t.interval(j).length < 12 for j in t.leaves())
    assert min_child_len(12) == 5
    with pytest.raises(ValueError):
        TemporalPartitionTree(11).add_children(1, 5)
    tree = TemporalPartitionTree(30)
    with pytest.raises(ValueError):
        tree.add_children(1, 3)  # left child of 3 frames < 5
    tree.add_children(1, 5)
    with pytest.raises(ValueError):
        tree.add_children(1, 15)  # already split


def test_tree_covering_lookup_matches_brute_force():
    tree = build_intervals(165, 3)
    for t in range(-3, 170):
        tc = min(max(t, 0), 164)
        best = max((j for j in tree if tree.interval(j).contains(tc)), key=depth_of)
        assert tree.covering(t) == best
        # A capped depth picks the covering node of that layer.
        j1 = tree.covering(t, max_depth=1)
        assert depth_of(j1) == 1 and tree.interval(j1).contains(tc)
    assert tree.covering(0) == 8 and tree.covering(164) == 15


def test_tree_dict_round_trip_and_local_time():
    tree = build_intervals(100, 2)
    again = TemporalPartitionTree.from_dict(tree.to_dict())
    assert again.intervals == tree.intervals
    iv = Interval(79, 159)
    assert iv.local(79) == 0 and iv.local(159) == 80 and iv.length == 81
    with pytest.raises(ValueError):
        iv.local(78)
    with pytest.raises(ValueError):
        Interval(5, 4)


def test_one_sided_split_parent_renders_the_half_left_out():
    # Root [0, 39] split at 19 keeping only the right child [19, 39]; that child split at 29 keeping only its
    # left child [19, 28]. Worked out by hand: node 1 renders 0-18, node 3 renders 29-39, node 6 renders 19-28.
    tree = TemporalPartitionTree(40, 12)
    assert tree.add_children(1, 19, keep=(False, True)) == (3,)
    assert tree.add_children(3, 29, keep=(True, False)) == (6,)
    assert sorted(tree.intervals) == [1, 3, 6]
    assert tree.has_children(1) and tree.has_children(3) and not tree.has_children(6)
    assert tree.leaves() == [6]
    assert tree.own_frames(1) == [Interval(0, 18)]
    assert tree.own_frames(3) == [Interval(29, 39)]
    assert tree.own_frames(6) == [Interval(19, 28)]
    assert tree.rendering_nodes() == [1, 3, 6]
    # Brute force: the deepest node whose interval holds t, among the nodes that exist.
    for t in range(40):
        best = max((j for j in tree if tree.interval(j).contains(t)), key=depth_of)
        assert tree.covering(t) == best
        assert any(iv.contains(t) for iv in tree.own_frames(best))  # rendered by exactly its own-frames node
    assert [tree.covering(t) for t in (0, 18, 19, 28, 29, 39)] == [1, 1, 6, 6, 3, 3]
    with pytest.raises(ValueError):
        tree.add_children(1, 19, keep=(True, False))  # node 1 already has a child
    with pytest.raises(ValueError):
        TemporalPartitionTree(40, 12).add_children(1, 19, keep=(False, False))
    # A fully split tree: only the leaves render, each its whole interval.
    full = build_intervals(40, 2)
    assert full.rendering_nodes() == full.leaves() == [4, 5, 6, 7]
    assert all(full.own_frames(j) == [full.interval(j)] for j in full.leaves())
    assert full.own_frames(1) == [] and full.own_frames(2) == []
    # grow_layer does not split a node that already has one child.
    assert tree.grow_layer(0) == []
