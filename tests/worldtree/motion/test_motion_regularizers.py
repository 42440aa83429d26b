"""Motion regularisers: hand computations, zero on rigid/constant motion, positive otherwise, safe gradients."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.spatial.transform import Rotation

from worldtree.motion import quaternion as Q
from worldtree.motion.regularizers import (
    MotionLossConfig,
    acceleration_losses,
    arap_loss,
    arap_loss_autograd,
    motion_losses,
    velocity_losses,
)
from worldtree.motion.scaffold import ArapGraph

f64 = torch.float64


def full_graph(M: int) -> ArapGraph:
    """Every node linked to every other node."""
    idx = torch.stack([torch.tensor([j for j in range(M) if j != i]) for i in range(M)])
    return ArapGraph(idx, torch.ones_like(idx, dtype=torch.bool))


def pair_graph() -> ArapGraph:
    return ArapGraph(torch.tensor([[1], [0]]), torch.ones(2, 1, dtype=torch.bool))


def rigid_nodes(T: int, M: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Nodes of one rigid body (random rotation + translation per frame), quats = the true rotations."""
    g = torch.Generator().manual_seed(seed)
    x0 = torch.randn(M, 3, generator=g, dtype=f64)
    rots = Rotation.random(T, random_state=seed)
    R = torch.tensor(rots.as_matrix())
    trans = torch.randn(T, 3, generator=g, dtype=f64)
    pos = torch.einsum("tij,mj->tmi", R, x0) + trans[:, None]
    body = torch.tensor(rots.as_quat(scalar_first=True))  # [T, 4]
    # Each node has its own rest orientation; the ARAP terms only see the motion, which is shared.
    rest = Q.normalize(torch.randn(M, 4, generator=g, dtype=f64))
    quat = Q.multiply(body[:, None], rest[None])
    return pos, quat


def test_hand_computed_positions_only():
    # Node 0 still at the origin; node 1 at x = 1, 2, 2; identity rotations; shift 1 with weight 1.
    pos = torch.zeros(3, 2, 3, dtype=f64)
    pos[:, 1, 0] = torch.tensor([1.0, 2.0, 2.0])
    quat = Q.identity((3, 2), dtype=f64)
    coord, length = arap_loss(pos, quat, pair_graph(), shifts=(1,), shift_weights=(1.0,))
    # local coords +-(1, 2, 2): per (t, i) differences [[1, 1], [0, 0]] -> mean 0.5, for both terms.
    assert coord.item() == pytest.approx(0.5) and length.item() == pytest.approx(0.5)
    v_xyz, v_rot = velocity_losses(pos, quat)
    a_xyz, a_rot = acceleration_losses(pos, quat)
    assert v_xyz.item() == pytest.approx(0.25)  # speeds [[0, 1], [0, 0]]
    assert a_xyz.item() == pytest.approx(0.5)  # |2 - 4 + 1| = 1 for node 1, 0 for node 0
    assert v_rot.item() < 1e-12 and a_rot.item() < 1e-12  # guarded sqrt: ~1e-154, not exactly 0
    cfg = MotionLossConfig(arap_shifts=(1,), arap_shift_weights=(1.0,))
    total = motion_losses(pos, quat, [pair_graph()], cfg).total
    assert total.item() == pytest.approx(0.3 * 0.5 + 0.3 * 0.5 + 5 * 0.25 + 0.3 * 0.5)


def test_hand_computed_rotations_only():
    # Still positions; node 1 turns about z by 0, 0.1, 0.3 rad.
    pos = torch.zeros(3, 2, 3, dtype=f64)
    pos[:, 1, 0] = 1.0
    ang = torch.tensor([0.0, 0.1, 0.3], dtype=f64)
    quat = Q.identity((3, 2), dtype=f64)
    quat[:, 1] = Q.from_axis_angle(torch.tensor([0.0, 0.0, 1.0], dtype=f64), ang)
    v_xyz, v_rot = velocity_losses(pos, quat)
    a_xyz, a_rot = acceleration_losses(pos, quat)
    assert v_xyz.item() < 1e-12 and a_xyz.item() < 1e-12
    assert v_rot.item() == pytest.approx((0.1 + 0.2) / 4)
    assert a_rot.item() == pytest.approx(0.1 / 2)
    coord, length = arap_loss(pos, quat, pair_graph(), shifts=(1,), shift_weights=(1.0,))
    # Node 0 seen from node 1's frame turns on the unit circle: chord 2 sin(dtheta / 2).
    assert coord.item() == pytest.approx((2 * math.sin(0.05) + 2 * math.sin(0.1)) / 4)
    assert length.item() == pytest.approx(0.0, abs=1e-15)


def test_zero_for_rigid_motion_and_positive_for_non_rigid():
    T, M = 7, 6
    pos, quat = rigid_nodes(T, M, seed=1)
    g = full_graph(M)
    coord, length = arap_loss(pos, quat, g)
    assert coord.item() < 1e-12 and length.item() < 1e-12
    assert velocity_losses(pos, quat)[0].item() > 0.1  # it does move
    # Growing the body over time breaks rigidity: both terms become positive.
    scale = torch.linspace(1.0, 1.5, T, dtype=f64)[:, None, None]
    c2, l2 = arap_loss(pos * scale, quat, g)
    assert c2.item() > 1e-3 and l2.item() > 1e-3
    # Wrong node rotations break the coordinate term but not the length term.
    c3, l3 = arap_loss(pos, Q.identity((T, M), dtype=f64), g)
    assert c3.item() > 1e-3 and l3.item() < 1e-12


def test_constant_velocity_has_no_acceleration():
    T, M = 6, 3
    t = torch.arange(T, dtype=f64)[:, None, None]
    g = torch.Generator().manual_seed(4)
    pos = torch.randn(1, M, 3, generator=g, dtype=f64) + t * torch.randn(1, M, 3, generator=g, dtype=f64)
    axis = torch.randn(M, 3, generator=g, dtype=f64)
    quat = Q.multiply(
        Q.from_axis_angle(axis[None], 0.3 * t[..., 0]), Q.normalize(torch.randn(M, 4, generator=g, dtype=f64))
    )
    a_xyz, a_rot = acceleration_losses(pos, quat)
    assert a_xyz.item() < 1e-12 and a_rot.item() < 1e-6
    _, v_rot = velocity_losses(pos, quat)
    assert v_rot.item() == pytest.approx(0.3)


def test_sign_invariance():
    pos, quat = rigid_nodes(6, 5, seed=2)
    pos = pos + 0.1 * torch.randn_like(pos)
    flip = torch.where(torch.rand(6, 5, 1) < 0.5, -1.0, 1.0).to(f64)
    a = motion_losses(pos, quat, [full_graph(5)])
    b = motion_losses(pos, quat * flip, [full_graph(5)])
    for k, v in a.as_floats().items():
        assert b.as_floats()[k] == pytest.approx(v, rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("T,M", [(1, 4), (2, 4), (5, 0), (3, 1), (6, 4)])
def test_degenerate_inputs_finite_with_finite_gradients(T, M, device):
    pos = torch.zeros(T, M, 3, dtype=torch.float32, device=device, requires_grad=True)  # static, coincident
    quat = Q.identity((T, M), device=device).requires_grad_(True)
    graph = (
        full_graph(M)
        if M > 1
        else ArapGraph(torch.zeros(M, 0, dtype=torch.long), torch.zeros(M, 0, dtype=torch.bool))
    )
    graph = ArapGraph(graph.idx.to(device), graph.valid.to(device))
    out = motion_losses(pos, quat, [graph, ArapGraph(graph.idx, graph.valid, 0.4, True)])
    out.total.backward()
    assert all(abs(v) < 1e-12 for v in out.as_floats().values())
    for p in (pos, quat):
        assert p.grad is not None and torch.isfinite(p.grad).all()


def test_masked_edges_and_gradients_match_finite_differences():
    T, M = 5, 4
    g = torch.Generator().manual_seed(9)
    pos = torch.randn(T, M, 3, generator=g, dtype=f64, requires_grad=True)
    quat = torch.randn(T, M, 4, generator=g, dtype=f64, requires_grad=True)
    graph = full_graph(M)
    graph.valid[0] = False  # node 0 has no valid edge: contributes nothing
    graph.valid[1, 0] = False
    cfg = MotionLossConfig()

    def f(p, q):
        # (a detached-neighbour graph is left out: finite differences see through the detach by design)
        return motion_losses(p, q, [graph], cfg).total

    assert torch.autograd.gradcheck(f, (pos, quat), eps=1e-6, atol=1e-5)


def test_detached_neighbours_get_no_gradient_through_the_edge():
    pos = torch.zeros(4, 2, 3, dtype=f64)
    pos[:, 1, 0] = torch.tensor([1.0, 1.5, 2.0, 3.0])
    pos.requires_grad_(True)
    quat = Q.identity((4, 2), dtype=f64)
    g = ArapGraph(torch.tensor([[1], [0]]), torch.tensor([[True], [False]]), 1.0, True)
    coord, _ = arap_loss(pos, quat, g, shifts=(1,), shift_weights=(1.0,))
    coord.backward()
    # Only node 0's row is active and its neighbour (node 1) is detached: node 1 gets no gradient.
    assert torch.all(pos.grad[:, 1] == 0) and torch.any(pos.grad[:, 0] != 0)


def _random_graph_case(T: int, detach: bool, seed: int, M: int = 11, K: int = 5):
    """A KNN-like graph (M nodes, K neighbours) with repeated neighbours, invalid edges, a row with none valid and
    two coincident nodes (zero-length edges, where the guarded norm's gradient must be 0),
    with float64 positions and rotations."""
    g = torch.Generator().manual_seed(seed)
    pos = torch.randn(T, M, 3, generator=g, dtype=f64)
    pos[:, 5] = pos[:, 4]
    quat = torch.randn(T, M, 4, generator=g, dtype=f64)
    idx = torch.randint(0, M, (M, K), generator=g)
    idx[4, 0] = 5
    valid = torch.rand(M, K, generator=g) > 0.3
    valid[2] = False
    valid[4, 0] = True
    return pos, quat, ArapGraph(idx, valid, 0.4, detach)


def _arap_values(fn, pos, quat, graph, dtype):
    p = pos.to(dtype).detach().clone().requires_grad_(True)
    q = quat.to(dtype).detach().clone().requires_grad_(True)
    coord, length = fn(p, q, graph, shifts=(1, 2, 4), shift_weights=(0.2, 0.5, 0.3))
    (0.7 * coord + 1.3 * length).backward()
    q_grad = q.grad if q.grad is not None else torch.zeros_like(q)
    return [coord.detach(), length.detach(), p.grad, q_grad]


@pytest.mark.parametrize("detach", [False, True])
@pytest.mark.parametrize("T", [1, 3, 9])  # 1 and 3: every / some shifts skipped (T <= s)
def test_fused_arap_equals_the_edge_by_edge_autograd_version(detach, T):
    pos, quat, graph = _random_graph_case(T, detach, seed=3 + T, M=7, K=4)
    got = _arap_values(arap_loss, pos, quat, graph, f64)
    want = _arap_values(arap_loss_autograd, pos, quat, graph, f64)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)
    if T > 1:
        assert want[0] > 0 and want[2].abs().sum() > 0  # the comparison saw non-trivial values

def test_fused_arap_float32_matches_float64():
    # The fused backward keeps float32 near the float64 reference (no cancellation it adds itself).
    g = torch.Generator().manual_seed(11)
    pos = torch.randn(6, 9, 3, generator=g, dtype=f64)
    quat = torch.randn(6, 9, 4, generator=g, dtype=f64)
    graph = full_graph(9)
    outs = []
    for dt in (f64, torch.float32):
        p = pos.to(dt).detach().clone().requires_grad_(True)
        q = quat.to(dt).detach().clone().requires_grad_(True)
        coord, length = arap_loss(p, q, graph)
        (coord + length).backward()
        outs.append([coord.double(), length.double(), p.grad.double(), q.grad.double()])
    for a, b in zip(*outs, strict=True):
        torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-5)


def _compiled_kernel():
    from worldtree.render import cpu_kernel

    if not cpu_kernel.available():
        pytest.skip(f"the compiled kernel does not build here: {cpu_kernel.build_error()}")
    return cpu_kernel


@pytest.mark.parametrize("detach", [False, True])
@pytest.mark.parametrize("T", [1, 3, 9])
def test_compiled_arap_matches_the_float64_autograd_reference(detach, T):
    # float32 on the CPU takes the compiled kernel; the reference is the edge-by-edge autograd version in float64.
    from worldtree.motion import regularizers

    _compiled_kernel()
    pos, quat, graph = _random_graph_case(T, detach, seed=17 + T)
    assert regularizers._compiled_ops(pos.float()) is not None  # the path under test is the compiled one
    got = _arap_values(arap_loss, pos, quat, graph, torch.float32)
    want = _arap_values(arap_loss_autograd, pos, quat, graph, f64)
    for a, b in zip(got, want, strict=True):
        assert a.dtype == torch.float32 and torch.isfinite(a).all()
        torch.testing.assert_close(a.double(), b, rtol=2e-5, atol=2e-6)
    if T > 1:
        assert want[0] > 0 and want[2].abs().sum() > 0
        if not detach:
            assert want[3].abs().sum() > 0  # the rotations' gradient was compared too


def test_compiled_arap_gives_the_same_bits_for_any_thread_count():
    _compiled_kernel()
    pos, quat, graph = _random_graph_case(12, False, seed=5)
    before = torch.get_num_threads()
    try:
        runs = []
        for n in (1, 2, 3):
            torch.set_num_threads(n)
            runs.append(_arap_values(arap_loss, pos, quat, graph, torch.float32))
    finally:
        torch.set_num_threads(before)
    for other in runs[1:]:
        for a, b in zip(runs[0], other, strict=True):
            assert torch.equal(a, b)


def test_arap_falls_back_to_the_tensor_version_without_the_kernel(monkeypatch):
    from worldtree.motion import regularizers
    from worldtree.render import cpu_kernel

    pos, quat, graph = _random_graph_case(6, False, seed=8)
    monkeypatch.setattr(cpu_kernel, "ops", lambda: None)
    assert regularizers._compiled_ops(pos.float()) is None
    got = _arap_values(arap_loss, pos, quat, graph, torch.float32)
    want = _arap_values(arap_loss_autograd, pos, quat, graph, f64)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a.double(), b, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("compiled", [True, False])
def test_arap_shows_a_nan_position_in_its_value(compiled, monkeypatch):
    # A NaN must reach the loss (and so the trainers' finiteness checks), not vanish behind the norm's guard.
    from worldtree.render import cpu_kernel

    if compiled:
        _compiled_kernel()
    else:
        monkeypatch.setattr(cpu_kernel, "ops", lambda: None)
    pos, quat, graph = _random_graph_case(5, False, seed=2)
    pos = pos.float()
    pos[2, 3, 1] = float("nan")
    coord, length = arap_loss(pos, quat.float(), graph)
    assert math.isnan(float(coord)) and math.isnan(float(length))


def test_frame_window_is_seeded_sized_and_covers_the_video():
    from worldtree.motion.regularizers import frame_window

    assert frame_window(40, 0, 1, 5) == slice(None) and frame_window(40, 40, 1, 5) == slice(None)
    assert frame_window(40, 100, 1, 5) == slice(None)
    seen = torch.zeros(40)
    for step in range(400):
        w = frame_window(40, 12, 3, step)
        assert w == frame_window(40, 12, 3, step)  # (seed, step) alone: a resumed fit repeats it
        assert w.stop - w.start == 12 and 0 <= w.start and w.stop <= 40
        seen[w] += 1
    assert seen.min() > 0  # every frame, ends included, is drawn
    # Middle frames are covered about 12/29 of the steps (29 possible starts); binomial sd is about 10.
    assert abs(float(seen[14:26].mean()) - 400 * 12 / 29) < 40
    assert any(frame_window(40, 12, 3, k) != frame_window(40, 12, 4, k) for k in range(10))  # the seed matters
