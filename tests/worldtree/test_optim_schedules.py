"""Learning-rate schedules against closed forms; GroupedAdam groups, updates and state moves."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from worldtree.optim import (
    ConstantLR,
    CosineLR,
    ExponentialLR,
    GroupedAdam,
    adam_fused,
    fused_supported,
    gaussian_schedules,
)


def test_exponential_schedule_closed_form():
    s = ExponentialLR(init=1.6e-4, final=1.6e-6, max_steps=30_000)
    assert math.isclose(s(0), 1.6e-4, rel_tol=1e-12)
    assert math.isclose(s(30_000), 1.6e-6, rel_tol=1e-12)
    assert math.isclose(s(60_000), 1.6e-6, rel_tol=1e-12)  # held after the end
    assert math.isclose(s(15_000), math.sqrt(1.6e-4 * 1.6e-6), rel_tol=1e-12)  # geometric midpoint
    for step in (1, 777, 12_345, 29_999):
        expect = 1.6e-4 * (1.6e-6 / 1.6e-4) ** (step / 30_000)
        assert math.isclose(s(step), expect, rel_tol=1e-12)
    assert s(-1) == 0.0


def test_exponential_schedule_with_delay():
    s = ExponentialLR(init=1e-2, final=1e-4, max_steps=1000, delay_steps=100, delay_mult=0.01)
    assert math.isclose(s(0), 1e-2 * 0.01, rel_tol=1e-12)
    expect_50 = (0.01 + 0.99 * math.sin(0.25 * math.pi)) * 1e-2 * (1e-2) ** (50 / 1000)
    assert math.isclose(s(50), expect_50, rel_tol=1e-12)
    assert math.isclose(s(100), 1e-2 * (1e-2) ** 0.1, rel_tol=1e-12)
    with pytest.raises(ValueError):
        ExponentialLR(init=0.0, final=1e-4, max_steps=10)


def test_constant_and_cosine():
    assert ConstantLR(3e-3)(0) == ConstantLR(3e-3)(10**6) == 3e-3
    c = CosineLR(init=1.0, final=0.1, max_steps=100)
    assert math.isclose(c(0), 1.0) and math.isclose(c(100), 0.1) and math.isclose(c(50), 0.55)
    assert math.isclose(c(25), 0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi / 4)))


def test_grouped_adam_sets_lrs_and_steps_like_adam():
    a = nn.Parameter(torch.tensor([1.0, -2.0]))
    b = nn.Parameter(torch.tensor([[0.5]]))
    opt = GroupedAdam({"a": a, "b": b}, {"a": ExponentialLR(1e-1, 1e-3, 10), "b": ConstantLR(0.2)}, eps=1e-15)
    assert opt.names == ["a", "b"]
    opt.set_step(5)
    assert math.isclose(opt.lr("a"), 1e-1 * (1e-2) ** 0.5, rel_tol=1e-12)
    assert opt.lr("b") == 0.2
    # First Adam step with bias correction moves each element by lr * g / |g| (eps negligible).
    a.grad = torch.tensor([3.0, -0.5])
    b.grad = torch.tensor([[-4.0]])
    opt.step()
    lr_a = 1e-1 * (1e-2) ** 0.5
    torch.testing.assert_close(a.detach(), torch.tensor([1.0 - lr_a, -2.0 + lr_a]))
    torch.testing.assert_close(b.detach(), torch.tensor([[0.7]]))
    opt.zero_grad()
    assert a.grad is None


def test_replace_param_moves_state_rows():
    p = nn.Parameter(torch.arange(4.0))
    opt = GroupedAdam({"p": p}, {"p": ConstantLR(0.1)})
    p.grad = torch.tensor([1.0, 2.0, 3.0, 4.0])
    opt.step()
    before = opt.optimizer.state[p]["exp_avg"].clone()
    new = nn.Parameter(p.detach()[[3, 1]])
    opt.replace_param("p", new, lambda _k, m: m[[3, 1]])
    st = opt.optimizer.state[new]
    torch.testing.assert_close(st["exp_avg"], before[[3, 1]])
    assert p not in opt.optimizer.state
    assert opt.group("p")["params"][0] is new
    assert float(st["step"]) == 1.0


def _adam_reference(x0, grads, lrs, eps, betas=(0.9, 0.999)):
    """Kingma & Ba's update with bias correction, in float64, one step per gradient."""
    x, m, v = (
        x0.double().clone(),
        torch.zeros_like(x0, dtype=torch.float64),
        torch.zeros_like(x0, dtype=torch.float64),
    )
    for k, (g, lr) in enumerate(zip(grads, lrs, strict=True), start=1):
        g = g.double()
        m = betas[0] * m + (1 - betas[0]) * g
        v = betas[1] * v + (1 - betas[1]) * g * g
        mh, vh = m / (1 - betas[0] ** k), v / (1 - betas[1] ** k)
        x = x - lr * mh / (vh.sqrt() + eps)
    return x


@pytest.mark.parametrize("fused", [None, False, True])
def test_grouped_adam_follows_adam_over_many_steps(fused):
    """The fused and the single-tensor update both follow the textbook Adam (float32 rounding only), under
    a changing learning rate and with a gradient that is zero for some elements."""
    g = torch.Generator().manual_seed(3)
    x0 = torch.randn(64, 3, generator=g)
    grads = [
        torch.randn(64, 3, generator=g) * 10.0 ** torch.randint(-6, 2, (64, 1), generator=g)
        for _ in range(40)
    ]
    for gr in grads[::7]:
        gr[:5] = 0.0
    sched = ExponentialLR(1e-2, 1e-4, 40)
    p = nn.Parameter(x0.clone())
    opt = GroupedAdam({"p": p}, {"p": sched}, eps=1e-15, fused=fused)
    assert bool(opt.group("p")["fused"]) == (fused is not False)  # a float32 CPU tensor takes the fused path
    for k, gr in enumerate(grads):
        opt.set_step(k)
        p.grad = gr.clone()
        opt.step()
    expect = _adam_reference(x0, grads, [sched(k) for k in range(40)], 1e-15)
    # Each step moves an element by at most about lr; 40 steps of float32 rounding stay far under 1e-5.
    torch.testing.assert_close(p.detach().double(), expect, rtol=0, atol=1e-5)
    assert torch.isfinite(p).all()


def test_fused_supported_only_for_dense_float_tensors_on_one_device():
    f = torch.zeros(3)
    assert fused_supported([f, torch.zeros(2, dtype=torch.float64)])
    assert not fused_supported([])
    assert not fused_supported([torch.zeros(3, dtype=torch.int64)])
    assert not fused_supported([torch.zeros(3).to_sparse()])
    assert not fused_supported([torch.zeros(3, device="meta")])
    if torch.cuda.is_available():
        assert not fused_supported([f, f.cuda()])


def test_adam_fused_is_true_or_none_never_false():
    """None leaves torch its own default (foreach on CUDA); False would switch that off as well."""
    f, i = torch.zeros(3), torch.zeros(3, dtype=torch.int64)
    assert adam_fused([f]) is True and adam_fused([i]) is None
    assert adam_fused([f], want=False) is None and adam_fused([i], want=True) is True


def test_missing_schedule_is_an_error():
    with pytest.raises(ValueError, match="no learning-rate schedule"):
        GroupedAdam({"x": nn.Parameter(torch.zeros(1))}, {})


def test_gaussian_schedules_3dgs_groups():
    s = gaussian_schedules(1.6e-4, 1.6e-6, 100, 1e-3, 5e-3, 0.05, 2.5e-3)
    assert set(s) == {"means", "quats", "log_scales", "opacity_logits", "sh0"}
    # Positions decay log-linearly from the first to the final rate; the midpoint is their geometric mean.
    assert s["means"](0) == pytest.approx(1.6e-4)
    assert s["means"](100) == pytest.approx(1.6e-6)
    assert s["means"](50) == pytest.approx(math.sqrt(1.6e-4 * 1.6e-6))
    assert [s[k](77) for k in ("quats", "log_scales", "opacity_logits", "sh0")] == [1e-3, 5e-3, 0.05, 2.5e-3]
