"""3DGS density control against brute-force bookkeeping: which Gaussians are cloned/split/pruned, that Adam
moments and statistics follow them, split geometry, opacity reset, statistics accumulation and the cap."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import torch

from worldtree.gaussians import GaussianSet, quat_to_rotmat
from worldtree.optim import ConstantLR, GroupedAdam
from worldtree.strategy import DensifyStrategy, duplicate, remove, reset_opacity, split

CORE = ("means", "quats", "log_scales", "opacity_logits", "sh0")


def _make(n: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    log_scales = torch.log(torch.rand(n, 3, generator=g) * 0.03 + 0.001)  # max scale straddles 0.01
    opac = torch.rand(n, generator=g)
    opac[::7] = 0.001  # some prunable
    gs = GaussianSet(
        {
            "means": torch.randn(n, 3, generator=g),
            "quats": torch.randn(n, 4, generator=g),
            "log_scales": log_scales,
            "opacity_logits": torch.log(opac / (1 - opac)),
            "sh0": torch.randn(n, 3, generator=g),
            # An untrained per-Gaussian tensor: the ops must carry it too; it names each Gaussian.
            "ids": torch.arange(n, dtype=torch.float32),
        }
    )
    gs.params["ids"].requires_grad_(False)
    opt = GroupedAdam({k: gs.params[k] for k in CORE}, {k: ConstantLR(1e-3) for k in CORE})
    for k in CORE:
        gs.params[k].grad = torch.ones_like(gs.params[k])
    opt.step()
    # Tag every moment row with its Gaussian's id so that we can follow it.
    for k in CORE:
        st = opt.optimizer.state[gs.params[k]]
        shape = (n,) + (1,) * (gs.params[k].ndim - 1)
        st["exp_avg"] = (torch.arange(n, dtype=torch.float32) + 1).view(shape).expand_as(gs.params[k]).clone()
        st["exp_avg_sq"] = st["exp_avg"] * 10
    return gs, opt


def _fake_render(n: int, grad: torch.Tensor | None = None, radii=None, h: int = 20, w: int = 40):
    m2d = torch.zeros(n, 2)
    m2d.grad = grad
    return SimpleNamespace(
        means2d=m2d,
        radii=torch.zeros(n, dtype=torch.int32) if radii is None else radii,
        rgb=torch.zeros(h, w, 3),
    )


def test_refine_matches_brute_force_bookkeeping():
    n, extent, step = 60, 1.0, 600
    strat = DensifyStrategy(refine_start=500, refine_every=100, reset_every=3000)
    gs, opt = _make(n)
    state = strat.initialize_state(extent)
    g = torch.Generator().manual_seed(1)
    state["grad2d"] = torch.rand(n, generator=g) * 8e-4
    state["count"] = torch.randint(0, 4, (n,), generator=g).float()
    state["radii"] = torch.rand(n, generator=g) * 5
    before = {k: v.detach().clone() for k, v in gs.params.items()}

    # Brute force, one Gaussian at a time, in 3DGS order: clone, split, prune.
    rows = [("orig", i) for i in range(n)]
    clones, splits = [], []
    for i in range(n):
        avg = float(state["grad2d"][i]) / max(float(state["count"][i]), 1.0)
        if avg >= 2e-4:
            big = math.exp(float(before["log_scales"][i].max())) > 0.01 * extent
            (splits if big else clones).append(i)
    rows += [("clone", i) for i in clones]
    rows = [r for r in rows if not (r[0] == "orig" and r[1] in splits)]
    rows += [("child", i) for _ in range(2) for i in splits]
    opac = torch.sigmoid(before["opacity_logits"])
    rows = [r for r in rows if float(opac[r[1]]) >= 0.005]  # no size prune before the first reset

    report = strat.step_post_backward(gs, opt, state, step, _fake_render(n))
    assert report["cloned"] == len(clones) > 0
    assert report["split"] == len(splits) > 0
    assert report["pruned"] > 0
    assert len(gs) == len(rows)
    assert gs.params["ids"].tolist() == [float(r[1]) for r in rows]
    for k in CORE:
        p = gs.params[k]
        assert opt.group(k)["params"][0] is p, "the optimiser must hold the new tensor"
        st = opt.optimizer.state[p]
        for j, (kind, i) in enumerate(rows):
            expect = float(i + 1) if kind == "orig" else 0.0
            assert torch.all(st["exp_avg"][j] == expect), (k, j, kind, i)
            assert torch.all(st["exp_avg_sq"][j] == expect * 10)
    for j, (kind, i) in enumerate(rows):
        if kind in ("orig", "clone"):
            for k in CORE:
                assert torch.equal(gs.params[k][j].detach(), before[k][i])
        else:
            torch.testing.assert_close(
                gs.params["log_scales"][j].detach(), before["log_scales"][i] - math.log(1.6)
            )
            for k in ("quats", "opacity_logits", "sh0"):
                assert torch.equal(gs.params[k][j].detach(), before[k][i])
    # Statistics restart and are resized with the Gaussians.
    for k in ("grad2d", "count", "radii"):
        assert state[k].shape == (len(gs),) and not state[k].any()
    # The optimiser still steps with the new shapes.
    for k in CORE:
        gs.params[k].grad = torch.ones_like(gs.params[k])
    opt.step()


def test_size_prune_only_after_first_reset():
    strat = DensifyStrategy(refine_start=0, refine_every=100, reset_every=3000, grow_grad2d=1.0)
    gs = GaussianSet.from_tensors(
        torch.zeros(3, 3),
        torch.tensor([[0.05] * 3, [0.5] * 3, [0.01] * 3]),
        torch.full((3,), 0.5),
        torch.zeros(3, 3),
    )
    opt = GroupedAdam(dict(gs.params.items()), {k: ConstantLR(1e-3) for k in CORE})
    state = strat.initialize_state(1.0)
    strat.step_post_backward(gs, opt, state, 3000 - 100 * 2, _fake_render(3))
    assert len(gs) == 3
    strat.step_post_backward(gs, opt, state, 3100, _fake_render(3))
    assert len(gs) == 2  # the 0.5-sized one is larger than 0.1 * extent
    assert torch.allclose(gs.scales.max(dim=1).values, torch.tensor([0.05, 0.01]))


def test_accumulation_uses_ndc_gradient_of_visible_gaussians():
    n, h, w = 5, 20, 40
    strat = DensifyStrategy()
    gs, opt = _make(n)
    state = strat.initialize_state(1.0)
    grad = torch.tensor([[1.0, 0.0], [0.0, 2.0], [3.0, 4.0], [1.0, 1.0], [float("nan"), 0.0]]) * 1e-4
    radii = torch.tensor([1, 2, 0, 7, 3], dtype=torch.int32)
    for _ in range(2):
        strat.step_post_backward(gs, opt, state, 10, _fake_render(n, grad, radii, h, w))
    expect = [2 * math.hypot(g[0] * w / 2, g[1] * h / 2) for g in grad.tolist()[:4]]
    expect[2] = 0.0  # invisible
    expect.append(0.0)  # NaN counted as zero
    np.testing.assert_allclose(state["grad2d"].numpy(), expect, rtol=1e-6)
    assert state["count"].tolist() == [2, 2, 0, 2, 2]
    assert state["radii"].tolist() == [1, 2, 0, 7, 3]


def test_split_children_sample_the_parent_gaussian():
    k = 6000
    scales = torch.tensor([0.1, 0.02, 0.05])
    q = torch.tensor([0.9, 0.2, -0.3, 0.1])
    gs = GaussianSet.from_tensors(
        torch.tensor([1.0, 2.0, 3.0]).expand(k, 3),
        scales.expand(k, 3),
        torch.full((k,), 0.5),
        torch.zeros(k, 3),
        quats=q.expand(k, 4),
    )
    torch.manual_seed(0)
    split(gs, None, {}, torch.ones(k, dtype=torch.bool), children=2, scale_div=1.6)
    assert len(gs) == 2 * k
    torch.testing.assert_close(gs.scales.detach(), (scales / 1.6).expand(2 * k, 3))
    off = (gs.means.detach() - torch.tensor([1.0, 2.0, 3.0])).double()
    R = quat_to_rotmat(q.double())
    cov_expect = R @ torch.diag(scales.double() ** 2) @ R.T
    cov = off.T @ off / off.shape[0]
    assert off.mean(0).abs().max() < 4 * 0.1 / math.sqrt(2 * k)
    assert (cov - cov_expect).abs().max() < 0.06 * float(cov_expect.abs().max())
    # In the Gaussian's own frame the offsets are standard normal per axis.
    local = off @ R / scales.double()
    np.testing.assert_allclose(local.std(0).numpy(), [1, 1, 1], atol=0.04)


def test_opacity_reset_caps_and_zeros_only_opacity_moments():
    gs, opt = _make(20)
    before = gs.opacities.detach().clone()
    other = opt.optimizer.state[gs.params["sh0"]]["exp_avg"].clone()
    reset_opacity(gs, opt, {}, 0.01)
    torch.testing.assert_close(
        gs.opacities.detach(), torch.minimum(before, torch.tensor(0.01)), rtol=1e-5, atol=1e-7
    )
    st = opt.optimizer.state[gs.params["opacity_logits"]]
    assert not st["exp_avg"].any() and not st["exp_avg_sq"].any() and float(st["step"]) == 1
    assert torch.equal(opt.optimizer.state[gs.params["sh0"]]["exp_avg"], other)


def test_duplicate_and_remove_keep_order_and_moments():
    gs, opt = _make(10)
    mask = torch.zeros(10, dtype=torch.bool)
    mask[[2, 5]] = True
    state = {"grad2d": torch.arange(10.0), "count": torch.ones(10), "radii": torch.zeros(10)}
    duplicate(gs, opt, state, mask)
    assert gs.params["ids"].tolist() == [*range(10), 2, 5]
    assert state["grad2d"].tolist() == [*range(10), 0, 0]
    remove(gs, opt, state, torch.tensor([True] + [False] * 10 + [True]))
    assert gs.params["ids"].tolist() == [*range(1, 10), 2]
    st = opt.optimizer.state[gs.params["means"]]
    assert st["exp_avg"][:, 0].tolist() == [*range(2, 11), 0]


def test_cap_keeps_largest_gradients():
    n = 20
    strat = DensifyStrategy(
        refine_start=0, refine_every=1, reset_every=0, max_gaussians=n + 3, prune_opacity=0.0
    )
    gs = GaussianSet.from_tensors(
        torch.randn(n, 3), torch.full((n, 3), 1e-3), torch.full((n,), 0.5), torch.zeros(n, 3)
    )
    opt = GroupedAdam(dict(gs.params.items()), {k: ConstantLR(1e-3) for k in CORE})
    state = strat.initialize_state(1.0)
    state["grad2d"] = torch.linspace(1e-3, 2e-3, n)
    state["count"] = torch.ones(n)
    state["radii"] = torch.zeros(n)
    report = strat.step_post_backward(gs, opt, state, 1, _fake_render(n))
    assert report["cloned"] == 3 and len(gs) == n + 3
    # The three clones are copies of the three largest-gradient Gaussians (the last three).
    torch.testing.assert_close(gs.means[n:].detach(), gs.means[n - 3 : n].detach())
