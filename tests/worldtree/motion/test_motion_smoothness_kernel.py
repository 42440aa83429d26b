"""The scaffold's velocity and acceleration terms (regularizers.smoothness_losses): the compiled CPU kernel against
the float64 tensor functions (velocity_losses, acceleration_losses), closed-form trajectories and the guards."""

from __future__ import annotations

import math

import pytest
import torch

from tests.worldtree.motion.compiled_kernels import assert_same_bits_at_thread_counts, require_kernel
from worldtree.motion import regularizers as R

f64 = torch.float64



def _case(T: int, M: int, seed: int) -> list[torch.Tensor]:
    """Random-walk trajectories of every rotation norm, with the guarded entries: a zero quaternion, a node's
    rotation followed by its antipode (no turn), a node at rest for a frame (zero velocity) and one at constant
    velocity for three frames (zero acceleration). Float64 values that float32 holds exactly."""
    g = torch.Generator().manual_seed(seed)
    pos = torch.cumsum(torch.randn(T, M, 3, generator=g, dtype=f64), 0)
    quat = torch.randn(T, M, 4, generator=g, dtype=f64) * torch.exp(torch.randn(T, M, 1, generator=g, dtype=f64))
    if T >= 3 and M >= 4:
        quat[1, 0] = 0.0
        quat[2, 1] = -3.0 * quat[1, 1]
        pos[2, 2] = pos[1, 2]
        pos[2, 3] = 2 * pos[1, 3] - pos[0, 3]
    return [x.float().double() for x in (pos, quat)]


def _values(fn, xs, dtype, seed=5):
    leaves = [x.to(dtype).detach().clone().requires_grad_(True) for x in xs]
    out = fn(*leaves)
    w = torch.randn(4, generator=torch.Generator().manual_seed(seed), dtype=f64).to(dtype)
    grads = torch.autograd.grad(sum(o * wi for o, wi in zip(out, w, strict=True)), leaves)
    return [torch.stack([o.detach() for o in out]), *grads]


@pytest.mark.parametrize("T, M", [(12, 37), (3, 5), (40, 8)])
def test_compiled_matches_the_float64_tensor_version(T, M):
    require_kernel()
    xs = _case(T, M, seed=T * M)
    assert R._compiled_ops(xs[0].float()) is not None
    got = _values(R.smoothness_losses, xs, torch.float32)
    want = _values(R._smoothness_tensor, xs, f64)
    for a, b in zip(got, want, strict=True):
        assert a.dtype == torch.float32 and a.shape == b.shape and torch.isfinite(a).all()
        scale = max(1.0, float(b.abs().max()))
        torch.testing.assert_close(a.double(), b, rtol=1e-5, atol=2e-6 * scale)
    assert want[1].abs().sum() > 0 and want[2].abs().sum() > 0


@pytest.mark.parametrize("T, M", [(1, 4), (2, 4), (3, 0), (5, 1)])
def test_short_videos_and_empty_scaffolds_are_zero_where_the_tensor_version_is(T, M):
    require_kernel()
    xs = _case(T, M, seed=1)
    got = _values(R.smoothness_losses, xs, torch.float32)
    want = _values(R._smoothness_tensor, xs, f64)
    for a, b in zip(got, want, strict=True):
        assert torch.isfinite(a).all()
        torch.testing.assert_close(a.double(), b, rtol=1e-5, atol=1e-6)
    if T < 3:
        assert float(got[0][2]) == 0.0 and float(got[0][3]) == 0.0


def test_closed_form_trajectories():
    require_kernel()
    # Every node moves by v per frame along x and turns by w radians per frame about its own fixed axis, at any
    # quaternion norm: speed |v|, angular speed w, no acceleration of either kind.
    T, M, v, w = 10, 3, 0.25, 0.1
    t = torch.arange(T, dtype=f64)[:, None]
    pos = torch.zeros(T, M, 3, dtype=f64)
    pos[..., 0] = v * t + torch.arange(M, dtype=f64)
    axes = torch.nn.functional.normalize(torch.tensor([[1.0, 2, 3], [0, 0, 1], [-1, 0.5, 0]], dtype=f64), dim=-1)
    half = 0.5 * w * t[..., None]  # [T, 1, 1]
    quat = torch.cat([torch.cos(half).expand(T, M, 1), torch.sin(half) * axes[None]], -1) * 2.5
    vx, vr, ax, ar = R.smoothness_losses(pos.float(), quat.float())
    assert float(vx) == pytest.approx(v, rel=1e-5)
    assert float(vr) == pytest.approx(w, rel=1e-4)
    # Zero acceleration reads sqrt(FLT_MIN) through the guard (1e-19), not 0 / 0.
    assert 0.0 <= float(ax) < 1e-6 and 0.0 <= float(ar) < 1e-5
    # A half turn per frame is the largest angle there is: pi, from either sign of the quaternion.
    quat2 = torch.zeros(2, 1, 4)
    quat2[0, 0, 0] = 1.0
    quat2[1, 0, 3] = -1.0
    _, vr2, _, _ = R.smoothness_losses(torch.zeros(2, 1, 3), quat2)
    assert float(vr2) == pytest.approx(math.pi, rel=1e-6)


def test_same_bits_for_any_thread_count():
    require_kernel()
    xs = _case(30, 301, seed=9)
    assert_same_bits_at_thread_counts(lambda: _values(R.smoothness_losses, xs, torch.float32))


def test_float64_takes_the_tensor_functions():
    xs = _case(6, 4, seed=3)
    assert R._compiled_ops(xs[0]) is None
    got = R.smoothness_losses(*xs)
    want = (*R.velocity_losses(*xs), *R.acceleration_losses(*xs))
    for a, b in zip(got, want, strict=True):
        assert torch.equal(a, b)
