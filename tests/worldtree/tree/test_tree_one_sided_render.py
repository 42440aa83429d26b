"""A one-sided split renders through the tree: a time in the child left out is rendered by the parent, a time
in the trained child by that child with its chain (``methods.worldtree``'s tree renderer)."""

from __future__ import annotations

from types import SimpleNamespace

import torch

from methods.worldtree import _tree_renderer
from worldtree.render import rasterize
from worldtree.tree.inherit import InheritConfig, child_state
from worldtree.tree.tpt import Interval, TemporalPartitionTree

W, H = 32, 24
K = torch.tensor([[20.0, 0.0, 16.0], [0.0, 20.0, 12.0], [0.0, 0.0, 1.0]])


def test_untrained_half_renders_from_the_parent(node_factory):
    root = node_factory(1, Interval(0, 39), num_dynamic=200)
    tree = TemporalPartitionTree(40, 12)
    tree.add_children(1, 19, keep=(False, True))  # node 2 [0, 18] not trained
    child = child_state(root, 3, tree.interval(3), InheritConfig(caps=(100,)), seed=0)
    with torch.no_grad():  # the child's own model differs from the root's (as after training)
        child.static.params["sh0"] += 0.5
        child.dynamic.params["sh0"] -= 0.5
    s = SimpleNamespace(tree=tree, states={1: root, 3: child}, scene=SimpleNamespace(num_frames=40),
                        cfg=SimpleNamespace(chain_length=None, photometric=SimpleNamespace(backend="reference")),
                        caches={})  # fmt: skip
    render = _tree_renderer(s)
    w2c = torch.eye(4)
    w2c[2, 3] = 3.0  # the Gaussians lie around the origin, 3 units in front of the camera

    def direct(state, t):
        m, q, ls, o, c = state.gaussians_at(t)
        return rasterize(m, q, ls, o, c, K, w2c, W, H, backend="reference").rgb

    with torch.no_grad():
        for t in (0, 10, 18):  # the calm half: the root's own render
            img = render(K, w2c, W, H, t).rgb
            assert img.abs().sum() > 0 and torch.equal(img, direct(root, t))
        for t in (19, 30, 39):  # the trained half: node 3 with its chain, not the root
            img = render(K, w2c, W, H, t).rgb
            assert torch.equal(img, direct(child, t))
            assert (img - direct(root, t)).abs().max() > 1e-3
