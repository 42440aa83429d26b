"""Inheritance: canonical-time filter, counts and cap, time shift, opacity reset, slices and copies."""

from __future__ import annotations

import math

import pytest
import torch

from worldtree.tree.inherit import InheritConfig, child_cap, child_state, select_inherited, split_state
from worldtree.tree.node import NodeState
from worldtree.tree.tpt import Interval


def _row_of(parent_means: torch.Tensor, child_means: torch.Tensor) -> torch.Tensor:
    """Index of each child Gaussian in the parent (means are distinct random points)."""
    d = torch.cdist(child_means.double(), parent_means.double())
    idx = d.argmin(dim=1)
    assert float(d.min(dim=1).values.max()) == 0.0
    return idx


def test_inherit_canonical_time_filter_shift_and_counts(root_state):
    # Root [0, 59], 600 Gaussians with t_ref = k % 60: 10 per frame.
    left, right = split_state(root_state, Interval(0, 29), Interval(30, 59), InheritConfig())
    assert len(left.dynamic) == 300 and len(right.dynamic) == 300  # under the 5000 cap: all kept
    p_t = root_state.dynamic.t_ref
    for child, offset in ((left, 0), (right, 30)):
        rows = _row_of(root_state.dynamic.means.detach(), child.dynamic.means.detach())
        # Every kept Gaussian had its canonical time inside the child's interval, shifted by the offset.
        assert torch.equal(child.dynamic.t_ref, p_t[rows] - offset)
        assert int(child.dynamic.t_ref.min()) >= 0 and int(child.dynamic.t_ref.max()) < 30
        # All of those inside were kept, once each, in the parent's order.
        inside = torch.nonzero((p_t >= offset) & (p_t < offset + 30)).flatten()
        assert torch.equal(rows, inside)
        for k in ("quats", "log_scales", "sh0", "skin_corr"):
            assert torch.equal(child.dynamic.params[k], root_state.dynamic.params[k][rows])


def test_inherit_cap_is_a_seeded_random_subset(root_state):
    cfg = InheritConfig(caps=(100, 40))
    assert child_cap(cfg, 1) == 100 and child_cap(cfg, 2) == 40 and child_cap(cfg, 5) == 40
    assert child_cap(InheritConfig(), 1) == 5000 and child_cap(InheritConfig(), 2) == 2000
    a1, b1 = split_state(root_state, Interval(0, 29), Interval(30, 59), cfg, seed=3)
    a2, _ = split_state(root_state, Interval(0, 29), Interval(30, 59), cfg, seed=3)
    a3, _ = split_state(root_state, Interval(0, 29), Interval(30, 59), cfg, seed=4)
    assert len(a1.dynamic) == len(b1.dynamic) == 100
    rows1 = _row_of(root_state.dynamic.means.detach(), a1.dynamic.means.detach())
    assert len(set(rows1.tolist())) == 100 and bool((rows1[1:] > rows1[:-1]).all())  # distinct, in order
    assert torch.equal(a1.dynamic.means, a2.dynamic.means)  # same seed, same subset
    assert not torch.equal(a1.dynamic.means, a3.dynamic.means)  # another seed, another subset
    # Subsampling is not biased to the front: kept canonical times spread over the interval.
    assert int(a1.dynamic.t_ref.max()) >= 25 and int(a1.dynamic.t_ref.min()) <= 4
    # Low-level selector: exact count and filter.
    t = torch.arange(1000) % 50
    sel = select_inherited(t, 10, 5, 30, seed=0)
    assert sel.numel() == 30 and bool(((t[sel] >= 10) & (t[sel] < 15)).all())


def test_inherit_opacity_reset(root_state):
    left, _ = split_state(root_state, Interval(0, 29), Interval(30, 59), InheritConfig())
    rows = _row_of(root_state.dynamic.means.detach(), left.dynamic.means.detach())
    o_parent = torch.sigmoid(root_state.dynamic.params["opacity_logits"].detach()[rows].double())
    o_child = torch.sigmoid(left.dynamic.params["opacity_logits"].detach().double())
    expected = torch.clamp(o_parent, max=0.05)
    torch.testing.assert_close(o_child, expected, rtol=0, atol=1e-6)
    assert bool((o_parent > 0.05).any()) and bool((o_parent < 0.05).any())  # both branches exercised
    # The static copy keeps its opacities unless asked.
    torch.testing.assert_close(left.static.opacities, root_state.static.opacities)
    reset, _ = split_state(
        root_state, Interval(0, 29), Interval(30, 59), InheritConfig(reset_static_opacity=True)
    )
    assert float(reset.static.opacities.detach().max()) <= 0.05 + 1e-6
    no_reset, _ = split_state(root_state, Interval(0, 29), Interval(30, 59), InheritConfig(opacity_cap=1.0))
    o_nr = no_reset.dynamic.params["opacity_logits"]
    assert torch.equal(o_nr, root_state.dynamic.params["opacity_logits"].detach()[rows])


def test_inherit_scaffold_cameras_static_and_motion_agree(root_state):
    _, right = split_state(root_state, Interval(0, 29), Interval(30, 59), InheritConfig())
    assert torch.equal(right.scaffold.pos, root_state.scaffold.pos.detach()[30:60])
    assert torch.equal(right.scaffold.quat, root_state.scaffold.quat.detach()[30:60])
    assert right.scaffold.M == root_state.scaffold.M
    assert torch.equal(right.w2cs[:, 0, 3], torch.arange(30, 60, dtype=torch.float32))  # global frames 30..59
    assert torch.equal(right.static.means, root_state.static.means)
    assert right.static.means.data_ptr() != root_state.static.means.data_ptr()
    # An inherited Gaussian moves in the child at child-local t exactly as in the parent at t + offset.
    rows = _row_of(root_state.dynamic.means.detach(), right.dynamic.means.detach())
    with torch.no_grad():
        pm, pq = root_state.dynamic.at(root_state.scaffold, 30 + 7)
        cm, cq = right.dynamic.at(right.scaffold, 7)
    torch.testing.assert_close(cm, pm[rows], atol=1e-5, rtol=0)
    torch.testing.assert_close(cq, pq[rows], atol=1e-5, rtol=0)


def test_inherit_chain_levels_and_payload_round_trip(root_state, tmp_path):
    cfg = InheritConfig(caps=(200, 80, 40))
    a, _ = split_state(root_state, Interval(0, 29), Interval(30, 59), cfg)  # node 2
    b, _ = split_state(a, Interval(0, 14), Interval(15, 29), cfg)  # node 4
    c, _ = split_state(b, Interval(0, 6), Interval(7, 14), cfg)  # node 8
    assert [x.node for x in c.chain] == [4, 2, 1]
    assert [x.level for x in c.chain] == [1, 2, 3]
    assert [x.trainable for x in c.chain] == [True, True, False]  # 2 nearest optimised, root frozen
    assert c.chain[2].interval == Interval(0, 59) and c.chain[2].scaffold.T == 60
    assert len(c.chain[0].dynamic) == len(b.dynamic) == 80  # the ancestor copy is not subsampled again
    assert len(c.dynamic) == min(40, int((b.dynamic.t_ref < 7).sum()))
    path = tmp_path / "node8.pt"
    c.save(path)
    back = NodeState.load(path)
    assert back.index == 8 and back.interval == c.interval
    for x, y in zip(back.chain, c.chain, strict=True):
        assert (x.node, x.level, x.trainable, x.interval) == (y.node, y.level, y.trainable, y.interval)
        assert torch.equal(x.dynamic.means, y.dynamic.means) and torch.equal(x.scaffold.pos, y.scaffold.pos)
    assert torch.equal(back.dynamic.t_ref, c.dynamic.t_ref) and back.dynamic.t_ref.dtype == torch.long
    assert torch.equal(back.w2cs, c.w2cs)


def test_inherit_rejects_bad_children(root_state):
    with pytest.raises(ValueError):
        split_state(root_state, Interval(0, 28), Interval(30, 59), InheritConfig())  # gap
    with pytest.raises(ValueError):
        child_state(root_state, 5, Interval(0, 29), InheritConfig())  # not a child of node 1
    with pytest.raises(ValueError):
        InheritConfig(opacity_cap=0.0)
    assert math.isfinite(float(InheritConfig().opacity_cap))


def test_inherit_static_scene_without_dynamic_content(tmp_path):
    # A scene with no dynamic track: empty scaffold (M = 0) and no dynamic Gaussian; the tree still works.
    from worldtree.dynamic import DynamicGaussians
    from worldtree.gaussians import GaussianSet
    from worldtree.motion.scaffold import Scaffold, ScaffoldConfig

    n = 30
    root = NodeState(
        1, Interval(0, n - 1), Scaffold.empty(n, 1.0, ScaffoldConfig()), DynamicGaussians.empty(),
        GaussianSet.from_tensors(torch.zeros(3, 3), torch.ones(3, 3), torch.full((3,), 0.5), torch.ones(3, 3)),
        torch.eye(4).repeat(n, 1, 1),
    )  # fmt: skip
    left, right = split_state(root, Interval(0, 14), Interval(15, 29), InheritConfig())
    assert len(right.dynamic) == 0 and right.scaffold.M == 0 and right.scaffold.T == 15
    with torch.no_grad():
        m, *_ = right.gaussians_at(20)
    assert m.shape == (3, 3)  # the static Gaussians only
    right.save(tmp_path / "n3.pt")
    assert NodeState.load(tmp_path / "n3.pt").scaffold.T == 15


def test_shared_static_model_is_saved_once_and_counted_once(root_state, tmp_path):
    from worldtree.tree.node import distinct_gaussians, share_static_model

    left, right = split_state(root_state, Interval(0, 29), Interval(30, 59), InheritConfig())
    # A child that re-fitted its background (node_static_lr > 0) holds its own model.
    with torch.no_grad():
        right.static.params["means"][0] += 1.0
    states = {1: root_state, 2: left, 3: right}
    share_static_model(states)
    assert left.static is not root_state.static  # never the root's own (trainable during a run) object
    assert right.static is not left.static
    n_static, n_root_dyn = len(root_state.static), len(root_state.dynamic)
    # Leaves 2 and 3: one background shared with the root counted once, the changed one again; each child's
    # dynamic Gaussians; the root's dynamic Gaussians as an ancestor copy held (identical) by both: once.
    want = n_static + len(left.dynamic) + n_static + len(right.dynamic) + n_root_dyn
    assert distinct_gaussians(states, [2, 3]) == want
    assert distinct_gaussians({1: root_state, 2: left}, [2]) == n_static + len(left.dynamic) + n_root_dyn

    # Saved with a reference: the file holds no static model and loads the named node's.
    root_state.save(tmp_path / "node1.pt")
    left.save(tmp_path / "node2.pt", static_shared_with=1)
    right.save(tmp_path / "node3.pt")
    assert (tmp_path / "node2.pt").stat().st_size < (tmp_path / "node3.pt").stat().st_size
    back = NodeState.load(tmp_path / "node2.pt")
    for k, v in root_state.static.params.items():
        assert torch.equal(back.static.params[k], v)
    assert torch.equal(NodeState.load(tmp_path / "node3.pt").static.means, right.static.means)
    with pytest.raises(ValueError, match="hand that model over"):
        NodeState.from_payload(left.to_payload(static_shared_with=1))
    with pytest.raises(ValueError, match="different runs"):
        NodeState.from_payload(
            left.to_payload(static_shared_with=1),
            static=right.static.__class__({k: v[:-1] for k, v in right.static.params.items()}),
        )
