"""KNN, skinning weights and Gaussian deformation against brute-force numpy references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from worldtree.motion import dualquat, se3, skinning
from worldtree.motion import quaternion as Q

f64 = torch.float64


def quat_np(r: Rotation) -> np.ndarray:
    return r.as_quat(scalar_first=True)


def left_matrix(q: np.ndarray) -> np.ndarray:
    """[4, 4] matrix L(q) with L(q) p = q p (Hamilton), written out independently of the library."""
    w, x, y, z = q
    return np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])


def reference_deform(points, quats, pos_ref, rot_ref, pos_t, rot_t, sigma, idx, valid=None, corr=None):
    """Brute-force loop: 4x4 relative transforms, Gaussian kernels, DQB with numpy dual quaternions."""
    out_p, out_q = [], []
    for i in range(points.shape[0]):
        nb = idx[i]
        d2 = ((points[i] - pos_ref[nb]) ** 2).sum(-1)
        w = np.exp(-d2 / (2 * sigma[nb] ** 2)) + 1e-6
        if corr is not None:
            w = np.maximum(w + corr[i], 0.0)
        if valid is not None:
            w = np.where(valid[i], w, 0.0)
        dqs = []
        for k in nb:
            T_ref, T_t = np.eye(4), np.eye(4)
            T_ref[:3, :3], T_ref[:3, 3] = rot_ref[k].as_matrix(), pos_ref[k]
            T_t[:3, :3], T_t[:3, 3] = rot_t[k].as_matrix(), pos_t[k]
            T = T_t @ np.linalg.inv(T_ref)
            r = quat_np(Rotation.from_matrix(T[:3, :3]))
            d = 0.5 * left_matrix(np.concatenate([[0.0], T[:3, 3]])) @ r
            dqs.append(np.concatenate([r, d]))
        dqs = np.array(dqs)
        pivot = dqs[np.argmax(w)].copy()
        if pivot[0] < 0:
            pivot = -pivot
        dqs = np.where((dqs[:, :4] @ pivot[:4] < 0)[:, None], -dqs, dqs)
        W = w.sum()
        alpha = min(max(W, 0.0), 1.0)
        b = alpha * (w[:, None] / W * dqs).sum(0) + (1 - alpha) * np.array([1.0, 0, 0, 0, 0, 0, 0, 0])
        r, d = b[:4] / np.linalg.norm(b[:4]), b[4:] / np.linalg.norm(b[:4])
        rc = r * np.array([1, -1, -1, -1])
        t = 2 * (left_matrix(d) @ rc)[1:]
        R = Rotation.from_quat(r, scalar_first=True)
        out_p.append(R.apply(points[i]) + t)
        out_q.append(left_matrix(r) @ quats[i])
    return np.array(out_p), np.array(out_q)


def scene(n=40, m=12, seed=0, sigma_val=0.4):
    rng = np.random.default_rng(seed)
    pos_ref = rng.uniform(-1, 1, size=(m, 3))
    rot_ref = Rotation.random(m, random_state=seed + 1)
    pos_t = pos_ref + rng.normal(size=(m, 3)) * 0.3
    rot_t = Rotation.from_rotvec(rng.normal(size=(m, 3)) * 0.8) * rot_ref
    points = rng.uniform(-1.2, 1.2, size=(n, 3))
    quats = quat_np(Rotation.random(n, random_state=seed + 2)) * rng.uniform(0.5, 2, size=(n, 1))
    sigma = np.full(m, sigma_val) * rng.uniform(0.5, 1.5, size=m)
    return points, quats, pos_ref, rot_ref, pos_t, rot_t, sigma


def as_torch(points, quats, pos_ref, rot_ref, pos_t, rot_t, sigma, device="cpu", dtype=f64):
    def tt(a):
        return torch.tensor(a, device=device, dtype=dtype)

    return (
        tt(points),
        tt(quats),
        tt(pos_ref),
        tt(quat_np(rot_ref)),
        tt(pos_t),
        tt(quat_np(rot_t)),
        tt(sigma),
    )


def test_knn_matches_brute_force_with_chunks(device):
    rng = np.random.default_rng(0)
    query = rng.normal(size=(2, 250, 3))
    ref = rng.normal(size=(37, 3))
    d2 = ((query[..., None, :] - ref) ** 2).sum(-1)
    expected = np.argsort(d2, axis=-1)[..., :5]
    for dtype in (torch.float64, torch.float32):
        idx, dist2 = skinning.knn(
            torch.tensor(query, dtype=dtype, device=device),
            torch.tensor(ref, dtype=dtype, device=device),
            5,
            chunk_size=64,
        )
        assert idx.shape == (2, 250, 5) and idx.dtype == torch.long
        np.testing.assert_array_equal(idx.cpu().numpy(), expected)
        np.testing.assert_allclose(
            dist2.double().cpu().numpy(), np.take_along_axis(d2, expected, -1), rtol=1e-5
        )


def test_knn_k_larger_than_nodes_and_no_nodes():
    q = torch.randn(10, 3)
    idx, d2 = skinning.knn(q, torch.randn(3, 3), 16)
    assert idx.shape == (10, 3)
    assert sorted(idx[0].tolist()) == [0, 1, 2]
    idx, d2 = skinning.knn(q, torch.zeros(0, 3), 16)
    assert idx.shape == (10, 0) and d2.shape == (10, 0)
    with pytest.raises(ValueError, match="knn"):
        skinning.knn(q, torch.randn(3, 2), 2)


def test_skinning_weights_formula_mask_and_correction():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(6, 3))
    nb = rng.normal(size=(6, 4, 3))
    sig = rng.uniform(0.3, 2.0, size=(6, 4))
    corr = rng.normal(size=(6, 4)) * 0.1
    valid = rng.random((6, 4)) > 0.3
    corr[0, :] = -5.0  # a correction can never make a weight negative
    expected = np.maximum(np.exp(-((pts[:, None] - nb) ** 2).sum(-1) / (2 * sig**2)) + 1e-6 + corr, 0.0)
    expected = np.where(valid, expected, 0.0)
    got = skinning.skinning_weights(
        *(torch.tensor(a) for a in (pts, nb, sig)), torch.tensor(valid), torch.tensor(corr)
    )
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-13)
    norm, total = skinning.normalize_weights(got)
    np.testing.assert_allclose(total.numpy(), expected.sum(-1), rtol=1e-13)
    np.testing.assert_allclose(total[0].item(), 0.0)
    np.testing.assert_allclose(norm[0].numpy(), 0.0)  # no weight left: zeros, not NaN
    np.testing.assert_allclose(norm[1:].sum(-1).numpy(), 1.0, rtol=1e-13)
    zero_norm, zero_total = skinning.normalize_weights(torch.zeros(2, 3))
    assert torch.all(zero_norm == 0) and torch.all(zero_total == 0)


@pytest.mark.parametrize("sigma_val", [0.15, 0.5, 3.0])
def test_deform_matches_brute_force_reference(sigma_val):
    pts, quats, pos_ref, rot_ref, pos_t, rot_t, sigma = scene(sigma_val=sigma_val)
    idx, _ = skinning.knn(torch.tensor(pts), torch.tensor(pos_ref), 6)
    valid = np.random.default_rng(3).random((pts.shape[0], 6)) > 0.2
    corr = np.random.default_rng(4).uniform(0, 0.05, size=(pts.shape[0], 6))
    ref_p, ref_q = reference_deform(
        pts, quats, pos_ref, rot_ref, pos_t, rot_t, sigma, idx.numpy(), valid, corr
    )
    got_p, got_q = skinning.deform(
        *as_torch(pts, quats, pos_ref, rot_ref, pos_t, rot_t, sigma),
        idx,
        torch.tensor(valid),
        torch.tensor(corr),
    )
    np.testing.assert_allclose(got_p.numpy(), ref_p, atol=1e-11)
    np.testing.assert_allclose(got_q.numpy(), ref_q, atol=1e-11)


def test_deform_shared_rigid_motion_is_exact(device):
    """All nodes moved by one rigid G: every Gaussian near them (W >= 1) is moved by exactly G."""
    pts, quats, pos_ref, rot_ref, _, _, sigma = scene(sigma_val=50.0)  # huge radius: every raw weight ~ 1
    G = Rotation.from_rotvec([0.3, -2.9, 0.8])
    g_t = np.array([0.5, -1.0, 2.0])
    pos_t, rot_t = G.apply(pos_ref) + g_t, G * rot_ref
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 2e-5)):
        args = as_torch(pts, quats, pos_ref, rot_ref, pos_t, rot_t, sigma, device, dtype)
        idx, _ = skinning.knn(args[0], args[2], 8)
        p, q = skinning.deform(*args, idx)
        assert p.device.type == device.type and p.dtype == dtype
        np.testing.assert_allclose(p.double().cpu().numpy(), G.apply(pts) + g_t, atol=tol * 10)
        expected_q = np.stack([left_matrix(quat_np(G)) @ qq for qq in quats])
        np.testing.assert_allclose(
            Q.to_matrix(q).double().cpu().numpy(),
            Q.to_matrix(torch.tensor(expected_q)).numpy(),
            atol=tol * 10,
        )
        np.testing.assert_allclose(
            q.norm(dim=-1).double().cpu().numpy(), np.linalg.norm(quats, axis=-1), rtol=tol
        )


def test_deform_static_nodes_leave_gaussians_unchanged():
    pts, quats, pos_ref, rot_ref, _, _, sigma = scene()
    args = as_torch(pts, quats, pos_ref, rot_ref, pos_ref, rot_ref, sigma)
    idx, _ = skinning.knn(args[0], args[2], 5)
    p, q = skinning.deform(*args, idx)
    np.testing.assert_allclose(p.numpy(), pts, atol=1e-14)
    np.testing.assert_allclose(q.numpy(), quats, atol=1e-14)


def test_far_points_stay_put_and_fully_masked_points_do_not_move():
    pts, quats, pos_ref, rot_ref, pos_t, rot_t, sigma = scene(sigma_val=0.07)
    far = pts + 100.0  # exp(-d^2 / 2 sigma^2) underflows: raw weights are the 1e-6 floor only
    args = list(as_torch(far, quats, pos_ref, rot_ref, pos_t, rot_t, sigma))
    idx, _ = skinning.knn(args[0], args[2], 16)
    p, _ = skinning.deform(*args, idx)
    # W = 12e-6: the identity keeps 1 - W of the blend, so motion of O(1) scene units shrinks to ~1e-4
    assert (p - args[0]).norm(dim=-1).max() < 2e-3
    valid = torch.zeros(idx.shape, dtype=torch.bool)
    p, q = skinning.deform(*args, idx, valid=valid)
    assert torch.equal(p, args[0]) and torch.equal(q, args[1])


def test_deform_with_no_nodes_returns_inputs():
    pts = torch.randn(5, 3, dtype=f64)
    quats = Q.normalize(torch.randn(5, 4, dtype=f64))
    empty = torch.zeros(0, 3, dtype=f64)
    idx, _ = skinning.knn(pts, empty, 16)
    e4 = torch.zeros(0, 4, dtype=f64)
    p, q = skinning.deform(pts, quats, empty, e4, empty, e4, torch.zeros(0, dtype=f64), idx)
    assert torch.equal(p, pts) and torch.equal(q, quats)


def test_deform_is_invariant_to_node_quaternion_signs():
    pts, quats, pos_ref, rot_ref, pos_t, rot_t, sigma = scene(seed=5)
    args = list(as_torch(pts, quats, pos_ref, rot_ref, pos_t, rot_t, sigma))
    idx, _ = skinning.knn(args[0], args[2], 6)
    p0, q0 = skinning.deform(*args, idx)
    rng = np.random.default_rng(6)
    args[3] = args[3] * torch.tensor(rng.choice([-1.0, 1.0], size=(12, 1)))
    args[5] = args[5] * torch.tensor(rng.choice([-1.0, 1.0], size=(12, 1)))
    p1, q1 = skinning.deform(*args, idx)
    np.testing.assert_allclose(p1.numpy(), p0.numpy(), atol=1e-13)
    np.testing.assert_allclose(Q.to_matrix(q1).numpy(), Q.to_matrix(q0).numpy(), atol=1e-13)


def test_per_gaussian_reference_frames():
    """Nodes follow rigid motions G_f per frame; a Gaussian made at frame f_i moves by G_s G_f^-1 to frame s."""
    rng = np.random.default_rng(7)
    m, n, frames = 10, 30, 4
    base = rng.uniform(-1, 1, size=(m, 3))
    base_rot = Rotation.random(m, random_state=8)
    Gs = [Rotation.from_rotvec(rng.normal(size=3)) for _ in range(frames)]
    gt = rng.normal(size=(frames, 3))
    traj_p = torch.tensor(np.stack([Gs[f].apply(base) + gt[f] for f in range(frames)]))
    traj_q = torch.tensor(np.stack([quat_np(Gs[f] * base_rot) for f in range(frames)]))
    ref_frame = torch.tensor(rng.integers(0, frames, size=n))
    local = rng.uniform(-1, 1, size=(n, 3))
    pts = np.stack([Gs[f].apply(local[i]) + gt[f] for i, f in enumerate(ref_frame.tolist())])
    pts_t = torch.tensor(pts)
    sigma = torch.full((m,), 30.0, dtype=f64)  # all weights ~1: W >= 1
    # neighbours found at each Gaussian's own reference frame
    idx = torch.stack([skinning.knn(pts_t[i], traj_p[f], 4)[0] for i, f in enumerate(ref_frame.tolist())])
    target = 2
    nb_p_ref = skinning.gather_frames(traj_p, ref_frame, idx)
    nb_q_ref = skinning.gather_frames(traj_q, ref_frame, idx)
    nb_p_t = skinning.gather_frames(traj_p, torch.full_like(ref_frame, target), idx)
    nb_q_t = skinning.gather_frames(traj_q, torch.full_like(ref_frame, target), idx)
    q_rel, t_rel = se3.relative(nb_q_t, nb_p_t, nb_q_ref, nb_p_ref)
    quats = Q.identity((n,), f64)
    p, _ = skinning.deform_neighbours(pts_t, quats, nb_p_ref, sigma[idx], q_rel, t_rel)
    np.testing.assert_allclose(p.numpy(), Gs[target].apply(local) + gt[target], atol=1e-11)


def _deform_flat(points, quats, pr, qr, pt, qt, sigma, corr, idx):
    p, q = skinning.deform(points, quats, pr, qr, pt, qt, sigma, idx, correction=corr)
    return torch.cat((p, q), -1)


@pytest.mark.parametrize("sigma_val", [0.3, 5.0])  # W < 1 (identity mix active) and W > 1
def test_deform_gradcheck(sigma_val):
    pts, quats, pos_ref, rot_ref, pos_t, rot_t, sigma = scene(n=3, m=5, seed=9, sigma_val=sigma_val)
    args = [a.requires_grad_(True) for a in as_torch(pts, quats, pos_ref, rot_ref, pos_t, rot_t, sigma)]
    idx, _ = skinning.knn(args[0].detach(), args[2].detach(), 3)
    corr = torch.full((3, 3), 0.01, dtype=f64, requires_grad=True)
    w = skinning.skinning_weights(args[0], args[2][idx], args[6][idx], correction=corr).sum(-1)
    assert torch.all((w - 1).abs() > 0.05)  # away from the kink of clamp(W, 0, 1)
    assert torch.autograd.gradcheck(_deform_flat, (*args, corr, idx))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_deform_gradients_finite_at_edges(dtype):
    pts, quats, pos_ref, rot_ref, pos_t, rot_t, sigma = scene(n=8, m=6, seed=10)
    pts[0] = pos_ref[0]  # exactly on a node
    pts[1] += 1e3  # far: kernels underflow
    rot_t = Rotation.from_rotvec(np.tile([0, 0, math.pi], (6, 1))) * rot_ref  # 180-degree node turns
    sigma[1] = 0.0  # zero radius
    args = [
        a.requires_grad_(True)
        for a in as_torch(pts, quats, pos_ref, rot_ref, pos_t, rot_t, sigma, dtype=dtype)
    ]
    idx, _ = skinning.knn(args[0].detach(), args[2].detach(), 4)
    valid = torch.ones(idx.shape, dtype=torch.bool)
    valid[2] = False  # fully masked
    corr = torch.zeros(idx.shape, dtype=dtype, requires_grad=True)
    p, q = skinning.deform(*args, idx, valid=valid, correction=corr)
    assert torch.isfinite(p).all() and torch.isfinite(q).all()
    (p.square().sum() + q.sum()).backward()
    for a in (*args, corr):
        assert a.grad is not None and torch.isfinite(a.grad).all()


def test_gather_frames_equals_indexing_values_and_gradient():
    # One index_select over the flattened table: same values as traj[frame, idx] and the same gradient
    # (repeated (frame, node) entries accumulate), checked against a loop over items.
    g = torch.Generator().manual_seed(5)
    T, M, N, K = 4, 6, 9, 3
    traj = torch.randn(T, M, 4, generator=g, dtype=f64, requires_grad=True)
    frame = torch.randint(0, T, (N,), generator=g)
    idx = torch.randint(0, M, (N, K), generator=g)
    idx[1] = idx[0]
    frame[1] = frame[0]  # a repeated row: its gradient must add up
    out = skinning.gather_frames(traj, frame, idx)
    loop = torch.stack([torch.stack([traj[frame[n], idx[n, k]] for k in range(K)]) for n in range(N)])
    assert torch.equal(out, loop)
    w = torch.randn(N, K, 4, generator=g, dtype=f64)
    (grad,) = torch.autograd.grad((out * w).sum(), traj)
    want = torch.zeros(T, M, 4, dtype=f64)
    for n in range(N):
        for k in range(K):
            want[frame[n], idx[n, k]] += w[n, k]
    torch.testing.assert_close(grad, want, rtol=0, atol=1e-14)


@pytest.mark.parametrize("mix_identity", [True, False])
def test_component_major_deform_equals_the_gathered_layout(mix_identity):
    # deform_dual_planes (inputs [C, N, K]) against deform_dual_neighbours (inputs [N, K, C]) on the same
    # transforms: values and every gradient. Includes masked neighbours, a negative weight correction (clamped
    # to 0), transforms of both signs (the alignment) and a row with no valid neighbour (without the identity
    # mix its blend is degenerate and falls back to the pivot).
    g = torch.Generator().manual_seed(21)
    N, K = 12, 5
    pts = torch.randn(N, 3, generator=g, dtype=f64)
    quats = torch.randn(N, 4, generator=g, dtype=f64)
    nb_pos = pts[:, None] + 0.5 * torch.randn(N, K, 3, generator=g, dtype=f64)
    sigma = 0.3 + torch.rand(N, K, generator=g, dtype=f64)
    q_rel = torch.randn(N, K, 4, generator=g, dtype=f64)
    t_rel = torch.randn(N, K, 3, generator=g, dtype=f64)
    real, dual = dualquat.from_quat_trans(q_rel, t_rel)
    flip = torch.rand(N, K, 1, generator=g) < 0.5
    real, dual = torch.where(flip, -real, real), torch.where(flip, -dual, dual)
    valid = torch.rand(N, K, generator=g) > 0.2
    valid[3] = False
    corr = 0.3 * torch.randn(N, K, generator=g, dtype=f64)
    corr[5, 0] = -5.0
    leaves = [pts, quats, nb_pos, sigma, real, dual, corr]
    wp, wq = torch.randn(N, 3, generator=g, dtype=f64), torch.randn(N, 4, generator=g, dtype=f64)
    results = []
    for planes in (True, False):
        xs = [x.clone().requires_grad_(True) for x in leaves]
        p, q, npos, sig, re, du, co = xs
        if planes:
            args = (npos.permute(2, 0, 1), sig, re.permute(2, 0, 1), du.permute(2, 0, 1))
            out = skinning.deform_dual_planes(p, q, *args, valid, co, mix_identity)
        else:
            out = skinning.deform_dual_neighbours(p, q, npos, sig, re, du, valid, co, mix_identity)
        grads = torch.autograd.grad((out[0] * wp).sum() + (out[1] * wq).sum(), xs)
        results.append([out[0].detach(), out[1].detach(), *grads])
    for a, b in zip(*results, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-13)
    assert torch.isfinite(results[0][0]).all() and results[1][2].abs().sum() > 0


def test_gather_planes_is_gather_frames_component_major():
    g = torch.Generator().manual_seed(4)
    traj = torch.randn(5, 7, 4, generator=g, dtype=f64)
    frame = torch.randint(0, 5, (6,), generator=g)
    idx = torch.randint(0, 7, (6, 3), generator=g)
    assert torch.equal(skinning.gather_planes(traj, frame, idx), traj[frame[:, None], idx].permute(2, 0, 1))


# ----------------------------------------------------------------------------- compiled DQB kernel (CPU, float32)
def _compiled_kernel():
    from worldtree.render import cpu_kernel

    if not cpu_kernel.available():
        pytest.skip(f"the compiled kernel does not build here: {cpu_kernel.build_error()}")
    return cpu_kernel


def _planes_case(N: int, K: int, seed: int) -> tuple[list[torch.Tensor], torch.Tensor]:
    """Inputs of deform_dual_planes, float64 values that float32 holds exactly (both paths see the same numbers):
    ``[points, quats, nb_pos, sigma, real, dual, correction]`` and ``valid``. Random rows plus the guarded cases:
    transforms of both signs (row 0: every neighbour the antipode of the one before), a row with no valid
    neighbour (1), corrections clamping some weights (2) or every weight (3) to 0, sigma 0 (4: ties of 1e-6 but
    one neighbour on the point), a node on the point (5)."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(N, 3, generator=g, dtype=f64)
    quats = torch.randn(N, 4, generator=g, dtype=f64)
    nb_pos = pts[:, None] + 0.5 * torch.randn(N, K, 3, generator=g, dtype=f64)
    sigma = 0.3 + torch.rand(N, K, generator=g, dtype=f64)
    real, dual = dualquat.from_quat_trans(
        torch.randn(N, K, 4, generator=g, dtype=f64), torch.randn(N, K, 3, generator=g, dtype=f64)
    )
    flip = torch.rand(N, K, 1, generator=g) < 0.5
    real, dual = torch.where(flip, -real, real), torch.where(flip, -dual, dual)
    real[0, 1::2], dual[0, 1::2] = -real[0, 0::2][: K // 2], -dual[0, 0::2][: K // 2]
    valid = torch.rand(N, K, generator=g) > 0.25
    valid[1] = False
    corr = 0.3 * torch.randn(N, K, generator=g, dtype=f64)
    corr[2, : K // 2] = -5.0
    corr[3] = -5.0
    sigma[4] = 0.0
    nb_pos[4, K - 1] = pts[4]
    nb_pos[5, 0] = pts[5]
    xs = [pts, quats, nb_pos.permute(2, 0, 1), sigma, real.permute(2, 0, 1), dual.permute(2, 0, 1), corr]
    return [x.float().double().contiguous() for x in xs], valid


def _planes_values(fn, xs, valid, dtype, mix_identity=True, use_valid=True, use_corr=True, seed=1):
    """(points_t, quats_t, gradients of a random linear loss w.r.t. every input) of ``fn`` in ``dtype``."""
    leaves = [x.to(dtype).detach().clone().requires_grad_(True) for x in (xs if use_corr else xs[:6])]
    corr = leaves[6] if use_corr else None
    p_t, q_t = fn(*leaves[:6], valid if use_valid else None, corr, mix_identity)
    g = torch.Generator().manual_seed(seed)
    wp = torch.randn(p_t.shape, generator=g, dtype=f64).to(dtype)
    wq = torch.randn(q_t.shape, generator=g, dtype=f64).to(dtype)
    grads = torch.autograd.grad((p_t * wp).sum() + (q_t * wq).sum(), leaves)
    return [p_t.detach(), q_t.detach(), *grads]


def _assert_close_f32(got, want):
    # float32 rounding with margin: the kernel rounds its inputs' products and sums in double and its outputs
    # once (about 1e-7 relative); 1e-5 of each tensor's largest value leaves room for the float32 weights.
    for a, b in zip(got, want, strict=True):
        assert a.dtype == torch.float32 and torch.isfinite(a).all()
        scale = max(1.0, float(b.abs().max()))
        torch.testing.assert_close(a.double(), b, rtol=1e-4, atol=1e-5 * scale)


@pytest.mark.parametrize("K", [8, 16, 5])  # 8 and 16: the kernel's fixed-length loops; 5: any K
@pytest.mark.parametrize("mix_identity", [True, False])
@pytest.mark.parametrize("masks", [(True, True), (False, False), (True, False)])
def test_compiled_deform_matches_the_float64_tensor_version(K, mix_identity, masks):
    _compiled_kernel()
    xs, valid = _planes_case(37, K, seed=K)  # 37: a partial block of Gaussians at the end
    use_valid, use_corr = masks
    assert skinning._compiled_ops(*(x.float() for x in xs[:6]), valid, xs[6].float()) is not None
    got = _planes_values(skinning.deform_dual_planes, xs, valid, torch.float32, mix_identity, *masks)
    want = _planes_values(skinning._deform_dual_planes_tensor, xs, valid, f64, mix_identity, *masks)
    _assert_close_f32(got, want)
    assert all(torch.isfinite(w).all() for w in want)
    if not mix_identity:
        # Row 1 (no valid neighbour) and row 3 (every weight clamped to 0): all weights 0, a degenerate blend,
        # so the pivot's transform (the first neighbour, taken with w >= 0).
        for n in [1] * use_valid + [3] * use_corr:
            q_piv = xs[4][:, n, 0]
            q_piv = q_piv if q_piv[0] >= 0 else -q_piv
            torch.testing.assert_close(got[1][n].double(), Q.multiply(q_piv, xs[1][n]), rtol=1e-5, atol=1e-6)
    assert want[2].abs().sum() > 0 and want[5].abs().sum() > 0  # the weights' gradients were compared too


def test_compiled_deform_gives_the_same_bits_for_any_thread_count():
    _compiled_kernel()
    before = torch.get_num_threads()
    try:
        for K in (8, 6):
            xs, valid = _planes_case(53, K, seed=3)
            runs = []
            for n in (1, 2, 3):
                torch.set_num_threads(n)
                runs.append(_planes_values(skinning.deform_dual_planes, xs, valid, torch.float32))
            for other in runs[1:]:
                for a, b in zip(runs[0], other, strict=True):
                    assert torch.equal(a, b)
    finally:
        torch.set_num_threads(before)


def test_deform_planes_uses_the_tensor_version_for_float64_and_without_the_kernel(monkeypatch):
    from worldtree.render import cpu_kernel

    xs, valid = _planes_case(20, 8, seed=4)
    assert skinning._compiled_ops(*xs[:6], valid, xs[6]) is None  # float64: the tensor version
    got = _planes_values(skinning.deform_dual_planes, xs, valid, f64)
    want = _planes_values(skinning._deform_dual_planes_tensor, xs, valid, f64)
    for a, b in zip(got, want, strict=True):
        assert torch.equal(a, b)
    monkeypatch.setattr(cpu_kernel, "ops", lambda: None)
    assert skinning._compiled_ops(*(x.float() for x in xs[:6]), valid, xs[6].float()) is None
    got = _planes_values(skinning.deform_dual_planes, xs, valid, torch.float32)
    want = _planes_values(skinning._deform_dual_planes_tensor, xs, valid, torch.float32)
    for a, b in zip(got, want, strict=True):
        assert torch.equal(a, b)
    # No neighbour at all: both paths leave it to the tensor version (which has no pivot to take and raises).
    empty = [torch.zeros(3, 4, 0), torch.zeros(4, 0), torch.zeros(4, 4, 0), torch.zeros(4, 4, 0)]
    assert skinning._compiled_ops(torch.zeros(4, 3), torch.zeros(4, 4), *empty, None, None) is None


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("which", [0, 2, 3, 4, 5, 6])  # points, nb_pos, sigma, real, dual, correction
def test_deform_planes_shows_a_nan_input_in_its_outputs(compiled, which, monkeypatch):
    # A NaN must reach the outputs (and so the loss and the trainers' finiteness checks), not vanish behind the
    # normalisation's guard (|b_real| > eps is false for a NaN) as an identity transform.
    from worldtree.render import cpu_kernel

    if compiled:
        _compiled_kernel()
    else:
        monkeypatch.setattr(cpu_kernel, "ops", lambda: None)
    xs, valid = _planes_case(20, 8, seed=6)
    xs = [x.float() for x in xs]
    valid[9] = True
    n = 9  # a Gaussian with every neighbour valid
    if which == 0:
        xs[0][n, 1] = float("nan")
    elif which in (2, 4, 5):
        xs[which][1, n, 3] = float("nan")
    else:
        xs[which][n, 3] = float("nan")
    p_t, q_t = skinning.deform_dual_planes(*xs[:6], valid, xs[6])
    assert bool(torch.isnan(p_t[n]).any())
    others = torch.arange(20) != n
    assert torch.isfinite(p_t[others]).all() and torch.isfinite(q_t[others]).all()


def test_compiled_scaffold_deform_equals_the_tensor_version(monkeypatch):
    # MotionScaffold.deform to one frame takes deform_dual_planes with gathered node tables (relative_dual); the
    # compiled and the tensor path give the same points, rotations and gradients (node poses, radii, Gaussians, correction).
    from worldtree.motion.scaffold import ScaffoldConfig, build_scaffold

    _compiled_kernel()
    T, P = 6, 90
    g = torch.Generator().manual_seed(7)
    traj = torch.cumsum(0.01 * torch.randn(T, P, 3, generator=g), 0) + 0.1 * torch.randn(1, P, 3, generator=g)
    scf = build_scaffold(traj, torch.ones(T, P, dtype=torch.bool), 1.0, ScaffoldConfig(node_spacing_units=1.0))
    scf = scf.float()
    N = 400
    t_ref = torch.randint(0, T, (N,), generator=g)
    pts = traj[t_ref, torch.randint(0, P, (N,), generator=g)] + 0.01 * torch.randn(N, 3, generator=g)
    rot = torch.randn(N, 4, generator=g)
    cache = scf.attach(pts, t_ref)
    corr = 0.05 * torch.randn(cache.idx.shape, generator=g)
    assert scf.T * scf.M < cache.idx.numel()  # the one-frame table path (deform_dual_planes)

    def run():
        scf.zero_grad()
        leaves = [x.detach().clone().requires_grad_(True) for x in (pts, rot, corr)]
        p_t, q_t = scf.deform(leaves[0], leaves[1], t_ref, 4, cache, leaves[2])
        gw = torch.Generator().manual_seed(8)
        wp, wq = torch.randn(p_t.shape, generator=gw), torch.randn(q_t.shape, generator=gw)
        ((p_t * wp).sum() + (q_t * wq).sum()).backward()
        nodes = (scf.pos.grad, scf.quat.grad, scf.sigma_logit.grad)
        return [p_t.detach(), q_t.detach(), *(x.grad for x in leaves), *nodes]

    got = run()
    monkeypatch.setattr(skinning, "_compiled_ops", lambda *args: None)
    monkeypatch.setattr(skinning, "_relative_ops", lambda *args: None)  # the node-motion table too
    want = run()
    for a, b in zip(got, want, strict=True):
        assert torch.isfinite(a).all()
        scale = max(1.0, float(b.abs().max()))
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * scale)
    assert want[5].abs().sum() > 0 and want[7].abs().sum() > 0  # node positions and radii were compared too
