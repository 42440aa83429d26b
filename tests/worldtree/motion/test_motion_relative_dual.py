"""The node motions ``T(t) T(t_ref)^-1`` as dual quaternions (skinning.relative_dual): the compiled CPU kernel
against the float64 tensor version (se3.relative + dualquat.from_quat_trans), closed-form motions, the guards."""

from __future__ import annotations

import math

import pytest
import torch

from tests.worldtree.motion.compiled_kernels import assert_same_bits_at_thread_counts, require_kernel
from worldtree.motion import dualquat, se3, skinning
from worldtree.motion import quaternion as Q

f64 = torch.float64



def _case(T: int, M: int, seed: int) -> list[torch.Tensor]:
    """``[q_t [1, M, 4], p_t [1, M, 3], q_ref [T, M, 4], p_ref [T, M, 3]]`` as the scaffold passes them, in
    float64 values that float32 holds exactly. Rotations of every norm (0.01 to 10), and the guarded rows: a zero
    reference quaternion, one below eps, the target's antipode (the same rotation), a zero target quaternion."""
    g = torch.Generator().manual_seed(seed)
    q_t = torch.randn(1, M, 4, generator=g, dtype=f64) * torch.exp(torch.randn(1, M, 1, generator=g, dtype=f64))
    p_t = 3 * torch.randn(1, M, 3, generator=g, dtype=f64)
    norm = torch.exp(2.3 * (2 * torch.rand(T, M, 1, generator=g, dtype=f64) - 1))
    q_ref = torch.randn(T, M, 4, generator=g, dtype=f64) * norm
    p_ref = 3 * torch.randn(T, M, 3, generator=g, dtype=f64)
    q_ref[0, 0] = 0.0
    q_ref[1, 1] = 1e-14
    q_ref[2, 2] = -2.5 * q_t[0, 2]
    q_t[0, 3] = 0.0
    return [x.float().double() for x in (q_t, p_t, q_ref, p_ref)]


def _values(fn, xs, dtype, seed=3):
    """(real, dual, gradients of a random linear loss w.r.t. every input) of ``fn`` in ``dtype``."""
    leaves = [x.to(dtype).detach().clone().requires_grad_(True) for x in xs]
    real, dual = fn(*leaves)
    g = torch.Generator().manual_seed(seed)
    wr = torch.randn(real.shape, generator=g, dtype=f64).to(dtype)
    wd = torch.randn(dual.shape, generator=g, dtype=f64).to(dtype)
    grads = torch.autograd.grad((real * wr).sum() + (dual * wd).sum(), leaves)
    return [real.detach(), dual.detach(), *grads]


@pytest.mark.parametrize("T, M", [(7, 13), (3, 5), (40, 33)])
def test_compiled_matches_the_float64_tensor_version(T, M):
    require_kernel()
    xs = _case(T, M, seed=T + M)
    assert skinning._relative_ops(*(x.float() for x in xs)) is not None
    got = _values(skinning.relative_dual, xs, torch.float32)
    want = _values(skinning._relative_dual_tensor, xs, f64)
    for a, b in zip(got, want, strict=True):
        assert a.dtype == torch.float32 and a.shape == b.shape and torch.isfinite(a).all()
        # Computed in double and rounded once: float32 rounding of each tensor's largest value, with margin.
        scale = max(1.0, float(b.abs().max()))
        torch.testing.assert_close(a.double(), b, rtol=1e-5, atol=2e-6 * scale)
    # The broadcast target pose gets the sum over the frames (autograd's expand backward) and is not all zero.
    assert got[2].shape == (1, M, 4) and want[2].abs().sum() > 0 and want[4].abs().sum() > 0


def test_guarded_quaternions_are_the_identity_with_zero_gradient():
    require_kernel()
    xs = _case(4, 6, seed=1)
    real, dual, g_qt, g_pt, g_qr, g_pr = _values(skinning.relative_dual, xs, torch.float32)
    # Zero and sub-eps reference rotations are the identity: the motion's rotation is the target's alone.
    for f, m in ((0, 0), (1, 1)):
        q_target = xs[0][0, m] / xs[0][0, m].norm()
        torch.testing.assert_close(real[f, m].double(), q_target, rtol=0, atol=1e-6)
        assert torch.equal(g_qr[f, m], torch.zeros(4))
    # The antipode of the target rotation (any norm) is the same rotation: no relative rotation.
    torch.testing.assert_close(real[2, 2].abs().double(), torch.tensor([1.0, 0, 0, 0], dtype=f64), rtol=0, atol=1e-6)
    # A zero target rotation is the identity for every reference frame, with zero gradient.
    assert torch.equal(g_qt[0, 3], torch.zeros(4))


def test_closed_form_motions():
    require_kernel()
    # A translation only: the motion is p_t - p_ref, dual = 0.5 (0, t).
    p_t, p_ref = torch.tensor([[1.0, -2.0, 0.5]]), torch.tensor([[0.25, 1.0, -3.0]])
    ident = torch.tensor([[2.0, 0.0, 0.0, 0.0]])  # any norm
    real, dual = skinning.relative_dual(ident, p_t, ident, p_ref)
    torch.testing.assert_close(real, torch.tensor([[1.0, 0, 0, 0]]))
    torch.testing.assert_close(dual, torch.cat([torch.zeros(1, 1), 0.5 * (p_t - p_ref)], 1))
    # A node turned by a about z at t_ref and by b at t: R_rel = Rz(b - a), t_rel = p_t - Rz(b - a) p_ref.
    a, b = 0.3, 1.1
    qa = torch.tensor([[math.cos(a / 2), 0, 0, math.sin(a / 2)]])
    qb = torch.tensor([[math.cos(b / 2), 0, 0, math.sin(b / 2)]])
    real, dual = skinning.relative_dual(qb, p_t, qa, p_ref)
    d = b - a
    torch.testing.assert_close(real, torch.tensor([[math.cos(d / 2), 0, 0, math.sin(d / 2)]]))
    rz = torch.tensor([[math.cos(d), -math.sin(d), 0], [math.sin(d), math.cos(d), 0], [0, 0, 1.0]])
    q, t = dualquat.to_quat_trans(real, dual)
    torch.testing.assert_close(t, p_t - p_ref @ rz.T, rtol=1e-5, atol=1e-6)
    # Carrying the reference position gives the target position (the node moves with its own motion).
    moved = Q.rotate(q, p_ref) + t
    torch.testing.assert_close(moved, p_t, rtol=1e-5, atol=1e-6)


def test_same_bits_for_any_thread_count():
    require_kernel()
    xs = _case(40, 60, seed=5)
    assert_same_bits_at_thread_counts(lambda: _values(skinning.relative_dual, xs, torch.float32))


def test_tensor_path_for_other_dtypes_and_scalars():
    xs = _case(3, 4, seed=2)
    assert skinning._relative_ops(*xs) is None  # float64: the tensor version
    real, dual = skinning.relative_dual(*xs)
    want = dualquat.from_quat_trans(*se3.relative(*xs))
    assert torch.equal(real, want[0]) and torch.equal(dual, want[1])
    # Unbatched float32 poses (no leading shape) take the tensor version too.
    one = [x[0, 0].float() for x in xs]
    real, dual = skinning.relative_dual(*one)
    assert real.shape == (4,) and dual.shape == (4,)


def test_a_nan_position_shows_in_the_outputs():
    require_kernel()
    xs = [x.float() for x in _case(3, 4, seed=4)]
    xs[3][1, 2, 0] = float("nan")
    real, dual = skinning.relative_dual(*xs)
    assert bool(torch.isnan(dual[1, 2]).any())
    others = torch.ones(3, 4, dtype=torch.bool)
    others[1, 2] = False
    assert torch.isfinite(dual[others]).all() and torch.isfinite(real).all()
