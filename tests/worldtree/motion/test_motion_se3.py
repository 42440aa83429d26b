"""SE(3) helpers against 4x4 matrix algebra, scipy's matrix exponential and scipy's align_vectors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from worldtree.motion import se3

SETTINGS = settings(max_examples=40, deadline=None, derandomize=True)
f64 = torch.float64


def random_pose(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)
    q = torch.tensor(Rotation.random(n, random_state=seed).as_quat(scalar_first=True))
    return q * torch.tensor(rng.uniform(0.5, 2.0, size=(n, 1))), torch.tensor(rng.normal(size=(n, 3)) * 3)


def as_matrix(q: torch.Tensor, t: torch.Tensor) -> np.ndarray:
    """4x4 matrices built with scipy (independent of se3.to_matrix)."""
    q = q.detach().numpy()
    T = np.tile(np.eye(4), (q.shape[0], 1, 1))
    T[:, :3, :3] = Rotation.from_quat(q, scalar_first=True).as_matrix()
    T[:, :3, 3] = t.detach().numpy()
    return T


def twist_matrix(xi: np.ndarray) -> np.ndarray:
    rho, w = xi[:3], xi[3:]
    X = np.zeros((4, 4))
    X[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
    X[:3, 3] = rho
    return X


def test_compose_invert_apply_relative_match_matrices(device):
    (q1, t1), (q2, t2) = random_pose(30, 0), random_pose(30, 1)
    x = torch.tensor(np.random.default_rng(2).normal(size=(30, 3)))
    T1, T2 = as_matrix(q1, t1), as_matrix(q2, t2)
    qc, tc = se3.compose(q1, t1, q2, t2)
    np.testing.assert_allclose(as_matrix(qc, tc), T1 @ T2, atol=1e-12)
    qi, ti = se3.invert(q1, t1)
    np.testing.assert_allclose(as_matrix(qi, ti), np.linalg.inv(T1), atol=1e-12)
    xh = np.concatenate([x.numpy(), np.ones((30, 1))], axis=1)
    np.testing.assert_allclose(se3.apply(q1, t1, x).numpy(), (T1 @ xh[..., None])[:, :3, 0], atol=1e-12)
    qr, tr = se3.relative(q1, t1, q2, t2)
    np.testing.assert_allclose(as_matrix(qr, tr), T1 @ np.linalg.inv(T2), atol=1e-12)
    np.testing.assert_allclose(se3.to_matrix(q1, t1).numpy(), T1, atol=1e-12)
    qb, tb = se3.from_matrix(torch.tensor(T1))
    np.testing.assert_allclose(as_matrix(qb, tb), T1, atol=1e-12)
    # device / dtype agnostic
    f32 = [x.to(device, torch.float32) for x in (q1, t1, q2, t2)]
    qd, td = se3.relative(*f32)
    assert qd.dtype == torch.float32
    assert qd.device.type == device.type
    np.testing.assert_allclose(
        as_matrix(qd.cpu().double(), td.cpu().double()), T1 @ np.linalg.inv(T2), atol=1e-4
    )


def test_relative_carries_attached_point():
    """A point rigidly attached to a node at t_ref stays attached at t."""
    (q_ref, p_ref), (q_t, p_t) = random_pose(10, 3), random_pose(10, 4)
    local = torch.tensor(np.random.default_rng(5).normal(size=(10, 3)))
    x_ref, x_t = se3.apply(q_ref, p_ref, local), se3.apply(q_t, p_t, local)
    qr, tr = se3.relative(q_t, p_t, q_ref, p_ref)
    np.testing.assert_allclose(se3.apply(qr, tr, x_ref).numpy(), x_t.numpy(), atol=1e-12)


@SETTINGS
@given(arrays(np.float64, 3, elements=st.floats(-5, 5)), arrays(np.float64, 3, elements=st.floats(-3.0, 3.0)))
def test_exp_matches_matrix_exponential_and_log_inverts(rho, w):
    xi = np.concatenate([rho, w])
    q, t = se3.exp(torch.tensor(xi))
    np.testing.assert_allclose(
        as_matrix(q[None], t[None])[0], scipy.linalg.expm(twist_matrix(xi)), atol=1e-10
    )
    if np.linalg.norm(w) < math.pi - 1e-3:
        np.testing.assert_allclose(se3.log(q, t).numpy(), xi, atol=1e-9)


@pytest.mark.parametrize("theta", [0.0, 1e-300, 1e-12, 1e-7, 1e-4, 0.05, 0.06, 0.4, 0.5, 3.0, math.pi - 1e-9])
def test_exp_log_round_trip_small_and_large_angles(theta):
    axis = np.array([0.48, 0.6, 0.64])
    xi = np.concatenate([[0.7, -1.2, 2.0], axis * theta])
    expm = scipy.linalg.expm(twist_matrix(xi))
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 3e-6)):
        q, t = se3.exp(torch.tensor(xi, dtype=dtype))
        np.testing.assert_allclose(as_matrix(q[None].double(), t[None].double())[0], expm, atol=tol)
        back = se3.log(q, t)
        q2, t2 = se3.exp(back)  # exp(log(T)) = T at every angle, pi included
        np.testing.assert_allclose(as_matrix(q2[None].double(), t2[None].double())[0], expm, atol=3 * tol)
        if theta <= 3.0 or dtype == torch.float64:  # float32 rounds pi - 1e-9 onto pi: either log is right
            np.testing.assert_allclose(back.double().numpy(), xi, atol=10 * tol)


def test_exp_log_gradients_finite_and_correct():
    for scale in (0.0, 1e-9, 1e-3, 0.05, 1.0):
        xi = torch.tensor(
            [[0.3, -0.2, 0.5, 0.1 * scale, -0.7 * scale, 0.2 * scale]], dtype=f64, requires_grad=True
        )
        assert torch.autograd.gradcheck(lambda x: torch.cat(se3.exp(x), -1), (xi,))
        q, t = se3.exp(xi.detach())
        q, t = q.requires_grad_(True), t.requires_grad_(True)
        assert torch.autograd.gradcheck(se3.log, (q, t))


def test_procrustes_recovers_known_rotation_from_noisy_points(device):
    rng = np.random.default_rng(7)
    R_true = Rotation.random(random_state=8)
    src = rng.normal(size=(200, 3)) * 2
    t_true = np.array([1.0, -2.0, 0.5])
    dst = R_true.apply(src) + t_true + rng.normal(size=src.shape) * 0.01
    w = rng.uniform(0.1, 1.0, size=200)
    fit = se3.procrustes(
        torch.tensor(src, device=device), torch.tensor(dst, device=device), torch.tensor(w, device=device)
    )
    assert int(fit.kind) == 0
    # independent oracle: scipy's weighted Wahba solver on the weight-centred points
    cs, cd = (w[:, None] * src).sum(0) / w.sum(), (w[:, None] * dst).sum(0) / w.sum()
    R_ref, _ = Rotation.align_vectors(dst - cd, src - cs, weights=w)
    np.testing.assert_allclose(fit.rotation.cpu().numpy(), R_ref.as_matrix(), atol=1e-10)
    np.testing.assert_allclose(fit.translation.cpu().numpy(), cd - R_ref.apply(cs), atol=1e-10)
    # and close to the truth given the noise
    assert (R_true.inv() * Rotation.from_matrix(fit.rotation.cpu().numpy())).magnitude() < 5e-3
    np.testing.assert_allclose(fit.translation.cpu().numpy(), t_true, atol=5e-3)
    # float32 on the same device agrees
    fit32 = se3.procrustes(
        torch.tensor(src, dtype=torch.float32, device=device),
        torch.tensor(dst, dtype=torch.float32, device=device),
    )
    np.testing.assert_allclose(fit32.rotation.cpu().numpy(), R_true.as_matrix(), atol=5e-3)


def test_procrustes_zero_weights_ignore_outliers_and_batch():
    rng = np.random.default_rng(9)
    Rs = Rotation.random(4, random_state=10)
    src = rng.normal(size=(4, 30, 3))
    dst = np.stack([Rs[i].apply(src[i]) for i in range(4)]) + 0.3
    dst[:, :5] += rng.normal(size=(4, 5, 3)) * 50  # outliers ...
    w = np.ones((4, 30))
    w[:, :5] = 0.0  # ... masked out
    fit = se3.procrustes(torch.tensor(src), torch.tensor(dst), torch.tensor(w))
    assert fit.rotation.shape == (4, 3, 3) and fit.translation.shape == (4, 3)
    np.testing.assert_allclose(fit.rotation.numpy(), Rs.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(fit.translation.numpy(), np.full((4, 3), 0.3), atol=1e-12)


def test_procrustes_never_returns_a_reflection():
    rng = np.random.default_rng(11)
    src = rng.normal(size=(50, 3))
    dst = src * np.array([1.0, 1.0, -1.0])  # a mirror image: best orthogonal map is a reflection
    fit = se3.procrustes(torch.tensor(src), torch.tensor(dst))
    R = fit.rotation.numpy()
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    # the best proper rotation (scipy's Wahba solver never reflects either)
    R_ref, _ = Rotation.align_vectors(dst - dst.mean(0), src - src.mean(0))
    cost = lambda M: np.sum((src @ M.T - dst + (dst.mean(0) - src.mean(0) @ M.T)) ** 2)  # noqa: E731
    assert cost(R) <= cost(R_ref.as_matrix()) + 1e-9


def test_procrustes_degenerate_inputs_are_finite():
    rng = np.random.default_rng(12)
    R_true = Rotation.from_rotvec([0.3, -1.0, 0.4])
    line = np.linspace(-1, 1, 9)[:, None] * np.array([[1.0, 2.0, -0.5]])
    cases = {
        "zero_weight": (rng.normal(size=(6, 3)), rng.normal(size=(6, 3)), np.zeros(6)),
        "coincident": (np.ones((6, 3)), np.ones((6, 3)) * 2, np.ones(6)),
        "dst_coincident": (rng.normal(size=(6, 3)), np.zeros((6, 3)), np.ones(6)),
        "single_point": (rng.normal(size=(1, 3)), rng.normal(size=(1, 3)), np.ones(1)),
        "collinear": (line, R_true.apply(line) + 1.0, np.ones(9)),
        "two_points": (line[[0, -1]], R_true.apply(line[[0, -1]]) + 1.0, np.ones(2)),
        "collinear_reversed": (line, -line, np.ones(9)),
    }
    for name, (src, dst, w) in cases.items():
        for dtype in (torch.float64, torch.float32):
            fit = se3.procrustes(
                torch.tensor(src, dtype=dtype), torch.tensor(dst, dtype=dtype), torch.tensor(w, dtype=dtype)
            )
            R = fit.rotation.double().numpy()
            assert np.isfinite(R).all() and np.isfinite(fit.translation.numpy()).all(), name
            np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-5, err_msg=name)
            np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-5, err_msg=name)
            if name in ("zero_weight", "coincident", "dst_coincident", "single_point"):
                assert int(fit.kind) == 2, name
                np.testing.assert_allclose(R, np.eye(3), atol=1e-6, err_msg=name)
            else:
                assert int(fit.kind) == 1, name
                # one of the equally good minimisers: maps every point exactly (noise-free) ...
                mapped = src @ R.T + fit.translation.double().numpy()
                np.testing.assert_allclose(mapped, dst, atol=1e-5, err_msg=name)
                # ... and the one nearest the identity: angle = angle between the line directions
                u = src[-1] - src[0]
                v = dst[-1] - dst[0]
                ang = math.acos(np.clip(u @ v / np.linalg.norm(u) / np.linalg.norm(v), -1, 1))
                np.testing.assert_allclose(Rotation.from_matrix(R).magnitude(), ang, atol=1e-3, err_msg=name)
    zero = se3.procrustes(
        torch.tensor(cases["zero_weight"][0]),
        torch.tensor(cases["zero_weight"][1]),
        torch.zeros(6, dtype=f64),
    )
    np.testing.assert_allclose(zero.translation.numpy(), 0.0)
    coinc = se3.procrustes(torch.ones(6, 3, dtype=f64), 2 * torch.ones(6, 3, dtype=f64))
    np.testing.assert_allclose(coinc.translation.numpy(), [1.0, 1.0, 1.0])


def test_procrustes_with_scale_recovers_similarity():
    rng = np.random.default_rng(13)
    R = Rotation.random(random_state=14)
    src = rng.normal(size=(40, 3))
    dst = 2.5 * R.apply(src) + np.array([0.1, 0.2, 0.3])
    fit = se3.procrustes(torch.tensor(src), torch.tensor(dst), with_scale=True)
    np.testing.assert_allclose(fit.scale.item(), 2.5, rtol=1e-12)
    np.testing.assert_allclose(fit.rotation.numpy(), R.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(fit.translation.numpy(), [0.1, 0.2, 0.3], atol=1e-12)
    assert not fit.rotation.requires_grad


def test_procrustes_rejects_wrong_shapes():
    with pytest.raises(ValueError, match="expected"):
        se3.procrustes(torch.zeros(5, 2), torch.zeros(5, 2))
