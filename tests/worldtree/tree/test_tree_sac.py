"""SAC: chain construction, local time of ancestors, chain-length truncation, policy, sibling independence."""

from __future__ import annotations

import pytest
import torch

from worldtree.optim import ConstantLR, GroupedAdam
from worldtree.tree.inherit import InheritConfig, split_state
from worldtree.tree.sac import AncestorPolicy, ancestor_optimizer, chain_gaussians_at, truncate_chain
from worldtree.tree.split import build_intervals
from worldtree.tree.tpt import Interval


def _grow(root, tree, cfg=InheritConfig()):
    """Child states of every node of ``tree`` from ``root`` (breadth first)."""
    states = {1: root}
    for j in sorted(tree.intervals):
        if 2 * j in tree:
            states[2 * j], states[2 * j + 1] = split_state(
                states[j], tree.interval(2 * j), tree.interval(2 * j + 1), cfg
            )
    return states


def test_sac_chain_is_parent_to_root(node_factory):
    tree = build_intervals(100, 2)
    states = _grow(node_factory(1, tree.interval(1)), tree)
    for j in tree:
        assert [a.node for a in states[j].chain] == tree.chain(j)
        for a in states[j].chain:
            assert a.interval == tree.interval(a.node)
            assert a.scaffold.T == tree.interval(a.node).length


def test_sac_ancestor_evaluated_at_its_own_local_time(node_factory, velocity):
    # Root [0,159] -> node 3 [79,159] -> node 7 [119,159]. Node 7's parent copy (node 3) has 81 local frames.
    tree = build_intervals(160, 2)
    states = _grow(node_factory(1, tree.interval(1), num_dynamic=400), tree)
    n7 = states[7]
    parent_copy, root_copy = n7.chain
    g = 130  # global frame
    assert parent_copy.local_time(g) == 51 and root_copy.local_time(g) == 130
    with torch.no_grad():
        m, _ = parent_copy.at(g)
        # Closed form: every node translates by VELOCITY per frame and weights are normalised, so a Gaussian
        # at local t_ref moves by (t - t_ref) * VELOCITY with t = g - 79 (the ancestor's local time).
        dt = (51 - parent_copy.dynamic.t_ref).float()[:, None]
        torch.testing.assert_close(m, parent_copy.dynamic.means + dt * velocity, atol=2e-5, rtol=0)
        m_root, _ = root_copy.at(g)
        dt = (130 - root_copy.dynamic.t_ref).float()[:, None]
        torch.testing.assert_close(m_root, root_copy.dynamic.means + dt * velocity, atol=2e-5, rtol=0)
    with pytest.raises(ValueError):
        parent_copy.at(60)  # before the ancestor's interval


def test_sac_chain_gaussians_and_truncation(node_factory):
    tree = build_intervals(60, 2)
    states = _grow(node_factory(1, tree.interval(1), num_dynamic=300), tree)
    chain = states[5].chain  # [node 2, node 1]
    sizes = [len(a.dynamic) for a in chain]
    with torch.no_grad():
        full = chain_gaussians_at(chain, 20)
        one = chain_gaussians_at(chain, 20, chain_length=1)
        assert chain_gaussians_at(chain, 20, chain_length=0) is None
    assert full[0].shape == (sum(sizes), 3) and one[0].shape == (sizes[0], 3)
    torch.testing.assert_close(one[0], full[0][: sizes[0]])  # nearest first
    assert [a.node for a in truncate_chain(chain, 5)] == [2, 1]
    assert truncate_chain(chain, None) == list(chain)
    with pytest.raises(ValueError):
        truncate_chain(chain, -1)
    # Opacities are activated, colours are RGB.
    assert float(full[3].min()) >= 0.0 and float(full[3].max()) <= 1.0


def test_sac_policy_optimised_nearest_two(node_factory):
    tree = build_intervals(200, 3)
    states = _grow(node_factory(1, tree.interval(1), num_dynamic=200), tree)
    chain = states[9].chain  # [4, 2, 1]
    policy = AncestorPolicy()
    assert [a.trainable for a in chain] == [True, True, False]
    assert chain[0].dynamic.params["means"].requires_grad and chain[0].scaffold.pos.requires_grad
    assert (
        not chain[2].dynamic.params["means"].requires_grad and not chain[2].scaffold.sigma_logit.requires_grad
    )
    assert not chain[0].dynamic.params["t_ref"].requires_grad
    names = set(chain[1].parameters(policy))
    assert names == {
        "gauss.means", "gauss.quats", "gauss.log_scales", "gauss.opacity_logits", "gauss.sh0",
        "gauss.skin_corr", "scaffold.pos", "scaffold.quat", "scaffold.sigma_logit",
    }  # fmt: skip
    assert chain[2].parameters(policy) == {}
    only_parent = AncestorPolicy(optimised_nearest=1)
    for a in chain:
        a.apply_policy(only_parent)
    assert [a.trainable for a in chain] == [True, False, False]
    # Gradient reaches trainable copies only.
    loss = chain_gaussians_at(chain, 30)[0].sum()
    loss.backward()
    assert chain[0].dynamic.params["means"].grad is not None and chain[0].scaffold.pos.grad is not None
    assert chain[1].dynamic.params["means"].grad is None


def test_sac_sibling_ancestor_copies_are_independent(node_factory):
    tree = build_intervals(60, 1)
    root = node_factory(1, tree.interval(1), num_dynamic=300)
    left, right = split_state(root, tree.interval(2), tree.interval(3), InheritConfig())
    a, b = left.chain[0], right.chain[0]
    assert a.node == b.node == 1
    before_b = {k: v.detach().clone() for k, v in b.parameters(AncestorPolicy()).items()}
    before_root = root.dynamic.means.detach().clone()
    # Same initialisation...
    for k, v in a.parameters(AncestorPolicy()).items():
        assert torch.equal(v, before_b[k]) and v.data_ptr() != b.parameters(AncestorPolicy())[k].data_ptr()
    # ...optimised independently: a few Adam steps on the left sibling's copy.
    params = a.parameters(AncestorPolicy())
    opt = GroupedAdam(params, {k: ConstantLR(1e-2) for k in params})
    for _ in range(3):
        m, q, ls, o, c = chain_gaussians_at(left.chain, 10)
        loss = (m**2).sum() + o.sum() + c.sum() + ls.sum() + q[:, 1].sum()
        loss.backward()
        opt.step()
        opt.zero_grad()
    moved = a.parameters(AncestorPolicy())
    assert not torch.equal(moved["gauss.means"], before_b["gauss.means"])
    assert not torch.equal(moved["scaffold.pos"], before_b["scaffold.pos"])
    for k, v in b.parameters(AncestorPolicy()).items():
        assert torch.equal(v, before_b[k]), k  # the right sibling's copy did not move
    assert torch.equal(root.dynamic.means, before_root)  # nor the parent


def test_sac_child_chain_carries_parents_trained_copies(node_factory):
    # A grandchild's root copy is a copy of its parent's (trained) root copy, not of the original root.
    tree = build_intervals(60, 2)
    root = node_factory(1, tree.interval(1), num_dynamic=300)
    n2, _ = split_state(root, tree.interval(2), tree.interval(3), InheritConfig())
    with torch.no_grad():
        n2.chain[0].dynamic.params["means"].add_(1.0)  # "training" node 2's root copy
    n4, n5 = split_state(n2, tree.interval(4), tree.interval(5), InheritConfig())
    for child in (n4, n5):
        assert child.chain[1].node == 1
        torch.testing.assert_close(child.chain[1].dynamic.means, root.dynamic.means + 1.0)
    assert n4.chain[1].dynamic.means.data_ptr() != n5.chain[1].dynamic.means.data_ptr()
    assert Interval(0, 59) == n4.chain[1].interval


def test_sac_node_render_list_order_and_times(node_factory, velocity):
    tree = build_intervals(80, 2)
    states = _grow(node_factory(1, tree.interval(1), num_dynamic=300), tree)
    n6 = states[6]  # [39, 58] (0..79 -> 39..79 -> 39..58); chain [3 (39..79), 1 (0..79)]
    assert n6.interval == Interval(39, 58) and n6.chain[0].interval == Interval(39, 79)
    g = 47
    with torch.no_grad():
        m, q, ls, o, c = n6.gaussians_at(g)
        m1, *_ = n6.gaussians_at(g, chain_length=1)
        m0, *_ = n6.gaussians_at(g, chain_length=0)
    ns, nd = len(n6.static), len(n6.dynamic)
    na = [len(a.dynamic) for a in n6.chain]
    assert m.shape == (ns + nd + sum(na), 3) and q.shape[0] == ls.shape[0] == o.shape[0] == c.shape[0]
    assert m1.shape[0] == ns + nd + na[0] and m0.shape[0] == ns + nd
    torch.testing.assert_close(m[:ns], n6.static.means.detach())  # static first, not deformed
    own = m[ns : ns + nd]  # the node's own Gaussians at local time 47 - 39 = 8
    dt = (8 - n6.dynamic.t_ref).float()[:, None]
    torch.testing.assert_close(own, n6.dynamic.means.detach() + dt * velocity, atol=2e-5, rtol=0)
    root_part = m[ns + nd + na[0] :]  # the root copy at its local time 47
    dt = (47 - n6.chain[1].dynamic.t_ref).float()[:, None]
    torch.testing.assert_close(
        root_part, n6.chain[1].dynamic.means.detach() + dt * velocity, atol=2e-5, rtol=0
    )
    torch.testing.assert_close(
        o[ns:], torch.cat([n6.dynamic.opacities] + [a.dynamic.opacities for a in n6.chain])
    )


def test_sac_ancestor_optimizer_groups_and_constant_lr(node_factory):
    tree = build_intervals(200, 3)
    states = _grow(node_factory(1, tree.interval(1), num_dynamic=100), tree)
    chain = states[9].chain  # [4, 2, 1]: 4 and 2 trainable
    lrs = {
        "gauss.means": 1e-3, "gauss.quats": 1e-3, "gauss.log_scales": 5e-3, "gauss.opacity_logits": 0.05,
        "gauss.sh0": 2.5e-3, "gauss.skin_corr": 1e-3, "scaffold.pos": 1e-4, "scaffold.quat": 1e-3,
        "scaffold.sigma_logit": 1e-3,
    }  # fmt: skip
    opt = ancestor_optimizer(chain, AncestorPolicy(), lrs)
    assert {n.split(".")[0] for n in opt.names} == {"a4", "a2"} and len(opt.names) == 18
    opt.set_step(10_000)
    assert opt.lr("a2.scaffold.pos") == 1e-4 and opt.lr("a4.gauss.opacity_logits") == 0.05
    with pytest.raises(ValueError, match="no learning rate"):
        ancestor_optimizer(chain, AncestorPolicy(), {"gauss.means": 1.0})
    assert ancestor_optimizer(chain, AncestorPolicy(optimised_nearest=0), lrs) is None
