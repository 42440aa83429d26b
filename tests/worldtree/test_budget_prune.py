"""Gaussian budget and contribution pruning: the renderer-weight contribution equals a brute-force one-hot
colour render, removing a Gaussian changes a view by at most its contribution, pruning removes exactly the
Gaussians below the threshold, and the budget follows its closed form and never lowers a set's size."""

from __future__ import annotations

import math

import pytest
import torch

from worldtree.budget import (
    BudgetConfig,
    growth_cap,
    inherited_prune_due,
    negligible,
    node_budget,
    render_contributions,
    total_px,
)
from worldtree.render import rasterize

W, H = 32, 24
K = torch.tensor([[30.0, 0.0, 16.0], [0.0, 30.0, 12.0], [0.0, 0.0, 1.0]])


def _scene(n: int = 12, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([torch.rand(n, 2, generator=g) * 1.2 - 0.6, 2.0 + torch.rand(n, 1, generator=g)], 1)
    quats = torch.randn(n, 4, generator=g)
    log_scales = torch.log(0.02 + 0.1 * torch.rand(n, 3, generator=g))
    opac = 0.05 + 0.9 * torch.rand(n, generator=g)
    opac[3] = 0.002  # nearly transparent
    means[5] = torch.tensor([5.0, 0.0, 2.0])  # outside every view
    cols = torch.rand(n, 3, generator=g)
    return means, quats, log_scales, opac, cols


def _views():
    out = []
    for k, dx in enumerate((0.0, 0.15)):
        w2c = torch.eye(4)
        w2c[0, 3] = dx
        out.append((k, K, w2c))
    return out


def test_contribution_is_the_renderers_blending_weight():
    m, q, ls, o, c = _scene()
    fn = lambda t: (m, q, ls, o, c)  # noqa: E731
    got = render_contributions(fn, _views(), W, H)
    brute = torch.zeros(len(m))
    for i in range(len(m)):
        onehot = torch.zeros_like(c)
        onehot[i] = 1.0
        per_view = [
            float(rasterize(m, q, ls, o, onehot, K_, w, W, H).rgb[..., 0].sum()) for _, K_, w in _views()
        ]
        brute[i] = max(per_view)
    torch.testing.assert_close(got, brute, atol=1e-4, rtol=1e-4)
    assert got[5] == 0.0 and got[3] < got.max()


def test_removing_a_gaussian_changes_a_view_by_at_most_its_contribution():
    m, q, ls, o, c = _scene(seed=1)
    views = _views()
    contrib = render_contributions(lambda t: (m, q, ls, o, c), views, W, H)
    for i in range(len(m)):
        keep = torch.arange(len(m)) != i
        for _, K_, w in views:
            full = rasterize(m, q, ls, o, c, K_, w, W, H).rgb
            less = rasterize(m[keep], q[keep], ls[keep], o[keep], c[keep], K_, w, W, H).rgb
            change = (full - less).abs().sum(dim=(0, 1)).max()
            assert change <= contrib[i] + 1e-4


def test_pruning_removes_exactly_below_threshold():
    contrib = torch.tensor([0.0, 0.5, 0.999, 1.0, 1.001, 40.0])
    mask = negligible(contrib, BudgetConfig().prune_contribution)
    assert mask.tolist() == [v < 1.0 for v in contrib.tolist()]
    assert not mask[contrib >= 1.0].any()


@pytest.mark.parametrize("err", [0.0, 0.01, 0.03, 0.05, 0.2, float("nan")])
def test_budget_closed_form(err):
    cfg = BudgetConfig(gaussians_per_pixel=2.0, error_ref=0.05, min_scale=0.25)
    e = 0.05 if math.isnan(err) else err
    expect = math.ceil(2.0 * 80 * 45 * min(1.0, max(0.25, e / 0.05)))
    assert node_budget(80, 45, err, cfg) == expect
    assert node_budget(80, 45, err, BudgetConfig(override=123)) == 123


def test_growth_cap_never_below_current():
    assert growth_cap(100, 250) == 250
    assert growth_cap(300, 250) == 300


def test_inherited_gaussians_are_pruned_only_after_enough_epochs():
    cfg = BudgetConfig(prune_min_epochs=10.0)
    assert not inherited_prune_due(199, 20, cfg)  # 9.95 passes over 20 frames
    assert inherited_prune_due(200, 20, cfg)
    assert inherited_prune_due(0, 20, BudgetConfig(prune_min_epochs=0.0))
    with pytest.raises(ValueError):
        BudgetConfig(prune_min_epochs=-1.0)


def test_total_cap_removes_the_smallest_within_the_sum_and_never_above_threshold():
    g = torch.Generator().manual_seed(7)
    contrib = torch.cat([torch.rand(200, generator=g) * 2.0, torch.tensor([0.0, 0.0, 5.0])])
    below = contrib < 1.0
    for total in (0.0, 0.3, 3.0, 25.0, 1e9):
        mask = negligible(contrib, 1.0, total)
        assert not mask[~below].any()  # never one at or above the threshold
        assert float(contrib[mask].sum()) <= total + 1e-9
        # Brute force: the removed ones are the k smallest below the threshold, k as large as the sum allows.
        vals = sorted(contrib[below].tolist())
        k = 0
        while k < len(vals) and sum(vals[: k + 1]) <= total:
            k += 1
        assert int(mask.sum()) == k
        if k:
            assert float(contrib[mask].max()) <= vals[k - 1]
    assert negligible(contrib, 1.0, 1e9).equal(below)  # an unlimited total is the plain rule
    assert total_px(BudgetConfig(prune_total_frac=0.01), 80, 45) == 36.0
    with pytest.raises(ValueError):
        BudgetConfig(prune_total_frac=-0.1)
