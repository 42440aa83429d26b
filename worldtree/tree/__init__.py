"""The WorldTree tree: Temporal Partition Tree (intervals, splits), Spatial Ancestral Chains, inheritance,
node states and the parallel layer runner. Method-agnostic; ``docs/worldtree.md`` describes it.

Modules: :mod:`~worldtree.tree.tpt` (indices, intervals, the tree), :mod:`~worldtree.tree.split` (split
strategies), :mod:`~worldtree.tree.sac` (ancestor copies, policy, time convention), :mod:`~worldtree.tree.node`
(a node's state and its files), :mod:`~worldtree.tree.inherit` (parent -> children),
:mod:`~worldtree.tree.parallel` (layer runner), :mod:`~worldtree.tree.build` (Algorithm 1 below a trained
root). Toy node trainers for the tests and the speed script live in ``benchmarks/fixtures/toy_nodes.py``.
"""

from worldtree.tree.split import build_intervals
from worldtree.tree.tpt import (
    DEFAULT_MIN_LEN,
    Interval,
    TemporalPartitionTree,
    ancestors,
    children,
    depth_of,
    layer_indices,
    parent,
)

__all__ = [
    "DEFAULT_MIN_LEN",
    "Interval",
    "TemporalPartitionTree",
    "ancestors",
    "build_intervals",
    "children",
    "depth_of",
    "layer_indices",
    "parent",
]
