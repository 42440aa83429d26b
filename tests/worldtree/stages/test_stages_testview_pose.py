"""Test-view pose: Sim(3) alignment (against an independent numpy Umeyama) and photometric refinement."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from worldtree.render import rasterize
from worldtree.stages.cameras import Sim3, apply_delta, centres, rotation_angle_deg
from worldtree.stages.testview_pose import (
    CameraPlacement,
    FrozenModelRenderer,
    PoseRefineConfig,
    align_sim3,
    refine_test_poses,
)


def numpy_umeyama(src: np.ndarray, dst: np.ndarray):
    """Umeyama 1991, eqs. 34-42, written from the paper: dst ~ c R src + t."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    var_s = ((src - mu_s) ** 2).sum(1).mean()
    cov = (dst - mu_d).T @ (src - mu_s) / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    c = np.trace(np.diag(D) @ S) / var_s
    return c, R, mu_d - c * R @ mu_s


def make_w2c(R_c2w: np.ndarray, centre: np.ndarray) -> np.ndarray:
    w2c = np.eye(4)
    w2c[:3, :3] = R_c2w.T
    w2c[:3, 3] = -R_c2w.T @ centre
    return w2c


def transform_poses(w2cs: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The same cameras in a frame where x' = s R x + t (written out directly, not via Sim3)."""
    out = []
    for w in w2cs:
        Rc2w = w[:3, :3].T
        c = -Rc2w @ w[:3, 3]
        out.append(make_w2c(R @ Rc2w, s * R @ c + t))
    return np.stack(out)


def random_rig(rng, n: int, collinear: bool = False) -> np.ndarray:
    poses = []
    for i in range(n):
        c = np.array([0.3 * i, 0.0, 0.0]) if collinear else rng.normal(size=3)
        poses.append(make_w2c(Rotation.random(random_state=rng).as_matrix(), c))
    return np.stack(poses)


def test_align_sim3_recovers_known_similarity():
    rng = np.random.default_rng(0)
    src = random_rig(rng, 8)
    R_true = Rotation.random(random_state=rng).as_matrix()
    s_true, t_true = 2.7, np.array([0.4, -1.2, 3.0])
    dst = transform_poses(src, s_true, R_true, t_true)
    sim = align_sim3(torch.from_numpy(src), torch.from_numpy(dst))
    c_ref, R_ref, t_ref = numpy_umeyama(
        centres(torch.from_numpy(src)).numpy(), centres(torch.from_numpy(dst)).numpy()
    )
    np.testing.assert_allclose(sim.scale, s_true, rtol=1e-10)
    np.testing.assert_allclose(sim.R.numpy(), R_true, atol=1e-10)
    np.testing.assert_allclose(sim.t.numpy(), t_true, atol=1e-10)
    np.testing.assert_allclose(sim.scale, c_ref, rtol=1e-10)
    np.testing.assert_allclose(sim.R.numpy(), R_ref, atol=1e-10)
    # The test camera's pose follows: exactly the pose written out independently.
    test = random_rig(rng, 1)
    got = sim.apply_w2c(torch.from_numpy(test)).numpy()
    np.testing.assert_allclose(got, transform_poses(test, s_true, R_true, t_true), atol=1e-9)


def test_align_sim3_noisy_matches_numpy_umeyama():
    rng = np.random.default_rng(1)
    src = random_rig(rng, 10)
    dst = transform_poses(src, 0.5, Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
    dst[:, :3, 3] += rng.normal(scale=0.01, size=(10, 3))
    sim = align_sim3(torch.from_numpy(src), torch.from_numpy(dst))
    c_ref, R_ref, t_ref = numpy_umeyama(
        centres(torch.from_numpy(src)).numpy(), centres(torch.from_numpy(dst)).numpy()
    )
    np.testing.assert_allclose(sim.scale, c_ref, rtol=1e-9)
    np.testing.assert_allclose(sim.R.numpy(), R_ref, atol=1e-9)
    np.testing.assert_allclose(sim.t.numpy(), t_ref, atol=1e-9)


def test_align_sim3_collinear_centres_use_orientations():
    rng = np.random.default_rng(2)
    src = random_rig(rng, 6, collinear=True)
    R_true = Rotation.random(random_state=rng).as_matrix()
    dst = transform_poses(src, 1.5, R_true, np.array([1.0, 2.0, 3.0]))
    sim = align_sim3(torch.from_numpy(src), torch.from_numpy(dst))
    np.testing.assert_allclose(sim.R.numpy(), R_true, atol=1e-9)
    np.testing.assert_allclose(sim.scale, 1.5, rtol=1e-9)
    np.testing.assert_allclose(sim.t.numpy(), [1.0, 2.0, 3.0], atol=1e-9)


def test_apply_w2c_keeps_the_image_of_mapped_points():
    rng = np.random.default_rng(3)
    sim = Sim3(
        1.7, torch.from_numpy(Rotation.random(random_state=rng).as_matrix()), torch.tensor([0.2, 0.1, -0.4])
    )
    w2c = torch.from_numpy(random_rig(rng, 1)[0])
    pts = torch.from_numpy(rng.normal(size=(20, 3)))

    def project(w, x):
        cam = x @ w[:3, :3].T + w[:3, 3]
        return cam[:, :2] / cam[:, 2:], cam[:, 2]

    uv0, z0 = project(w2c, pts)
    uv1, z1 = project(sim.apply_w2c(w2c), sim.apply_points(pts))
    torch.testing.assert_close(uv1, uv0)
    torch.testing.assert_close(z1, 1.7 * z0)


# ---------------------------------------------------------------------------------------------- refinement
W, H = 48, 32


def tiny_scene(seed: int = 0):
    """~300 coloured Gaussians on a bumpy surface 4 units in front of a camera at the origin."""
    g = torch.Generator().manual_seed(seed)
    n = 300
    xy = (torch.rand(n, 2, generator=g) - 0.5) * torch.tensor([3.6, 2.6])
    z = 4.0 + 0.4 * torch.sin(2.0 * xy[:, :1]) * torch.cos(1.5 * xy[:, 1:])
    means = torch.cat([xy, z], 1)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1)
    log_scales = torch.full((n, 3), float(np.log(0.09)))
    opac = torch.full((n,), 0.9)
    colors = torch.rand(n, 3, generator=g)
    K = torch.tensor([[40.0, 0.0, (W - 1) / 2], [0.0, 40.0, (H - 1) / 2], [0.0, 0.0, 1.0]])

    def render_fn(_time: int, w2c: torch.Tensor):
        return rasterize(means, quats, log_scales, opac, colors, K, w2c, W, H)

    return render_fn


def pose_errors(a: torch.Tensor, b: torch.Tensor) -> tuple[float, float]:
    rot = float(rotation_angle_deg(a[:3, :3], b[:3, :3]))
    return rot, float((centres(a) - centres(b)).norm())


def test_refinement_recovers_a_small_perturbation():
    render_fn = tiny_scene()
    truth = torch.eye(4)
    with torch.no_grad():
        target = render_fn(0, truth).rgb
    xi = torch.tensor([0.04, -0.03, 0.02, 0.012, -0.01, 0.008])  # ~4 cm and ~0.9 degrees
    start = apply_delta(xi, truth)
    rot0, tr0 = pose_errors(start, truth)
    cfg = PoseRefineConfig(first_steps=150, lr_init=3e-3, lr_final=1e-4)
    res = refine_test_poses(render_fn, start, target[None], [0], cfg)
    rot1, tr1 = pose_errors(res.w2cs[0], truth)
    assert res.steps == [150]
    assert res.loss_after[0] < 0.3 * res.loss_before[0]
    assert rot1 < 0.25 * rot0, (rot0, rot1)
    assert tr1 < 0.25 * tr0, (tr0, tr1)


def test_next_frames_start_from_the_previous_result():
    render_fn = tiny_scene(1)
    truth = torch.eye(4)
    with torch.no_grad():
        target = render_fn(0, truth).rgb
    start = apply_delta(torch.tensor([0.03, 0.02, 0.0, 0.0, 0.01, 0.0]), truth)
    # Three frames of the same static view: later frames get few steps but start near the answer.
    cfg = PoseRefineConfig(first_steps=300, next_steps=5)
    res = refine_test_poses(render_fn, start, target[None].repeat(3, 1, 1, 1), [0, 1, 2], cfg)
    assert res.steps == [300, 5, 5]
    _, tr_start = pose_errors(start, truth)
    for k in range(3):
        _, tr = pose_errors(res.w2cs[k], truth)
        assert tr < 0.1 * tr_start
    # Frame 1 starts where frame 0 ended, so its starting error is frame 0's final error.
    assert res.loss_before[1] == pytest.approx(res.loss_after[0], rel=1e-5)


def test_disabled_refinement_and_empty_views_keep_the_pose():
    render_fn = tiny_scene()
    start = apply_delta(torch.tensor([0.03, 0.0, 0.0, 0.0, 0.0, 0.0]), torch.eye(4))
    target = torch.zeros(1, H, W, 3)
    res = refine_test_poses(render_fn, start, target, [0], PoseRefineConfig(enabled=False))
    torch.testing.assert_close(res.w2cs[0], start)
    # A camera looking away sees nothing (alpha 0 everywhere): no step is taken, the pose is kept.
    away = torch.diag(torch.tensor([1.0, 1.0, -1.0, 1.0]))
    away[0, 0] = -1.0
    res = refine_test_poses(render_fn, away, target, [0], PoseRefineConfig(first_steps=5))
    assert res.steps == [0]
    torch.testing.assert_close(res.w2cs[0], away)


def test_orientation_alignment_is_robust_on_a_small_noisy_rig():
    """A rig 0.1 wide with 1 cm centre noise: Umeyama's rotation tilts by degrees, the orientations' does not."""
    rng = np.random.default_rng(7)
    src = []
    for i in range(11):
        R = Rotation.from_euler("y", 0.01 * i).as_matrix()
        src.append(make_w2c(R, np.array([0.01 * i, 0.02 * (i % 2), 0.0])))
    src = np.stack(src)
    R_true = Rotation.from_euler("xyz", [0.1, -0.2, 0.05]).as_matrix()
    dst = transform_poses(src, 1.0, R_true, np.array([0.5, 0.0, 0.1]))
    for k in range(11):  # centre noise only: c' = c + e  <=>  t' = t - R e
        dst[k][:3, 3] -= dst[k][:3, :3] @ rng.normal(scale=0.01, size=3)
    src_t, dst_t = torch.from_numpy(src), torch.from_numpy(dst)
    err_or = rotation_angle_deg(align_sim3(src_t, dst_t, "orientations").R, torch.from_numpy(R_true))
    err_ce = rotation_angle_deg(align_sim3(src_t, dst_t, "centres").R, torch.from_numpy(R_true))
    assert float(err_or) < 1e-6
    assert float(err_ce) > 1.0


# ---------------------------------------------------------------------------------- frozen-model renderer
def moving_model(seed: int = 0):
    """``gaussians_at(t)`` of a trainable-looking model whose Gaussians drift with the frame (leaf tensors
    with ``requires_grad``, as a trained fit's parameters are), K, and a call counter."""
    g = torch.Generator().manual_seed(seed)
    n = 200
    xy = (torch.rand(n, 2, generator=g) - 0.5) * torch.tensor([3.0, 2.2])
    base = torch.cat([xy, 4.0 + 0.3 * torch.rand(n, 1, generator=g)], 1).requires_grad_(True)
    velocity = (0.05 * torch.randn(n, 3, generator=g)).requires_grad_(True)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1).requires_grad_(True)
    log_scales = torch.full((n, 3), float(np.log(0.1)), requires_grad=True)
    opac = torch.full((n,), 0.85, requires_grad=True)
    colors = torch.rand(n, 3, generator=g).requires_grad_(True)
    K = torch.tensor([[40.0, 0.0, (W - 1) / 2], [0.0, 40.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
    calls = []

    def gaussians_at(t: int):
        calls.append(t)
        return base + t * velocity, quats * 1.0, log_scales * 1.0, opac * 1.0, colors * 1.0

    return gaussians_at, K, calls


def test_frozen_renderer_equals_uncached_render_and_pose_gradient():
    gaussians_at, K, calls = moving_model()
    cached = FrozenModelRenderer(gaussians_at, K, W, H, "auto")
    for t in (0, 0, 3, 3, 3):
        xi = torch.tensor([0.02, -0.01, 0.01, 0.005, 0.0, -0.004], requires_grad=True)
        w2c = apply_delta(xi, torch.eye(4))
        # Uncached: the model's tensors stay in the graph, as before the cache.
        ref = rasterize(*gaussians_at(t), K, w2c, W, H)
        (g_ref,) = torch.autograd.grad((ref.rgb * torch.linspace(0, 1, 3)).sum() + ref.alpha.sum(), [xi])
        out = cached(t, apply_delta(xi, torch.eye(4)))
        (g_got,) = torch.autograd.grad((out.rgb * torch.linspace(0, 1, 3)).sum() + out.alpha.sum(), [xi])
        torch.testing.assert_close(out.rgb, ref.rgb.detach(), rtol=0, atol=1e-6)
        torch.testing.assert_close(out.alpha, ref.alpha.detach(), rtol=0, atol=1e-6)
        torch.testing.assert_close(g_got, g_ref, rtol=1e-5, atol=1e-6)
    assert cached.computed == 2  # once for frame 0, once for frame 3


def test_refinement_with_the_frozen_renderer_matches_the_uncached_one():
    gaussians_at, K, calls = moving_model(2)
    truth = torch.eye(4)
    with torch.no_grad():
        targets = torch.stack([rasterize(*gaussians_at(t), K, truth, W, H).rgb for t in (0, 1, 2)])
    start = apply_delta(torch.tensor([0.03, 0.02, 0.0, 0.0, 0.01, 0.0]), truth)
    cfg = PoseRefineConfig(first_steps=20, next_steps=4)

    def uncached(t: int, w2c: torch.Tensor):
        return rasterize(*gaussians_at(t), K, w2c, W, H)

    ref = refine_test_poses(uncached, start, targets, [0, 1, 2], cfg)
    calls.clear()
    renderer = FrozenModelRenderer(gaussians_at, K, W, H, "auto")
    got = refine_test_poses(renderer, start, targets, [0, 1, 2], cfg)
    torch.testing.assert_close(got.w2cs, ref.w2cs, rtol=0, atol=1e-5)
    np.testing.assert_allclose(got.loss_after, ref.loss_after, rtol=1e-4, atol=1e-7)
    assert got.steps == ref.steps == [20, 4, 4]
    assert calls == [0, 1, 2]  # the model was evaluated once per frame, not once per step (34 renders)


def test_coinciding_frame_finds_the_same_camera_only():
    from worldtree.stages.testview_pose import coinciding_frame

    rng = np.random.default_rng(3)
    R = Rotation.random(5, random_state=4).as_matrix()
    centres_np = rng.normal(size=(5, 3)) * 0.1  # a rig about 0.1 units across
    given = torch.from_numpy(np.stack([make_w2c(R[i], centres_np[i]) for i in range(5)]))
    for i in range(5):
        assert coinciding_frame(given[i].float(), given) == i  # float32 round trip of the same pose
    dup = torch.cat([given, given[2:3]])
    assert coinciding_frame(given[2], dup) == 2  # the first of two frames of one camera
    # Turned by 1e-3 rad, or moved by 1e-3 of the rig: another camera (tolerance 1e-4 of each).
    turned = make_w2c(Rotation.from_rotvec([0, 1e-3, 0]).as_matrix() @ R[1], centres_np[1])
    assert coinciding_frame(torch.from_numpy(turned), given) is None
    spread = np.linalg.norm(centres_np - centres_np.mean(0), axis=1).max()
    moved = make_w2c(R[1], centres_np[1] + np.array([1e-3 * spread, 0, 0]))
    assert coinciding_frame(torch.from_numpy(moved), given) is None
    close = make_w2c(R[1], centres_np[1] + np.array([1e-5 * spread, 0, 0]))
    assert coinciding_frame(torch.from_numpy(close), given) == 1
    assert coinciding_frame(given[0], given[:0]) is None
    # One training camera: the centre tolerance is absolute (no rig size to scale it).
    assert coinciding_frame(given[0], given[:1]) == 0
    assert coinciding_frame(torch.from_numpy(moved), given[1:2]) is None  # moved 3e-4 units > 1e-4
    assert coinciding_frame(torch.from_numpy(close), given[1:2]) == 0  # moved 3e-6 units


def drifting_rig(T: int = 12, seed: int = 0):
    """A row of T cameras (frame i from camera i) looking down +z, a known Sim(3), and fitted poses that are
    the Sim(3) of the given ones left-multiplied by a residual drifting linearly with time (rotations of a
    few tenths of a degree, translations of a few thousandths), written with scipy, not the module's se3."""
    rng = np.random.default_rng(seed)
    given = np.stack([make_w2c(np.eye(3), np.array([0.1 * i, 0.02 * (i % 2), 0.0])) for i in range(T)])
    s, R, t = 2.0, Rotation.from_euler("xyz", [5, -8, 12], degrees=True).as_matrix(), np.array([0.3, -0.1, 0.5])
    placed = transform_poses(given, s, R, t)
    a0, a1 = rng.normal(size=3) * 0.004, rng.normal(size=3) * 0.0004  # radians, radians per frame
    b0, b1 = rng.normal(size=3) * 0.004, rng.normal(size=3) * 0.0004

    def residual(time: float) -> np.ndarray:
        D = np.eye(4)
        D[:3, :3] = Rotation.from_rotvec(a0 + a1 * time).as_matrix()
        D[:3, 3] = b0 + b1 * time
        return D

    fitted = np.stack([residual(i) @ placed[i] for i in range(T)])
    sim3 = Sim3(s, torch.tensor(R), torch.tensor(t))
    return torch.tensor(given), torch.tensor(fitted), sim3, residual, (s, R, t)


def test_placement_carries_the_residual_of_the_frames_near_in_time():
    given, fitted, sim3, residual, (s, R, t) = drifting_rig()
    place = CameraPlacement.fit(given, fitted, sim3, time_sigma=2.0)
    assert place.spacing == pytest.approx(0.1 * float(np.hypot(0.1, 0.02)), rel=1e-6)
    # A camera halfway between cameras 4 and 5, at time 4.5: where the drifting residual puts it.
    new = make_w2c(np.eye(3), np.array([0.45, 0.01, 0.0]))
    truth = residual(4.5) @ transform_poses(new[None], s, R, t)[0]
    got = place.place(torch.tensor(new), 4.5)
    only_sim3 = sim3.apply_w2c(torch.tensor(new))
    rot, tr = pose_errors(got, torch.tensor(truth))
    rot0, tr0 = pose_errors(only_sim3, torch.tensor(truth))
    assert rot < 0.02 * rot0 and tr < 0.02 * tr0, (rot, rot0, tr, tr0)
    # Every training camera at its own time comes back near its fitted pose (its own residual weighs most).
    for i in (0, 5, 11):
        rot, tr = pose_errors(place.place(given[i], float(i)), fitted[i])
        rot0, tr0 = pose_errors(sim3.apply_w2c(given[i]), fitted[i])
        assert rot < 0.1 * rot0 and tr < 0.1 * tr0
    assert got.dtype == torch.float64 and place.place(given[0].float(), 0.0).dtype == torch.float32


def test_placement_without_time_weight_is_the_sim3_and_weights_stay_finite():
    given, fitted, sim3, _, _ = drifting_rig()
    off = CameraPlacement.fit(given, fitted, sim3, time_sigma=0.0)
    torch.testing.assert_close(off.place(given[3], 3.0), sim3.apply_w2c(given[3]))
    on = CameraPlacement.fit(given, fitted, sim3, time_sigma=2.0)
    for time in (-1e6, 1e6, 5.5):  # far outside the video: the nearest frame's residual, no 0 / 0
        w = on.weights(centres(given[2][None])[0], time)
        assert torch.isfinite(w).all() and float(w.sum()) == pytest.approx(1.0)
    assert float(on.weights(centres(given[2][None])[0], 1e6).argmax()) == 11
    torch.testing.assert_close(on.place(given[3], float("nan")), sim3.apply_w2c(given[3]))
    # A frame whose fitted pose is not finite contributes a zero residual instead of NaN.
    bad = fitted.clone()
    bad[4] = float("nan")
    p = CameraPlacement.fit(given, bad, sim3, time_sigma=2.0)
    assert torch.isfinite(p.twists).all() and float(p.twists[4].abs().max()) == 0.0
    assert torch.isfinite(p.place(given[4], 4.0)).all()
    # Every camera at one centre (a fixed camera): a unit spacing, the time alone decides.
    one = given[:1].repeat(5, 1, 1)
    p = CameraPlacement.fit(one, fitted[:5], sim3, time_sigma=1.0)
    assert p.spacing == pytest.approx(0.1) and int(p.weights(centres(one[:1])[0], 4.0).argmax()) == 4
    with pytest.raises(ValueError, match=r"\[T, 4, 4\]"):
        CameraPlacement.fit(given, fitted[:3], sim3, time_sigma=1.0)


def test_a_frame_starts_from_its_candidate_when_that_renders_it_better():
    render_fn = tiny_scene(2)
    truth = torch.eye(4)
    with torch.no_grad():
        target = render_fn(0, truth).rgb
    far = apply_delta(torch.tensor([0.3, 0.2, 0.0, 0.0, 0.05, 0.0]), truth)
    near = apply_delta(torch.tensor([0.01, 0.0, 0.0, 0.0, 0.0, 0.0]), truth)
    cfg = PoseRefineConfig(first_steps=0, next_steps=0)  # no steps: only the choice of start is seen
    cands = torch.stack([far, near, far])
    res = refine_test_poses(render_fn, far, target[None].repeat(3, 1, 1, 1), [0, 1, 2], cfg, w2c_candidates=cands)
    torch.testing.assert_close(res.w2cs[0], far)  # the first frame starts from w2c_init
    torch.testing.assert_close(res.w2cs[1], near)  # the candidate renders frame 1 better than frame 0's pose
    torch.testing.assert_close(res.w2cs[2], near)  # the worse candidate is not taken
    assert res.loss_before[1] < res.loss_before[0]
    with pytest.raises(ValueError, match="candidates"):
        refine_test_poses(render_fn, far, target[None], [0], cfg, w2c_candidates=cands)
