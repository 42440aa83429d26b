"""Same seed, same run: the deterministic-kernel switch (worldtree.infra.determinism)."""

from __future__ import annotations

import torch

from worldtree.infra.determinism import deterministic_for


def _gather_grad(x, idx, w):
    x.grad = None
    (x[idx] * w).sum().backward()
    return x.grad.clone()


def test_cpu_switch_makes_index_backward_repeat_bit_for_bit():
    """The backward of ``x[idx]`` with many repeated indices (the scaffold gathers' pattern) adds in thread
    order unless deterministic kernels are on; with the switch every repeat equals the first exactly, and
    the gradient is the float64 per-row sum (an independent computation) to float32 rounding."""
    torch.set_num_threads(2)  # the accumulation races only with more than one thread (conftest resets both)
    assert deterministic_for("cpu") is True
    assert torch.are_deterministic_algorithms_enabled()
    g = torch.Generator().manual_seed(0)
    x = torch.randn(1000, 3, generator=g, requires_grad=True)
    idx = torch.randint(0, 1000, (400_000,), generator=g)
    w = torch.randn(400_000, 3, generator=g)
    first = _gather_grad(x, idx, w)
    assert all(torch.equal(first, _gather_grad(x, idx, w)) for _ in range(10))
    ref = torch.zeros(1000, 3, dtype=torch.float64).index_add_(0, idx, w.double())
    torch.testing.assert_close(first.double(), ref, rtol=1e-4, atol=1e-3)


def test_cuda_device_leaves_the_switch_off():
    """On CUDA the flag is off (gsplat's atomics ignore it; cuBLAS would need an environment setting);
    naming the device needs no GPU."""
    torch.use_deterministic_algorithms(True)
    assert deterministic_for("cuda:0") is False
    assert not torch.are_deterministic_algorithms_enabled()
    assert deterministic_for(torch.device("cpu")) is True
