"""Dual quaternions and DQB: exactness, sign invariance, closed forms and every guarded edge case."""

from __future__ import annotations

import math

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from worldtree.motion import dualquat as DQ
from worldtree.motion import quaternion as Q
from worldtree.motion import se3

SETTINGS = settings(max_examples=40, deadline=None, derandomize=True)
f64 = torch.float64


def rot_z(angle: float) -> torch.Tensor:
    return torch.tensor([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)], dtype=f64)


def matrix(q: torch.Tensor, t: torch.Tensor) -> np.ndarray:
    """4x4 from scipy (independent of the code under test)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q.detach().cpu().double().numpy(), scalar_first=True).as_matrix()
    T[:3, 3] = t.detach().cpu().double().numpy()
    return T


def test_round_trip_product_and_inverse(device):
    rng = np.random.default_rng(0)
    q = torch.tensor(Rotation.random(20, random_state=1).as_quat(scalar_first=True), device=device) * 3.0
    t = torch.tensor(rng.normal(size=(20, 3)), device=device)
    r, d = DQ.from_quat_trans(q, t)
    np.testing.assert_allclose(r.norm(dim=-1).cpu().numpy(), 1.0, atol=1e-12)
    np.testing.assert_allclose((r * d).sum(-1).cpu().numpy(), 0.0, atol=1e-12)  # unit dual quaternion
    q2, t2 = DQ.to_quat_trans(r, d)
    torch.testing.assert_close(q2, Q.normalize(q))
    torch.testing.assert_close(t2, t)
    # product = composition
    q_b, t_b = q.roll(1, 0), t.roll(1, 0)
    pr, pd = DQ.multiply(r, d, *DQ.from_quat_trans(q_b, t_b))
    for i in (0, 7):
        qc, tc = DQ.to_quat_trans(pr[i], pd[i])
        np.testing.assert_allclose(matrix(qc, tc), matrix(q[i], t[i]) @ matrix(q_b[i], t_b[i]), atol=1e-12)
    # conjugate = inverse transform; dual conjugate flips the dual part only
    ir, idd = DQ.conjugate(r, d)
    qi, ti = DQ.to_quat_trans(ir, idd)
    np.testing.assert_allclose(matrix(qi[3], ti[3]), np.linalg.inv(matrix(q[3], t[3])), atol=1e-12)
    dr, dd = DQ.dual_conjugate(r, d)
    assert torch.equal(dr, r) and torch.equal(dd, -d)
    # a scaled, non-orthogonal dual quaternion normalises back to the same transform
    nr, nd = DQ.normalize(2.5 * r, 2.5 * d + 0.3 * r)
    torch.testing.assert_close(nr, r)
    torch.testing.assert_close(nd, d)


def test_normalize_and_to_quat_trans_zero_real_part():
    r = torch.zeros(2, 4, dtype=f64, requires_grad=True)
    d = torch.ones(2, 4, dtype=f64, requires_grad=True)
    q, t = DQ.to_quat_trans(r, d)
    np.testing.assert_allclose(q.detach().numpy(), [[1, 0, 0, 0]] * 2)
    np.testing.assert_allclose(t.detach().numpy(), 0.0)
    (q.sum() + t.sum()).backward()
    assert torch.isfinite(r.grad).all() and torch.isfinite(d.grad).all()


@st.composite
def shared_transform_case(draw):
    k = draw(st.integers(1, 6))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    angle = draw(st.sampled_from([0.0, 1e-9, 0.3, 2.0, math.pi - 1e-7, math.pi]))
    axis = rng.normal(size=3)
    q = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_quat(scalar_first=True)
    t = rng.normal(size=3) * 5
    signs = rng.choice([-1.0, 1.0], size=(k, 1))
    scales = rng.uniform(0.2, 3.0, size=(k, 1))  # any norm is allowed
    weights = rng.uniform(0.0, 1.0, size=k)
    weights[rng.integers(k)] += 0.05  # at least one positive weight
    weights = weights / weights.sum() * draw(st.sampled_from([1.0, 1.5, 7.0]))  # W >= 1: no identity mix
    return q, t, q[None] * signs * scales, np.tile(t, (k, 1)), weights


@SETTINGS
@given(shared_transform_case(), st.booleans())
def test_blend_of_one_shared_transform_is_exact(case, mix):
    q, t, qs, ts, w = case
    qb, tb = DQ.blend(torch.tensor(qs), torch.tensor(ts), torch.tensor(w), mix_identity=mix)
    np.testing.assert_allclose(matrix(qb, tb), matrix(torch.tensor(q), torch.tensor(t)), atol=1e-11)
    pts = np.random.default_rng(1).normal(size=(5, 3))
    moved = DQ.apply_points(qb, tb, torch.tensor(pts)).numpy()
    np.testing.assert_allclose(moved, Rotation.from_quat(q, scalar_first=True).apply(pts) + t, atol=1e-10)
    g = Rotation.random(5, random_state=2).as_quat(scalar_first=True)
    rots = DQ.apply_rotations(qb, torch.tensor(g))
    expected = (
        Rotation.from_quat(q, scalar_first=True) * Rotation.from_quat(g, scalar_first=True)
    ).as_matrix()
    np.testing.assert_allclose(Q.to_matrix(rots).numpy(), expected, atol=1e-11)


@SETTINGS
@given(st.integers(1, 6), st.integers(0, 2**31 - 1), st.sampled_from([0.3, 1.0, 3.0]))
def test_blend_is_invariant_to_input_quaternion_signs(k, seed, w_scale):
    rng = np.random.default_rng(seed)
    # transforms spread up to 180 degrees apart, also near a common 180-degree turn
    base = Rotation.random(random_state=seed % 1000)
    rots = base * Rotation.from_rotvec(rng.normal(size=(k, 3)) * rng.uniform(0.01, 1.5))
    q = torch.tensor(rots.as_quat(scalar_first=True))
    t = torch.tensor(rng.normal(size=(k, 3)))
    w = torch.tensor(rng.uniform(0.0, 1.0, size=k) * w_scale)
    flip = torch.tensor(rng.choice([-1.0, 1.0], size=(k, 1)))
    qa, ta = DQ.blend(q, t, w)
    qb, tb = DQ.blend(q * flip, t, w)
    np.testing.assert_allclose(matrix(qa, ta), matrix(qb, tb), atol=1e-12)


def test_pure_translations_blend_to_weighted_average():
    t = torch.tensor([[1.0, 0, 0], [0, 2.0, 0], [0, 0, -4.0]], dtype=f64)
    q = Q.identity((3,), f64)
    w = torch.tensor([0.5, 1.0, 0.5], dtype=f64)  # W = 2 > 1: normalised weights
    qb, tb = DQ.blend(q, t, w)
    np.testing.assert_allclose(tb.numpy(), [0.25, 1.0, -1.0], atol=1e-15)
    np.testing.assert_allclose(qb.numpy(), [1, 0, 0, 0], atol=1e-15)
    # W = 0.4 < 1: mixed with the identity, i.e. the raw weights scale the translations
    w = torch.tensor([0.1, 0.1, 0.2], dtype=f64)
    _, tb = DQ.blend(q, t, w)
    np.testing.assert_allclose(tb.numpy(), [0.1, 0.2, -0.8], atol=1e-15)
    _, tb = DQ.blend(q, t, w, mix_identity=False)
    np.testing.assert_allclose(tb.numpy(), [0.25, 0.5, -2.0], atol=1e-15)


def test_coaxial_rotations_blend_to_the_nlerp_angle():
    """About one axis, DQB of rotations is nlerp: angle = 2 atan2(sum c_i sin(a_i/2), sum c_i cos(a_i/2))."""
    for a, b, w1, w2 in ((0.2, 1.4, 0.3, 0.5), (2.0, -2.5, 0.7, 0.8), (0.0, 3.0, 0.1, 0.05)):
        q = torch.stack([rot_z(a), rot_z(b)])
        # the hemisphere of the stronger one decides the sign of the other
        sa, ca, sb, cb = math.sin(a / 2), math.cos(a / 2), math.sin(b / 2), math.cos(b / 2)
        piv = (sa, ca) if w1 >= w2 else (sb, cb)
        if piv[1] < 0:
            piv = (-piv[0], -piv[1])
        sa, ca = (sa, ca) if sa * piv[0] + ca * piv[1] >= 0 else (-sa, -ca)
        sb, cb = (sb, cb) if sb * piv[0] + cb * piv[1] >= 0 else (-sb, -cb)
        W = w1 + w2
        alpha = min(W, 1.0)
        c1, c2, c0 = alpha * w1 / W, alpha * w2 / W, 1 - alpha  # c0 = identity's share
        expected = 2 * math.atan2(c1 * sa + c2 * sb, c0 + c1 * ca + c2 * cb)
        qb, tb = DQ.blend(q, torch.zeros(2, 3, dtype=f64), torch.tensor([w1, w2], dtype=f64))
        np.testing.assert_allclose(
            Q.log(qb).numpy(), [0, 0, math.remainder(expected, 2 * math.pi)], atol=1e-12
        )
        np.testing.assert_allclose(tb.numpy(), 0.0, atol=1e-15)


def test_near_180_degree_rotations_blend_without_cancellation():
    deg = math.pi / 180
    q = torch.stack([rot_z(179 * deg), rot_z(181 * deg)])  # w = +0.0087 and -0.0087: on both sides of w = 0
    assert q[0, 0] > 0 > q[1, 0]
    qb, tb = DQ.blend(q, torch.zeros(2, 3, dtype=f64), torch.tensor([0.6, 0.6], dtype=f64))
    np.testing.assert_allclose(Q.angle(qb).item(), math.pi, atol=1e-12)
    np.testing.assert_allclose(Q.to_matrix(qb).numpy(), np.diag([-1.0, -1.0, 1.0]), atol=1e-12)
    # aligning each to w >= 0 separately (the naive fix) would average 179 and -179 degrees into ~0
    naive = Q.standardize(q).mean(0)
    assert Q.angle(naive).item() < 0.1
    # with translations: both transforms carry the origin to (1, 2, 3) -> so does the blend
    t = torch.tensor([[1.0, 2, 3], [1.0, 2, 3]], dtype=f64)
    qb, tb = DQ.blend(q, t, torch.tensor([0.6, 0.6], dtype=f64))
    np.testing.assert_allclose(tb.numpy(), [1, 2, 3], atol=1e-12)


def test_weight_sums_zero_and_tiny_give_identity():
    q = torch.tensor(Rotation.random(4, random_state=3).as_quat(scalar_first=True))
    t = torch.tensor(np.random.default_rng(4).normal(size=(4, 3)))
    for w_val, tol in ((0.0, 0.0), (1e-300, 1e-280), (1e-12, 1e-10)):
        w = torch.full((4,), w_val, dtype=f64)
        qb, tb = DQ.blend(q, t, w)
        np.testing.assert_allclose(qb.numpy(), [1, 0, 0, 0], atol=tol)
        np.testing.assert_allclose(tb.numpy(), 0.0, atol=tol)
    # a masked (zero) weight contributes nothing: same as dropping that neighbour
    w = torch.tensor([0.7, 0.0, 0.9, 0.0], dtype=f64)
    qa, ta = DQ.blend(q, t, w)
    qb, tb = DQ.blend(q[[0, 2]], t[[0, 2]], w[[0, 2]])
    np.testing.assert_allclose(matrix(qa, ta), matrix(qb, tb), atol=1e-14)


def test_no_neighbours_gives_identity():
    qb, tb = DQ.blend(torch.zeros(5, 0, 4), torch.zeros(5, 0, 3), torch.zeros(5, 0))
    assert qb.shape == (5, 4) and tb.shape == (5, 3)
    np.testing.assert_allclose(qb.numpy(), [[1, 0, 0, 0]] * 5)


def test_antipodal_inputs():
    q = Q.exp(torch.tensor([0.4, -0.2, 0.9], dtype=f64))
    t = torch.tensor([1.0, -1.0, 0.5], dtype=f64)
    qs, ts = torch.stack([q, -q]), torch.stack([t, t])
    w = torch.tensor([0.5, 0.5], dtype=f64)
    # aligned (default): q and -q are the same transform -> exact
    qb, tb = DQ.blend(qs, ts, w)
    np.testing.assert_allclose(matrix(qb, tb), matrix(q, t), atol=1e-14)
    # not aligned: the blend cancels to 0 -> falls back to the strongest neighbour's transform
    for mix in (True, False):
        qb, tb = DQ.blend(qs, ts, torch.tensor([1.0, 1.0], dtype=f64), mix_identity=mix, align=False)
        np.testing.assert_allclose(matrix(qb, tb), matrix(q, t), atol=1e-14)


def test_cancelling_negative_weights_fall_back_to_the_strongest():
    q = torch.stack(
        [Q.exp(torch.tensor([0.0, 0.0, 1.0], dtype=f64)), Q.exp(torch.tensor([0.0, 0.0, 1.0], dtype=f64))]
    )
    t = torch.tensor([[1.0, 0, 0], [1.0, 0, 0]], dtype=f64)
    qb, tb = DQ.blend(q, t, torch.tensor([0.5, -0.5], dtype=f64), mix_identity=False)
    np.testing.assert_allclose(matrix(qb, tb), matrix(q[0], t[0]), atol=1e-14)
    # with the identity mix, W = 0 means "stay put"
    qb, tb = DQ.blend(q, t, torch.tensor([0.5, -0.5], dtype=f64))
    np.testing.assert_allclose(matrix(qb, tb), np.eye(4), atol=1e-14)


def _blend_flat(q, t, w, mix):
    qb, tb = DQ.blend(q, t, w, mix_identity=mix)
    return torch.cat((qb, tb), -1)


def test_blend_gradcheck():
    rng = np.random.default_rng(5)
    q = torch.tensor(Rotation.random(6, random_state=6).as_quat(scalar_first=True)).reshape(2, 3, 4)
    q = q.requires_grad_(True)
    t = torch.tensor(rng.normal(size=(2, 3, 3)), requires_grad=True)
    for w_scale in (0.3, 2.0):  # W < 1 (identity mix active) and W > 1
        w = torch.tensor(rng.uniform(0.2, 1.0, size=(2, 3)) * w_scale, requires_grad=True)
        for mix in (True, False):
            assert torch.autograd.gradcheck(_blend_flat, (q, t, w, mix))


def test_blend_gradients_finite_at_guarded_edges():
    deg = math.pi / 180
    cases = {
        "zero_weights": (torch.stack([rot_z(1.0), rot_z(2.0)]), torch.zeros(2), True, True),
        "near_180": (torch.stack([rot_z(179 * deg), rot_z(181 * deg)]), torch.tensor([0.6, 0.6]), True, True),
        "exact_180": (torch.stack([rot_z(math.pi), rot_z(math.pi)]), torch.tensor([0.3, 0.3]), True, True),
        "antipodal_fallback": (
            torch.stack([rot_z(1.0), -rot_z(1.0)]),
            torch.tensor([1.0, 1.0]),
            False,
            False,
        ),
        "cancelling_weights": (torch.stack([rot_z(1.0), rot_z(1.0)]), torch.tensor([0.5, -0.5]), False, True),
    }
    for name, (q, w, mix, align) in cases.items():
        q = q.clone().requires_grad_(True)
        w = w.to(f64).requires_grad_(True)
        t = torch.ones(2, 3, dtype=f64, requires_grad=True)
        qb, tb = DQ.blend(q, t, w, mix_identity=mix, align=align)
        assert torch.isfinite(qb).all() and torch.isfinite(tb).all(), name
        (qb.sum() + tb.sum()).backward()
        for g in (q.grad, t.grad, w.grad):
            assert g is not None and torch.isfinite(g).all(), name


def test_blend_float32_on_each_device(device):
    q = torch.tensor(
        Rotation.random(8, random_state=7).as_quat(scalar_first=True), dtype=torch.float32, device=device
    )
    t = torch.randn(8, 3, device=device)
    w = torch.rand(8, device=device) + 0.4  # 3 neighbours: W >= 1.2, no identity mix
    qb, tb = DQ.blend(q[:, None].expand(8, 3, 4), t[:, None].expand(8, 3, 3), w[:, None].expand(8, 3))
    assert qb.device.type == device.type and qb.dtype == torch.float32
    x = torch.randn(8, 3, device=device)
    torch.testing.assert_close(DQ.apply_points(qb, tb, x), se3.apply(q, t, x), atol=1e-5, rtol=1e-5)
