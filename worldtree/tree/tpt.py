"""The Temporal Partition Tree (TPT): a binary tree over the training frames, nodes in a BFS array.

Indices: the root is node 1; node ``j`` has children ``2j`` (left) and ``2j + 1`` (right), parent ``j // 2``
and depth ``floor(log2 j)``; layer ``d`` holds the indices ``2^d .. 2^(d+1) - 1`` (not all need exist).

Intervals are *inclusive* global frame ranges ``[start, end]``. A node ``[L, R]`` split at ``P`` gets the
children ``[L, P - 1]`` and ``[P, R]`` (the paper's ``[T^L, T^P)`` and ``[T^P, T^R]``); the binary split is
``P = (L + R) // 2`` (:mod:`worldtree.tree.split` has the others, and :func:`~worldtree.tree.split.build_intervals`).

Minimum interval (REFERENCE: "no child is made for an interval shorter than 12 frames"), made precise here:
it is the *node's own* length that counts. A node with fewer than ``min_len`` frames is a leaf; a node with
``>= min_len`` frames (and at least 2) is split, and then always into two children, so the children of a node
cover exactly its frames and every frame is covered by one node of each layer down to its leaf. Children may
be shorter than ``min_len`` (a 12-frame node gives 5 + 7 frames). This reading matches the paper's depth study:
160 frames reach depth 4 (nodes of 9-11 frames), which a rule on the children's length (>= 12 each) would forbid
(it stops at depth 3). Strategies other than binary keep each child at least ``min_child_len = max(1,
(min_len - 1) // 2)`` frames, the shortest child the binary rule itself makes (5 for ``min_len = 12``), i.e.
``P`` in ``[L + min_child_len, R + 1 - min_child_len]``.

One-sided splits (``--depth auto``, :mod:`worldtree.tree.adaptive`): a split may keep only one of its two
children, when the parent's own fit already holds the other half's frames. The parent then still renders that
half: every frame is rendered by the deepest node whose interval contains it (:meth:`TemporalPartitionTree.covering`),
and :meth:`TemporalPartitionTree.own_frames` says which frames each node renders.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

__all__ = [
    "DEFAULT_MIN_LEN",
    "Interval",
    "TemporalPartitionTree",
    "ancestors",
    "binary_point",
    "can_split",
    "children",
    "depth_of",
    "layer_indices",
    "min_child_len",
    "parent",
    "split_range",
]

DEFAULT_MIN_LEN = 12
"""A node shorter than this many frames gets no children (REFERENCE section 1)."""


def min_child_len(min_len: int) -> int:
    """Shortest child a split may make: ``max(1, (min_len - 1) // 2)`` (binary's shortest; see above)."""
    return max(1, (int(min_len) - 1) // 2)


# The three TPT rules, stated once here (the tree, the split strategies and the --depth auto criterion use them).
def can_split(length: int, min_len: int) -> bool:
    """Whether a node of ``length`` frames gets children: ``length >= max(min_len, 2)``."""
    return int(length) >= max(int(min_len), 2)


def split_range(start: int, end: int, min_len: int) -> tuple[int, int]:
    """``(lo, hi)``: the split points ``P`` allowed for the node ``[start, end]`` (inclusive; each child keeps
    ``>= min_child_len`` frames); only meaningful when :func:`can_split`."""
    c = min_child_len(min_len)
    return int(start) + c, int(end) + 1 - c


def binary_point(start: int, end: int) -> int:
    """The binary split point of the node ``[start, end]``: ``(start + end) // 2``."""
    return (int(start) + int(end)) // 2


# ---------------------------------------------------------------------------------------------- indices
def _check_index(j: int) -> int:
    if int(j) != j or j < 1:
        raise ValueError(f"tree node indices start at 1 (root); got {j!r}")
    return int(j)


def depth_of(j: int) -> int:
    """Depth of node ``j`` (root 1 -> 0, nodes 2..3 -> 1, 4..7 -> 2, ...): ``floor(log2 j)``."""
    return _check_index(j).bit_length() - 1


def parent(j: int) -> int:
    """Parent index ``j // 2``; the root has none (ValueError)."""
    if _check_index(j) == 1:
        raise ValueError("the root (node 1) has no parent")
    return j // 2


def children(j: int) -> tuple[int, int]:
    """``(2j, 2j + 1)``: left and right child indices."""
    j = _check_index(j)
    return 2 * j, 2 * j + 1


def ancestors(j: int) -> list[int]:
    """The chain of node ``j``: ``[parent, grandparent, ..., root]`` (empty for the root).

    Equals ``[floor(j / 2^a) for a = 1 .. log2 j]`` (the paper's SAC index set, nearest first).
    """
    j = _check_index(j)
    out = []
    while j > 1:
        j //= 2
        out.append(j)
    return out


def layer_indices(d: int) -> range:
    """Every index a layer ``d`` can hold: ``2^d .. 2^(d+1) - 1``."""
    if d < 0:
        raise ValueError(f"depth must be >= 0, got {d}")
    return range(1 << d, 1 << (d + 1))


# --------------------------------------------------------------------------------------------- interval
@dataclass(frozen=True)
class Interval:
    """Inclusive range of global frame indices ``[start, end]``."""

    start: int
    """First global frame."""
    end: int
    """Last global frame (inclusive)."""

    def __post_init__(self) -> None:
        if not 0 <= self.start <= self.end:
            raise ValueError(f"Interval needs 0 <= start <= end, got [{self.start}, {self.end}]")

    @property
    def length(self) -> int:
        """Number of frames ``end - start + 1``."""
        return self.end - self.start + 1

    def contains(self, t: int) -> bool:
        """Whether global frame ``t`` lies in the interval."""
        return self.start <= t <= self.end

    def local(self, t: int) -> int:
        """Node-local index of global frame ``t`` (``t - start``); ValueError outside the interval."""
        if not self.contains(t):
            raise ValueError(f"frame {t} is outside [{self.start}, {self.end}]")
        return t - self.start

    def split_at(self, p: int) -> tuple[Interval, Interval]:
        """``([start, p - 1], [p, end])``; ``p`` must leave both non-empty."""
        if not self.start < p <= self.end:
            raise ValueError(f"split point {p} must satisfy {self.start} < P <= {self.end}")
        return Interval(self.start, p - 1), Interval(p, self.end)

    def __str__(self) -> str:
        return f"[{self.start}, {self.end}]"


# ------------------------------------------------------------------------------------------------- tree
SplitFn = Callable[[int, Interval], "int | None"]
"""``split(node, interval) -> P`` (global frame of the right child's first frame) or None for a leaf."""


class TemporalPartitionTree:
    """The tree's intervals, grown layer by layer (the model states live elsewhere, keyed by index).

    Args:
        num_frames: T, the number of training frames; the root is ``[0, T - 1]``.
        min_len: nodes shorter than this are leaves (see the module docstring).
    """

    def __init__(self, num_frames: int, min_len: int = DEFAULT_MIN_LEN):
        if num_frames < 1:
            raise ValueError(f"the tree needs at least one frame, got {num_frames}")
        if min_len < 1:
            raise ValueError(f"min_len must be >= 1, got {min_len}")
        self.num_frames = int(num_frames)
        self.min_len = int(min_len)
        self.intervals: dict[int, Interval] = {1: Interval(0, num_frames - 1)}

    # ------------------------------------------------------------------ queries
    def __contains__(self, j: int) -> bool:
        return j in self.intervals

    def __len__(self) -> int:
        return len(self.intervals)

    def __iter__(self) -> Iterator[int]:
        """Node indices in BFS order (ascending index)."""
        return iter(sorted(self.intervals))

    def interval(self, j: int) -> Interval:
        if j not in self.intervals:
            raise KeyError(f"node {j} is not in the tree")
        return self.intervals[j]

    @property
    def depth(self) -> int:
        """Depth of the deepest node (0 for a root-only tree)."""
        return max(depth_of(j) for j in self.intervals)

    def layer(self, d: int) -> list[int]:
        """Existing nodes of depth ``d``, ascending."""
        return [j for j in layer_indices(d) if j in self.intervals]

    def has_children(self, j: int) -> bool:
        """Whether node ``j`` has at least one child (a one-sided split keeps one)."""
        a, b = children(j)
        return a in self.intervals or b in self.intervals

    def leaves(self) -> list[int]:
        """Nodes without children, ascending."""
        return [j for j in sorted(self.intervals) if not self.has_children(j)]

    def own_frames(self, j: int) -> list[Interval]:
        """The frames node ``j`` renders: its interval minus its children's (ascending runs; all of it for a
        leaf, none for a node with both children, the missing half after a one-sided split)."""
        iv = self.interval(j)
        taken = [self.intervals[c] for c in children(j) if c in self.intervals]
        out, start = [], iv.start
        for c in sorted(taken, key=lambda x: x.start):
            if c.start > start:
                out.append(Interval(start, c.start - 1))
            start = c.end + 1
        if start <= iv.end:
            out.append(Interval(start, iv.end))
        return out

    def rendering_nodes(self) -> list[int]:
        """Nodes that render at least one frame (:meth:`own_frames` not empty), ascending: the leaves, plus
        every parent of a one-sided split."""
        return [j for j in sorted(self.intervals) if self.own_frames(j)]

    def chain(self, j: int) -> list[int]:
        """Ancestors of an existing node, nearest first (:func:`ancestors`)."""
        self.interval(j)
        return ancestors(j)

    def can_split(self, j: int) -> bool:
        """Whether node ``j`` has ``>= min_len`` frames (and at least 2), i.e. gets children."""
        return can_split(self.interval(j).length, self.min_len)

    def split_range(self, j: int) -> tuple[int, int]:
        """``(lo, hi)``: the split points allowed for node ``j`` (inclusive, each child ``>= min_child_len``
        frames); only meaningful when :meth:`can_split`."""
        iv = self.interval(j)
        return split_range(iv.start, iv.end, self.min_len)

    def covering(self, t: int, max_depth: int | None = None) -> int:
        """The deepest node (at most ``max_depth`` deep) whose interval contains global frame ``t``.

        Test frames beyond the training frames are clamped to ``[0, T - 1]`` first (a test time past the last
        training frame is rendered by the node holding the last frame).
        """
        t = min(max(int(t), 0), self.num_frames - 1)
        j = 1
        while True:
            if max_depth is not None and depth_of(j) >= max_depth:
                return j
            left, right = 2 * j, 2 * j + 1
            if left in self.intervals and self.intervals[left].contains(t):
                j = left
            elif right in self.intervals and self.intervals[right].contains(t):
                j = right
            else:
                return j

    # ------------------------------------------------------------------ growth
    def add_children(self, j: int, p: int, keep: tuple[bool, bool] = (True, True)) -> tuple[int, ...]:
        """Split node ``j`` at global frame ``p`` (children ``[L, p-1]``, ``[p, R]``); returns the indices of
        the children added: both by default, only those ``keep`` marks for a one-sided split (the node itself
        goes on rendering the frames of a child left out).

        ValueError when ``j`` already has children, is shorter than ``min_len``, a child would be shorter than
        ``min_child_len``, or ``keep`` keeps neither child.
        """
        iv = self.interval(j)
        a, b = children(j)
        if not any(keep):
            raise ValueError(
                f"split of node {j}: keep at least one child (a node without children is a leaf)"
            )
        if self.has_children(j):
            raise ValueError(f"node {j} already has children")
        if not self.can_split(j):
            raise ValueError(f"node {j} {iv} has {iv.length} frames; nodes under {self.min_len} are leaves")
        lo, hi = self.split_range(j)
        if not lo <= p <= hi:
            raise ValueError(
                f"split of node {j} {iv} at {p}: each child needs >= {min_child_len(self.min_len)} frames, "
                f"so P must lie in [{lo}, {hi}]"
            )
        added = []
        for c, half, k in zip((a, b), iv.split_at(p), keep, strict=True):
            if k:
                self.intervals[c] = half
                added.append(c)
        return tuple(added)

    def remove_leaf(self, j: int) -> None:
        """Drop leaf ``j`` (not the root): its parent renders its frames again (:meth:`own_frames`), e.g. a
        child that did not beat its parent on held-out frames (:mod:`worldtree.tree.validate`)."""
        if j == 1:
            raise ValueError("the root cannot be removed")
        self.interval(j)
        if self.has_children(j):
            raise ValueError(f"node {j} has children; only a leaf can be removed")
        del self.intervals[j]

    def grow_layer(self, d: int, split: SplitFn | None = None) -> list[int]:
        """Add the children of every node of depth ``d`` that can be split; returns the new indices.

        ``split(j, interval)`` gives P (default: binary ``(L + R) // 2``); it is called only for nodes with
        ``>= min_len`` frames, and None from it keeps the node a leaf.
        """
        new: list[int] = []
        for j in self.layer(d):
            if self.has_children(j) or not self.can_split(j):
                continue
            iv = self.intervals[j]
            p = binary_point(iv.start, iv.end) if split is None else split(j, iv)
            if p is None:
                continue
            new.extend(self.add_children(j, int(p)))
        return new

    def to_dict(self) -> dict:
        """JSON-able record: ``{"num_frames", "min_len", "nodes": {j: [start, end]}}``."""
        return {
            "num_frames": self.num_frames,
            "min_len": self.min_len,
            "nodes": {str(j): [iv.start, iv.end] for j, iv in sorted(self.intervals.items())},
        }

    @classmethod
    def from_dict(cls, d: dict) -> TemporalPartitionTree:
        tree = cls(int(d["num_frames"]), int(d["min_len"]))
        tree.intervals = {int(k): Interval(int(v[0]), int(v[1])) for k, v in d["nodes"].items()}
        return tree
