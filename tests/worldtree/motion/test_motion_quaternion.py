"""Quaternion maths against scipy's Rotation (an independent implementation) and closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation, Slerp

from worldtree.motion import quaternion as Q

SETTINGS = settings(max_examples=40, deadline=None, derandomize=True)
f64 = torch.float64

quat_arrays = arrays(np.float64, 4, elements=st.floats(-2.0, 2.0)).filter(lambda q: np.linalg.norm(q) > 1e-3)
vec_arrays = arrays(np.float64, 3, elements=st.floats(-5.0, 5.0))


def scipy_rot(q: np.ndarray) -> Rotation:
    return Rotation.from_quat(np.asarray(q, dtype=np.float64), scalar_first=True)


def same_rotation(a: torch.Tensor, b: np.ndarray, atol: float) -> bool:
    """Quaternions equal up to sign."""
    a = a.detach().cpu().numpy()
    b = np.asarray(b) / np.linalg.norm(b, axis=-1, keepdims=True)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    dots = np.abs((a * b).sum(-1))
    return bool(np.all(np.abs(dots - 1.0) < atol))


def near_pi_matrices() -> np.ndarray:
    """Rotations at and within 1e-9..1e-3 rad of 180 degrees about assorted axes (trace near -1)."""
    rng = np.random.default_rng(3)
    axes = np.concatenate([np.eye(3), rng.normal(size=(20, 3))])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    out = []
    for delta in (0.0, 1e-9, 1e-6, 1e-3):
        out.append(Rotation.from_rotvec(axes * (math.pi - delta)).as_matrix())
    return np.concatenate(out)


@SETTINGS
@given(quat_arrays)
def test_to_matrix_matches_scipy_for_any_norm(q):
    R = Q.to_matrix(torch.tensor(q))
    np.testing.assert_allclose(R.numpy(), scipy_rot(q).as_matrix(), atol=1e-12)


@SETTINGS
@given(quat_arrays)
def test_from_matrix_round_trip_matches_scipy(q):
    R = scipy_rot(q).as_matrix()
    got = Q.from_matrix(torch.tensor(R))
    assert got[0] >= 0
    assert same_rotation(got, q, 1e-12)
    np.testing.assert_allclose(Q.to_matrix(got).numpy(), R, atol=1e-12)


def test_from_matrix_near_180_degrees_and_identity(device):
    Rs = np.concatenate([near_pi_matrices(), np.eye(3)[None]])
    for dtype, atol in ((torch.float64, 1e-12), (torch.float32, 2e-6)):
        got = Q.from_matrix(torch.tensor(Rs, dtype=dtype, device=device))
        assert torch.isfinite(got).all()
        assert same_rotation(got.double(), Rotation.from_matrix(Rs).as_quat(scalar_first=True), atol)
        np.testing.assert_allclose(Q.to_matrix(got).double().cpu().numpy(), Rs, atol=10 * atol)


def test_from_matrix_gradient_finite_at_180_and_identity():
    Rs = torch.tensor(np.concatenate([near_pi_matrices()[:3], np.eye(3)[None]]), requires_grad=True)
    Q.from_matrix(Rs).sum().backward()
    assert torch.isfinite(Rs.grad).all()


@SETTINGS
@given(quat_arrays, quat_arrays)
def test_multiply_is_scipy_composition(a, b):
    got = Q.multiply(torch.tensor(a), torch.tensor(b))
    # Hamilton product scales norms; compare the rotation it represents.
    assert same_rotation(got, (scipy_rot(a) * scipy_rot(b)).as_quat(scalar_first=True), 1e-12)
    np.testing.assert_allclose(got.norm().item(), np.linalg.norm(a) * np.linalg.norm(b), rtol=1e-12)


@SETTINGS
@given(quat_arrays, vec_arrays)
def test_rotate_and_conjugate_match_scipy(q, v):
    qt, vt = torch.tensor(q), torch.tensor(v)
    np.testing.assert_allclose(Q.rotate(qt, vt).numpy(), scipy_rot(q).apply(v), atol=1e-11)
    np.testing.assert_allclose(Q.rotate(Q.conjugate(qt), vt).numpy(), scipy_rot(q).inv().apply(v), atol=1e-11)
    np.testing.assert_allclose(Q.multiply(Q.inverse(qt), qt).numpy(), [1, 0, 0, 0], atol=1e-12)


def test_rotate_broadcasts_batch_shapes(device):
    q = Q.normalize(torch.randn(5, 1, 4, device=device))
    v = torch.randn(1, 7, 3, device=device)
    out = Q.rotate(q, v)
    assert out.shape == (5, 7, 3)
    ref = (Q.to_matrix(q) @ v[..., None])[..., 0]
    torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-5)


def test_normalize_zero_and_tiny_quaternions_are_safe():
    q = torch.tensor([[0.0, 0, 0, 0], [1e-30, 0, 0, 0], [0, 3.0, 0, 4.0]], dtype=f64, requires_grad=True)
    out = Q.normalize(q)
    np.testing.assert_allclose(out.detach().numpy(), [[1, 0, 0, 0], [1, 0, 0, 0], [0, 0.6, 0, 0.8]])
    out.sum().backward()
    assert torch.isfinite(q.grad).all()
    assert torch.all(q.grad[:2] == 0)
    np.testing.assert_allclose(Q.to_matrix(q[:1].detach()).numpy()[0], np.eye(3))


def test_align_sign_and_standardize():
    ref = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=f64)
    q = torch.tensor([[0.1, -0.9, 0.3, 0.0], [0.1, 0.9, 0.3, 0.0]], dtype=f64)
    out = Q.align_sign(q, ref)
    assert torch.all((out * ref).sum(-1) >= 0)
    np.testing.assert_allclose(out.numpy(), [[-0.1, 0.9, -0.3, 0.0], [0.1, 0.9, 0.3, 0.0]])
    assert torch.all(Q.standardize(-q)[:, 0] >= 0)


@SETTINGS
@given(arrays(np.float64, 3, elements=st.floats(-3.1, 3.1)))
def test_exp_log_match_scipy_rotvec(w):
    got = Q.exp(torch.tensor(w))
    assert same_rotation(got, Rotation.from_rotvec(w).as_quat(scalar_first=True), 1e-12)
    if np.linalg.norm(w) < math.pi - 1e-6:
        np.testing.assert_allclose(Q.log(got).numpy(), w, atol=1e-11)


@pytest.mark.parametrize("theta", [0.0, 1e-300, 1e-20, 1e-9, 1e-5, 1e-3, 0.05, 0.06, 0.3, 0.5])
def test_exp_log_small_angles_are_accurate(theta):
    axis = np.array([0.3, -0.5, 0.81])
    axis /= np.linalg.norm(axis)
    w = axis * theta
    # Closed form evaluated in extended precision by the Python float path (sin/cos of tiny args are exact).
    expected = np.concatenate([[math.cos(theta / 2)], math.sin(theta / 2) * axis])
    for dtype, rtol in ((torch.float64, 1e-14), (torch.float32, 1e-6)):
        q = Q.exp(torch.tensor(w, dtype=dtype))
        np.testing.assert_allclose(q.double().numpy(), expected, rtol=rtol, atol=rtol * 1e-30)
        back = Q.log(torch.tensor(expected, dtype=dtype)).double().numpy()
        np.testing.assert_allclose(back, w, rtol=10 * rtol, atol=1e-300)


def test_log_near_180_degrees():
    for delta in (0.0, 1e-12, 1e-7, 1e-3):
        w = np.array([0.0, 0.0, math.pi - delta])
        q = Q.exp(torch.tensor(w))
        got = Q.log(q).numpy()
        if delta == 0.0:  # either +pi or -pi about z is correct
            np.testing.assert_allclose(np.abs(got), np.abs(w), atol=1e-12)
        else:
            np.testing.assert_allclose(got, w, atol=1e-12)
    q = torch.tensor([-1e-17, 0.0, 0.0, 1.0], dtype=f64)  # just past pi: standardised to the other side
    np.testing.assert_allclose(np.abs(Q.log(q).numpy()), [0, 0, math.pi], atol=1e-12)


def test_exp_log_gradcheck_small_and_zero_angles():
    for scale in (0.0, 1e-8, 1e-3, 0.04, 1.0):
        w = (torch.tensor([[0.3, -0.2, 0.5]], dtype=f64) * scale).requires_grad_(True)
        assert torch.autograd.gradcheck(Q.exp, (w,))
        q = Q.exp(w.detach()).requires_grad_(True)
        assert torch.autograd.gradcheck(Q.log, (q,))
    zero = torch.zeros(1, 3, dtype=f64, requires_grad=True)
    Q.exp(zero).sum().backward()
    np.testing.assert_allclose(zero.grad.numpy(), [[0.5, 0.5, 0.5]])  # d(0.5 w)/dw at 0
    ident = Q.identity((1,), f64).requires_grad_(True)
    Q.log(ident).sum().backward()
    assert torch.isfinite(ident.grad).all()


def test_angle_and_angle_between():
    rng = np.random.default_rng(0)
    a, b = Rotation.random(50, random_state=1), Rotation.random(50, random_state=2)
    ta, tb = torch.tensor(a.as_quat(scalar_first=True)), torch.tensor(b.as_quat(scalar_first=True))
    np.testing.assert_allclose(Q.angle_between(ta, -tb).numpy(), (a.inv() * b).magnitude(), atol=1e-12)
    # The unit and component-major forms (what the motion regularisers call) against scipy and against the
    # composition they replace, with the same gradients.
    ua = ta.clone().requires_grad_(True)
    np.testing.assert_allclose(Q.angle_between_unit(ua, -tb).detach().numpy(), (a.inv() * b).magnitude(), atol=1e-12)
    ref = torch.autograd.grad(Q.angle(Q.multiply(Q.conjugate(ua), tb)).sum(), ua)[0]
    got = torch.autograd.grad(Q.angle_between_components(ua.T, tb.T).sum(), ua)[0]
    np.testing.assert_allclose(got.numpy(), ref.numpy(), atol=1e-10)
    np.testing.assert_allclose(
        Q.multiply_components(ta.T, tb.T).T.numpy(), Q.multiply(ta, tb).numpy(), atol=1e-15
    )
    # Same rotation (either sign) and half a turn apart: 0 and pi, finite gradients at both.
    half = Q.multiply(ta[:1], Q.from_axis_angle(torch.tensor([[0.0, 0.6, 0.8]], dtype=f64), math.pi))
    pairs = torch.cat((ta[:1], -ta[:1], half)).requires_grad_(True)
    ang = Q.angle_between_unit(ta[:1].expand(3, 4), pairs)
    np.testing.assert_allclose(ang.detach().numpy(), [0.0, 0.0, math.pi], atol=1e-7)
    ang.sum().backward()
    assert torch.isfinite(pairs.grad).all()
    tiny = torch.tensor(Rotation.from_rotvec(rng.normal(size=(4, 3)) * 1e-9).as_quat(scalar_first=True))
    np.testing.assert_allclose(
        Q.angle(tiny).numpy(), Rotation.from_quat(tiny.numpy(), scalar_first=True).magnitude(), rtol=1e-9
    )


@SETTINGS
@given(quat_arrays, quat_arrays, st.floats(0.0, 1.0))
def test_slerp_matches_scipy(a, b, t):
    ra, rb = scipy_rot(a), scipy_rot(b)
    if (ra.inv() * rb).magnitude() > math.pi - 1e-6:
        return  # the two shorter arcs are equally long; scipy and we may pick either
    ref = Slerp([0.0, 1.0], Rotation.concatenate([ra, rb]))([t]).as_quat(scalar_first=True)[0]
    got = Q.slerp(torch.tensor(a), torch.tensor(b), t)
    assert same_rotation(got, ref, 1e-10)
    assert same_rotation(Q.slerp(torch.tensor(a), torch.tensor(b), 0.0), a, 1e-12)
    assert same_rotation(Q.slerp(torch.tensor(a), torch.tensor(b), 1.0), b, 1e-12)


def test_slerp_midpoint_halves_the_angle_and_takes_short_arc():
    a = Q.exp(torch.tensor([0.0, 0.0, 0.2], dtype=f64))
    b = -Q.exp(torch.tensor([0.0, 0.0, 1.4], dtype=f64))  # negated: must still take the short arc
    mid = Q.slerp(a, b, 0.5)
    np.testing.assert_allclose(Q.log(mid).numpy(), [0, 0, 0.8], atol=1e-12)
    # batched t
    out = Q.slerp(a, b, torch.tensor([0.0, 0.25, 1.0], dtype=f64))
    np.testing.assert_allclose(Q.log(out).numpy()[:, 2], [0.2, 0.5, 1.4], atol=1e-12)


def test_slerp_identical_and_nearly_identical_endpoints():
    a = Q.exp(torch.tensor([0.1, 0.2, 0.3], dtype=f64))
    for d in (0.0, 1e-14, 1e-9):
        b = Q.exp(torch.tensor([0.1, 0.2, 0.3 + d], dtype=f64))
        a_ = a.clone().requires_grad_(True)
        b_ = b.clone().requires_grad_(True)
        out = Q.slerp(a_, b_, 0.3)
        expected = Q.exp(torch.tensor([0.1, 0.2, 0.3 + 0.3 * d], dtype=f64))
        np.testing.assert_allclose(out.detach().numpy(), expected.numpy(), atol=1e-14)
        out.sum().backward()
        assert torch.isfinite(a_.grad).all() and torch.isfinite(b_.grad).all()


def test_slerp_gradcheck():
    a = Q.exp(torch.tensor([0.1, 0.2, 0.3], dtype=f64)).requires_grad_(True)
    b = Q.exp(torch.tensor([-0.4, 0.9, 0.1], dtype=f64)).requires_grad_(True)
    t = torch.tensor(0.37, dtype=f64, requires_grad=True)
    assert torch.autograd.gradcheck(Q.slerp, (a, b, t))


@SETTINGS
@given(vec_arrays, vec_arrays)
def test_from_two_vectors_is_the_smallest_rotation(a, b):
    if np.linalg.norm(a) < 1e-3 or np.linalg.norm(b) < 1e-3:
        return
    q = Q.from_two_vectors(torch.tensor(a), torch.tensor(b))
    ua, ub = a / np.linalg.norm(a), b / np.linalg.norm(b)
    np.testing.assert_allclose(Q.rotate(q, torch.tensor(ua)).numpy(), ub, atol=1e-10)
    np.testing.assert_allclose(Q.angle(q).item(), math.acos(np.clip(ua @ ub, -1, 1)), atol=1e-7)


def test_from_two_vectors_opposite_parallel_and_zero():
    a = torch.tensor([[1.0, 0, 0], [0, 0, 2.0], [0.3, 0.4, 0.5], [0, 0, 0]], dtype=f64)
    b = torch.tensor([[-3.0, 0, 0], [0, 0, -1.0], [0.6, 0.8, 1.0], [1, 0, 0]], dtype=f64)
    q = Q.from_two_vectors(a, b)
    assert torch.isfinite(q).all()
    ub = b[:3] / b[:3].norm(dim=-1, keepdim=True)
    np.testing.assert_allclose(
        Q.rotate(q[:3], a[:3] / a[:3].norm(dim=-1, keepdim=True)).numpy(), ub.numpy(), atol=1e-12
    )
    np.testing.assert_allclose(Q.angle(q).numpy(), [math.pi, math.pi, 0, 0], atol=1e-12)


def test_6d_round_trip_and_degenerate_inputs():
    R = torch.tensor(Rotation.random(20, random_state=4).as_matrix())
    np.testing.assert_allclose(Q.matrix_from_6d(Q.matrix_to_6d(R)).numpy(), R.numpy(), atol=1e-12)
    d6 = torch.tensor(
        [[0.0] * 6, [1.0, 2, 3, 2, 4, 6], [0, 0, 0, 1, 0, 0], [2.0, 0, 0, 5, 1e-12, 0]], dtype=f64
    )
    d6.requires_grad_(True)
    M = Q.matrix_from_6d(d6)
    eye = torch.eye(3, dtype=f64).expand_as(M)
    torch.testing.assert_close(M.transpose(-1, -2) @ M, eye, atol=1e-12, rtol=0)
    np.testing.assert_allclose(torch.linalg.det(M).detach().numpy(), 1.0, atol=1e-12)
    M.sum().backward()
    assert torch.isfinite(d6.grad).all()


def test_gradients_finite_at_exact_singular_points():
    """Exact zeros and 180-degree turns, where an unguarded torch.where branch would poison the gradient."""
    # log at exactly 180 degrees (w = 0) and at the identity
    q = torch.tensor(
        [[0.0, 0.0, 0.0, 1.0], [0.0, 0.6, 0.8, 0.0], [1.0, 0, 0, 0]], dtype=f64, requires_grad=True
    )
    Q.log(q).sum().backward()
    assert torch.isfinite(q.grad).all()
    # slerp at the endpoints t = 0 and t = 1 (sinc of an exact 0)
    a = Q.exp(torch.tensor([0.1, 0.2, 0.3], dtype=f64)).requires_grad_(True)
    b = Q.exp(torch.tensor([-0.4, 0.9, 0.1], dtype=f64)).requires_grad_(True)
    t = torch.tensor([0.0, 1.0], dtype=f64, requires_grad=True)
    Q.slerp(a, b, t).sum().backward()
    for g in (a.grad, b.grad, t.grad):
        assert torch.isfinite(g).all()
    # angle and from_axis_angle with a zero axis
    axis = torch.zeros(3, dtype=f64, requires_grad=True)
    Q.angle(Q.from_axis_angle(axis, 1.0)).backward()
    assert torch.isfinite(axis.grad).all()
