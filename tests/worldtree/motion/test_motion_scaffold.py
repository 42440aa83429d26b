"""Motion scaffold: construction, curve-distance graph, rotations, deformation, slicing, densify/resample."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from worldtree.motion import quaternion as Q
from worldtree.motion.regularizers import motion_losses
from worldtree.motion.scaffold import (
    Scaffold,
    ScaffoldConfig,
    build_scaffold,
    curve_distance,
    densify,
    greedy_select,
    resample_nodes,
    subsample_frames,
)

f64 = torch.float64
SCALE = 1.0  # scene scale: one unit = 0.01


def rigid_scene(T: int, N: int, seed: int, device="cpu"):
    """Points in a 12-unit cube moved by one random rigid transform per frame: (traj [T,N,3], R [T,3,3])."""
    g = torch.Generator().manual_seed(seed)
    x0 = (torch.rand(N, 3, generator=g, dtype=f64) - 0.5) * 0.12
    R = torch.tensor(Rotation.random(T, random_state=seed).as_matrix())
    trans = torch.randn(T, 3, generator=g, dtype=f64) * 0.2
    traj = torch.einsum("tij,nj->tni", R, x0) + trans[:, None]
    return traj.to(device), R.to(device)


def brute_curve_distance(a, b, oa, ob, k):
    """Per-pair loop: k_eff-th largest distance over the co-observed frames (numpy)."""
    T = a.shape[0]
    out = np.full((a.shape[1], b.shape[1]), np.inf)
    for i in range(a.shape[1]):
        for j in range(b.shape[1]):
            co = oa[:, i] & ob[:, j]
            n = int(co.sum())
            if n == 0:
                continue
            d = np.sort(np.linalg.norm(a[co, i] - b[co, j], axis=-1))[::-1]
            k_eff = max(1, min(math.ceil(k * n / T), k, n))
            out[i, j] = d[k_eff - 1]
    return out


@pytest.mark.parametrize("mode", ["reference", "accumulated"])
def test_rigid_motion_rotations_and_deformation(device, mode):
    T, N = 8, 120
    traj, R = rigid_scene(T, N, seed=3, device=device)
    obs = torch.ones(T, N, dtype=torch.bool, device=device)
    cfg = ScaffoldConfig(rotation_mode=mode, node_spacing_units=2.0)
    scf = build_scaffold(traj, obs, SCALE, cfg)
    assert 10 < scf.M < N and scf.pos.device.type == torch.device(device).type
    q_true = Q.from_matrix(R)
    for a in range(T):
        for b in (0, T - 1):
            rel_s = Q.multiply(scf.quat[a].detach(), Q.conjugate(scf.quat[b].detach()))
            rel_t = Q.multiply(q_true[a], Q.conjugate(q_true[b])).expand_as(rel_s)
            assert math.degrees(float(Q.angle_between(rel_s, rel_t).max())) < 1.0
    # Gaussians = the track points, each with its own reference frame, moved to per-Gaussian targets.
    g = torch.Generator().manual_seed(0)
    t_ref = torch.randint(0, T, (N,), generator=g).to(device)
    t_dst = torch.randint(0, T, (N,), generator=g).to(device)
    pts = traj[t_ref, torch.arange(N, device=device)]
    rot = Q.normalize(torch.randn(N, 4, generator=g, dtype=f64)).to(device)
    p_t, q_t = scf.deform(pts, rot, t_ref, t_dst)
    expect = traj[t_dst, torch.arange(N, device=device)]
    assert float((p_t - expect).detach().norm(dim=-1).max()) < 1e-6
    rel = torch.einsum("nij,nkj->nik", R[t_dst], R[t_ref])  # R(t) R(t_ref)^T
    q_expect = Q.multiply(Q.from_matrix(rel), rot)
    assert math.degrees(float(Q.angle_between(q_t, q_expect).detach().max())) < 1e-3
    # A scalar target frame and a precomputed cache give the same answer.
    cache = scf.attach(pts, t_ref)
    p5, q5 = scf.deform(pts, rot, t_ref, 5, cache)
    # Deforming to the reference frame itself is the identity.
    p_same, q_same = scf.deform(pts, rot, t_ref, t_ref, cache)
    assert torch.allclose(p_same, pts, atol=1e-12) and torch.allclose(q_same, rot, atol=1e-12)
    # The scalar-target path (per-node table) and the per-Gaussian path agree.
    p5b, q5b = scf.deform(pts, rot, t_ref, torch.full((N,), 5, device=device), cache)
    assert torch.allclose(p5, p5b, atol=1e-12) and torch.allclose(q5, q5b, atol=1e-12)
    assert float((p5 - traj[5]).detach().norm(dim=-1).max()) < 1e-6


def test_rotations_are_continuous_in_time():
    traj, _ = rigid_scene(10, 60, seed=5)
    scf = build_scaffold(traj, torch.ones(10, 60, dtype=torch.bool), SCALE)
    dots = (scf.quat[1:] * scf.quat[:-1]).sum(-1)
    assert bool((dots >= 0).all())


def test_curve_distance_matches_brute_force_and_closed_forms():
    g = torch.Generator().manual_seed(7)
    T, P, Qn = 9, 6, 7
    a = torch.randn(T, P, 3, generator=g, dtype=f64)
    b = torch.randn(T, Qn, 3, generator=g, dtype=f64)
    oa = torch.rand(T, P, generator=g) < 0.6
    ob = torch.rand(T, Qn, generator=g) < 0.6
    oa[:, 0] = False  # never observed: inf everywhere
    D = curve_distance(a, b, oa, ob, top_k=3)
    ref = brute_curve_distance(a.numpy(), b.numpy(), oa.numpy(), ob.numpy(), 3)
    np.testing.assert_allclose(D.numpy(), ref, atol=1e-12)
    assert np.isinf(ref[0]).all()
    assert torch.equal(curve_distance(a, b, oa, ob, top_k=3, max_chunk=10), D)  # one row per block
    # More frames than max_frames: the brute force on the same evenly spaced frames.
    fr = subsample_frames(T, 4)
    ref4 = brute_curve_distance(a[fr].numpy(), b[fr].numpy(), oa[fr].numpy(), ob[fr].numpy(), 3)
    np.testing.assert_allclose(curve_distance(a, b, oa, ob, top_k=3, max_frames=4).numpy(), ref4, atol=1e-12)
    # Two parallel curves: the distance is the offset; two outlier frames are ignored with k = 3.
    base = torch.randn(T, 1, 3, generator=g, dtype=f64)
    other = base + torch.tensor([0.3, 0.0, 0.4], dtype=f64)
    other[2, 0, 0] += 10.0
    other[5, 0, 1] -= 7.0
    assert torch.isclose(curve_distance(base, other, top_k=3)[0, 0], torch.tensor(0.5, dtype=f64))
    assert curve_distance(base, other, top_k=1)[0, 0] > 7.0  # k = 1 is the plain maximum
    # Frame subsampling: at most 100 evenly spaced frames, ends included.
    fr = subsample_frames(250, 100)
    assert fr.numel() <= 100 and fr[0] == 0 and fr[-1] == 249 and bool((fr[1:] > fr[:-1]).all())


def short_tracks(T: int, N: int, span: int, seed: int):
    """Curves observed on one short run of frames each (as dynamic tracks): (traj [T,N,3], obs [T,N])."""
    g = torch.Generator().manual_seed(seed)
    traj = torch.cumsum(torch.randn(T, N, 3, generator=g, dtype=f64) * 0.01, dim=0)
    start = torch.randint(0, T - span + 1, (N,), generator=g)
    t = torch.arange(T)[:, None]
    return traj, (t >= start) & (t < start + span)


def test_curve_distance_of_short_tracks_skips_only_pairs_that_share_no_frame():
    # Spans of 3 of 30 frames: most pairs share no frame, so the pairwise path (not every row x column)
    # computes the block; the brute force still decides every pair.
    traj, obs = short_tracks(30, 40, 3, seed=5)
    D = curve_distance(traj, traj, obs, obs, top_k=3)
    ref = brute_curve_distance(traj.numpy(), traj.numpy(), obs.numpy(), obs.numpy(), 3)
    np.testing.assert_allclose(D.numpy(), ref, atol=1e-12)
    assert 0.1 < np.isfinite(ref).mean() < 0.5  # both kinds of pair are present
    # Long spans take the every-pair path for the same block: the same rule, the same numbers.
    traj2, obs2 = short_tracks(30, 40, 25, seed=5)
    ref2 = brute_curve_distance(traj2.numpy(), traj2.numpy(), obs2.numpy(), obs2.numpy(), 3)
    np.testing.assert_allclose(curve_distance(traj2, traj2, obs2, obs2, top_k=3).numpy(), ref2, atol=1e-12)
    # One row per block (greedy_select's queries) equals the whole matrix.
    assert torch.equal(curve_distance(traj, traj, obs, obs, top_k=3, max_chunk=10), D)


def test_knn_graph_equals_brute_force():
    T, N = 6, 80
    g = torch.Generator().manual_seed(11)
    traj = (
        torch.cumsum(torch.randn(T, N, 3, generator=g, dtype=f64) * 0.01, dim=0)
        + torch.rand(1, N, 3, generator=g, dtype=f64) * 0.15
    )
    obs = torch.rand(T, N, generator=g) < 0.8
    obs[0] = True
    scf = build_scaffold(traj, obs, SCALE, ScaffoldConfig(node_spacing_units=1.5))
    M, K = scf.M, scf.K
    assert K == min(16, M)
    ref = brute_curve_distance(
        scf.pos.detach().numpy(), scf.pos.detach().numpy(), scf.observed.numpy(), scf.observed.numpy(), 3
    )
    np.fill_diagonal(ref, np.inf)
    idx = scf.knn_idx.numpy()
    assert (idx[:, 0] == np.arange(M)).all() and bool(scf.edge_valid[:, 0].all())
    for i in range(M):
        got = ref[i, idx[i, 1:]]
        np.testing.assert_allclose(got, np.sort(ref[i])[: K - 1], atol=1e-12)  # ties may swap indices
        assert len(set(idx[i].tolist())) == K
        np.testing.assert_array_equal(scf.edge_valid[i, 1:].numpy(), got < 5 * 0.01 * SCALE)
    # Nodes are pairwise farther than the spacing in the curve metric, and cover every track within it.
    assert (ref > 1.5 * 0.01).all()


def test_greedy_select_spacing_and_coverage():
    g = torch.Generator().manual_seed(2)
    x = torch.rand(300, 2, generator=g, dtype=f64)
    D = torch.cdist(x, x)
    sel = greedy_select(300, lambda i: D[i], 0.1, priority=-torch.arange(300.0))
    sub = D[sel][:, sel] + torch.eye(len(sel), dtype=f64) * 10
    assert bool((sub > 0.1).all())
    assert bool((D[:, sel].min(dim=1).values <= 0.1).all())
    assert sel[0] == 0  # highest priority first
    assert len(greedy_select(300, lambda i: D[i], 0.1, max_count=5)) == 5
    assert greedy_select(0, lambda i: D[i], 0.1).numel() == 0


def test_empty_scaffold_is_accepted_everywhere(device):
    T = 5
    traj = torch.randn(T, 10, 3, dtype=f64, device=device)
    scf = build_scaffold(traj, torch.zeros(T, 10, dtype=torch.bool, device=device), SCALE)
    assert scf.M == 0 and scf.T == T and scf.K == 0
    assert (
        build_scaffold(
            torch.zeros(T, 0, 3, device=device), torch.zeros(T, 0, dtype=torch.bool, device=device), 1.0
        ).M
        == 0
    )
    pts = torch.randn(4, 3, dtype=f64, device=device)
    rot = Q.normalize(torch.randn(4, 4, dtype=f64, device=device))
    p, q = scf.deform(pts, rot, torch.zeros(4, dtype=torch.long, device=device), 3)
    assert torch.equal(p, pts) and torch.allclose(q, rot)
    assert scf.slice_time(1, 3).M == 0 and scf.sigma.shape == (0,)
    losses = motion_losses(scf.pos, scf.quat, scf.arap_graphs())
    losses.total.backward()
    assert all(math.isfinite(v) for v in losses.as_floats().values())
    assert resample_nodes(scf).M == 0
    again = Scaffold.from_state(scf.to_state())
    assert again.M == 0 and again.T == T
    # Densifying an empty scaffold creates still nodes where the content is.
    grown, n = densify(scf, pts, torch.tensor([0, 1, 2, 3], device=device))
    assert n == grown.M == 4 and not grown.observed.any()
    assert torch.allclose(grown.pos, pts[None].expand(T, 4, 3))


def test_slice_time(device):
    T, N = 10, 80
    traj, _ = rigid_scene(T, N, seed=8, device=device)
    scf = build_scaffold(traj, torch.ones(T, N, dtype=torch.bool, device=device), SCALE)
    sub = scf.slice_time(3, 7)
    assert sub.T == 4 and sub.M == scf.M
    assert torch.equal(sub.pos, scf.pos[3:7]) and torch.equal(sub.quat, scf.quat[3:7])
    assert torch.equal(sub.observed, scf.observed[3:7]) and torch.equal(sub.knn_idx, scf.knn_idx)
    assert torch.equal(sub.sigma, scf.sigma)
    for ga, gb in zip(sub.arap_graphs(), scf.arap_graphs(), strict=True):
        assert torch.equal(ga.idx, gb.idx) and torch.equal(ga.valid, gb.valid)
    # Independent copy: editing the slice leaves the parent alone.
    with torch.no_grad():
        sub.pos.add_(1.0)
    assert not torch.equal(sub.pos, scf.pos[3:7])
    sub = scf.slice_time(3, 7)
    # Deformation in local frames equals the parent's at the shifted frames.
    pts = traj[4, :20]
    rot = Q.identity((20,), dtype=f64, device=device)
    local = sub.deform(pts, rot, torch.full((20,), 1, device=device), 3)
    full = scf.deform(pts, rot, torch.full((20,), 4, device=device), 6)
    assert torch.allclose(local[0], full[0]) and torch.allclose(local[1], full[1])
    for bad in ((0, 0), (5, 3), (-1, 2), (0, T + 1)):
        with pytest.raises(ValueError):
            scf.slice_time(*bad)


def test_parameters_state_roundtrip_and_sigma():
    T, N = 6, 60
    traj, _ = rigid_scene(T, N, seed=9)
    scf = build_scaffold(traj, torch.ones(T, N, dtype=torch.bool), SCALE)
    names = {n for n, _ in scf.named_parameters()}
    assert names == {"pos", "quat", "sigma_logit"}
    assert torch.allclose(scf.sigma, torch.full((scf.M,), 0.07, dtype=f64))
    assert float(scf.sigma_max) == pytest.approx(0.2)
    back = Scaffold.from_state(scf.to_state(), device="cpu")
    for k, v in scf.state_dict().items():
        assert torch.equal(back.state_dict()[k], v)
    assert back.cfg == scf.cfg and back.unit == scf.unit


def test_densify_adds_far_nodes_following_the_motion():
    T, N = 8, 100
    traj, _ = rigid_scene(T, N, seed=4)
    scf = build_scaffold(
        traj, torch.ones(T, N, dtype=torch.bool), SCALE, ScaffoldConfig(node_spacing_units=2.0)
    )
    # Points near the object, and two clusters of far ones (10 units away) at frame 2.
    center = traj[2].mean(0)
    far = center + torch.tensor([[0.2, 0.0, 0.0], [0.2005, 0.0, 0.0], [0.0, 0.0, -0.2]], dtype=f64)
    points = torch.cat((traj[2, :10], far))
    t = torch.full((13,), 2)
    grown, n = densify(scf, points, t)
    assert n == 2 and grown.M == scf.M + 2  # the two close far points make one node
    assert torch.equal(grown.pos[:, : scf.M], scf.pos) and not grown.observed[:, scf.M :].any()
    new = grown.pos[2, scf.M :]
    assert torch.cdist(new, far).min(dim=1).values.max() < 1e-12  # placed on the far points at their frame
    assert grown.knn_idx.shape[0] == grown.M
    # Caps: at most densify_max_new nodes per call; nothing far -> unchanged.
    one = Scaffold.from_state(scf.to_state())
    one.cfg = replace(scf.cfg, densify_max_new=1)
    capped, n1 = densify(one, points, t)
    assert n1 == 1 and capped.M == scf.M + 1
    same, n0 = densify(scf, traj[2, :10], t[:10])
    assert n0 == 0 and same is scf


def test_resample_nodes_thins_by_curve_spacing():
    T, N = 6, 100
    traj, _ = rigid_scene(T, N, seed=12)
    scf = build_scaffold(traj, torch.ones(T, N, dtype=torch.bool), SCALE)
    coarse = resample_nodes(scf, 4.0)
    assert 0 < coarse.M < scf.M
    D = coarse.curve_distances()
    assert bool((D > 0.04).all())
    # Kept nodes keep their trajectories exactly.
    for j in range(coarse.M):
        assert bool(((scf.pos - coarse.pos[:, j : j + 1]).abs().amax(dim=(0, 2)) == 0).any())


def test_multilevel_graphs():
    T, N = 6, 150
    traj, _ = rigid_scene(T, N, seed=13)
    scf = build_scaffold(traj, torch.ones(T, N, dtype=torch.bool), SCALE)
    graphs = scf.arap_graphs()
    assert [g.weight for g in graphs] == [1.0, 0.4, 0.3]
    assert [g.detach_neighbours for g in graphs] == [False, True, True]
    assert graphs[0].idx.shape == (scf.M, scf.K - 1)
    D = scf.curve_distances()
    for g, units in zip(graphs[1:], (1.0, 4.0), strict=True):
        assert g.idx.shape[0] == scf.M and g.idx.shape[1] <= 8
        is_self = g.idx == torch.arange(scf.M)[:, None]
        assert not bool((g.valid & is_self).any())  # itself only as padding when the subset is tiny
        d = D.gather(1, g.idx)
        assert torch.equal(g.valid, d < 0.05 * units)
    # The coarse level draws its neighbours from fewer nodes than the fine one.
    assert graphs[2].idx.unique().numel() < graphs[1].idx.unique().numel()


def test_bad_inputs():
    with pytest.raises(ValueError):
        build_scaffold(torch.zeros(3, 4, 2), torch.ones(3, 4, dtype=torch.bool), 1.0)
    with pytest.raises(ValueError):
        build_scaffold(torch.zeros(3, 4, 3), torch.ones(3, 4, dtype=torch.bool), 0.0)
    with pytest.raises(ValueError):
        ScaffoldConfig(rotation_mode="spline")
    with pytest.raises(ValueError):
        ScaffoldConfig(arap_level_k=(8,))


def test_deform_gradients_reach_every_parameter(device):
    T, N = 6, 60
    traj, _ = rigid_scene(T, N, seed=14, device=device)
    g = torch.Generator().manual_seed(1)
    traj = traj + 0.002 * torch.randn(T, N, 3, generator=g, dtype=f64).to(device)  # slightly non-rigid
    scf = build_scaffold(traj, torch.ones(T, N, dtype=torch.bool, device=device), SCALE)
    pts = (traj[1] + 0.01).requires_grad_(True)
    rot = Q.identity((N,), dtype=f64, device=device)
    corr = torch.zeros(N, scf.K, dtype=f64, device=device, requires_grad=True)
    p, q = scf.deform(pts, rot, torch.full((N,), 1, device=device), 4, correction=corr)
    (p.square().sum() + q[..., 1:].sum()).backward()
    for x in (scf.pos, scf.quat, scf.sigma_logit, pts, corr):
        assert x.grad is not None and torch.isfinite(x.grad).all() and bool((x.grad != 0).any())


@pytest.mark.parametrize("T, n_gauss", [(6, 80), (40, 12)], ids=["every-frame-node", "used-pairs"])
def test_scalar_target_table_path_has_the_per_gaussian_gradients(device, T, n_gauss):
    # One target frame uses a dual-quaternion table of node motions (converted once, gathered per neighbour):
    # over every (frame, node) when that is smaller than the Gaussians' (Gaussian, neighbour) pairs, else over
    # the distinct pairs they use. A per-Gaussian target vector composes every (Gaussian, neighbour) transform
    # itself: same values, same gradients for every parameter, either way.
    N = 80
    traj, _ = rigid_scene(T, N, seed=21, device=device)
    g = torch.Generator().manual_seed(2)
    traj = traj + 0.003 * torch.randn(T, N, 3, generator=g, dtype=f64).to(device)
    scf = build_scaffold(traj, torch.ones(T, N, dtype=torch.bool, device=device), SCALE)
    t_ref = torch.randint(0, T, (n_gauss,), generator=g).to(device)
    pts = traj[t_ref, torch.arange(n_gauss, device=device)] + 0.01
    rot = Q.normalize(torch.randn(n_gauss, 4, generator=g, dtype=f64)).to(device)
    cache = scf.attach(pts, t_ref)
    assert (scf.T * scf.M < cache.idx.numel()) == (n_gauss == N)  # which table the scalar target builds
    N = n_gauss
    wp = torch.randn(N, 3, generator=g, dtype=f64).to(device)
    wq = torch.randn(N, 4, generator=g, dtype=f64).to(device)
    grads = []
    for target in (3, torch.full((N,), 3, device=device)):
        leaves = [scf.pos, scf.quat, scf.sigma_logit]
        x, r = pts.clone().requires_grad_(True), rot.clone().requires_grad_(True)
        p, q = scf.deform(x, r, t_ref, target, cache)
        got = torch.autograd.grad((p * wp).sum() + (q * wq).sum(), [*leaves, x, r])
        grads.append((p.detach(), q.detach(), got))
    (p1, q1, g1), (p2, q2, g2) = grads
    torch.testing.assert_close(p1, p2, rtol=0, atol=1e-12)
    torch.testing.assert_close(q1, q2, rtol=0, atol=1e-12)
    for a, b in zip(g1, g2, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10)


def test_attach_picks_the_nearest_node_at_the_reference_frame():
    T, N = 5, 80
    traj, _ = rigid_scene(T, N, seed=15)
    scf = build_scaffold(
        traj, torch.ones(T, N, dtype=torch.bool), SCALE, ScaffoldConfig(node_spacing_units=3.0)
    )
    g = torch.Generator().manual_seed(3)
    pts = traj[2, :30] + 0.01 * torch.randn(30, 3, generator=g, dtype=f64)
    t_ref = torch.randint(0, T, (30,), generator=g)
    cache = scf.attach(pts, t_ref)
    for i in range(30):
        d = (scf.pos[t_ref[i]].detach() - pts[i]).norm(dim=-1)
        assert d[cache.attach[i]] == d.min()
        assert torch.equal(cache.idx[i], scf.knn_idx[cache.attach[i]])
        assert torch.equal(cache.valid[i], scf.edge_valid[cache.attach[i]])


def test_lift_fill_build_pipeline_on_a_moving_plane():
    """A textured square moving rigidly in front of a moving camera: tracks + analytic depth maps -> lift ->
    fill -> scaffold; node rotations and deformation follow the true motion."""
    from worldtree.motion.lift import fill_gaps, lift_tracks

    T, H, W, n_side = 6, 60, 80, 12
    K = torch.tensor([[70.0, 0, 40.0], [0, 70.0, 30.0], [0, 0, 1]], dtype=f64)
    rots = Rotation.from_rotvec(np.linspace(0, 1, T)[:, None] * np.array([0.3, 0.5, 0.2]))
    R_obj = torch.tensor(rots.as_matrix())
    t_obj = torch.tensor(np.linspace(0, 1, T)[:, None] * np.array([0.05, -0.03, 0.04]) + [0, 0, 1.0])
    g = np.linspace(-0.1, 0.1, n_side)
    local = torch.tensor([[x, y, 0.0] for x in g for y in g], dtype=f64)  # [N, 3] in the plane z = 0
    world = torch.einsum("tij,nj->tni", R_obj, local) + t_obj[:, None]
    w2cs = torch.eye(4, dtype=f64).repeat(T, 1, 1)
    w2cs[:, :3, :3] = torch.tensor(
        Rotation.from_rotvec(np.linspace(0, 1, T)[:, None] * [0.0, 0.05, 0.0]).as_matrix()
    )
    w2cs[:, 0, 3] = torch.linspace(0, 0.02, T, dtype=f64)
    cam = torch.einsum("tij,tnj->tni", w2cs[:, :3, :3], world) + w2cs[:, None, :3, 3]
    uv = (cam @ K.T)[..., :2] / cam[..., 2:]
    # Depth of the plane along each pixel ray: z = (n . p0) / (n . K^-1 (u, v, 1)) in camera coordinates.
    vv, uu = torch.meshgrid(torch.arange(H, dtype=f64), torch.arange(W, dtype=f64), indexing="ij")
    rays = torch.stack((uu, vv, torch.ones_like(uu)), -1) @ torch.linalg.inv(K).T  # [H, W, 3]
    depths = torch.zeros(T, H, W, dtype=f64)
    for t in range(T):
        n_cam = w2cs[t, :3, :3] @ R_obj[t][:, 2]
        p0 = cam[t, 0]
        depths[t] = (n_cam @ p0) / (rays @ n_cam)
    vis = torch.ones(T, local.shape[0], dtype=torch.bool)
    vis[2:4, ::7] = False  # a few gaps, filled by interpolation
    pts, valid = lift_tracks(uv, vis, depths, K.expand(T, 3, 3), w2cs)
    assert torch.equal(valid, vis)
    err = (pts - world)[valid].norm(dim=-1).max()
    assert err < 1e-4  # bilinear sampling of a smooth depth map: tiny error
    traj, observed = fill_gaps(pts, valid)
    scf = build_scaffold(traj, observed, 1.0, ScaffoldConfig(node_spacing_units=3.0))
    assert scf.M > 10
    q_true = Q.from_matrix(R_obj)
    for t in range(T):
        rel_s = Q.multiply(scf.quat[t].detach(), Q.conjugate(scf.quat[0].detach()))
        rel_t = Q.multiply(q_true[t], Q.conjugate(q_true[0])).expand_as(rel_s)
        assert math.degrees(float(Q.angle_between(rel_s, rel_t).max())) < 1.0
    p, _ = scf.deform(
        world[0],
        Q.identity((local.shape[0],), dtype=f64),
        torch.zeros(local.shape[0], dtype=torch.long),
        T - 1,
    )
    assert float((p - world[T - 1]).detach().norm(dim=-1).max()) < 2e-3  # 0.2 units
