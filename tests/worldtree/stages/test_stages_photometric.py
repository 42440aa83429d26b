"""Joint photometric fit on a tiny scene with a rigidly moving object: deformation, losses, gradients."""

from __future__ import annotations

import numpy as np
import torch

from worldtree.dynamic import DynamicGaussians
from worldtree.gaussians import GaussianSet
from worldtree.motion.scaffold import ScaffoldConfig, build_scaffold
from worldtree.render import rasterize
from worldtree.stages.photometric import PhotometricConfig, PhotometricFit, anchored_depth_l1, ssi_depth_l1
from worldtree.strategy import DensifyStrategy
from worldtree.trainer import Trainer, TrainerConfig

W, H, T = 48, 32, 5
VEL = torch.tensor([0.12, 0.0, 0.0])  # object velocity, world units per frame


def scene(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    n_s, n_d = 300, 60
    xy = (torch.rand(n_s, 2, generator=g) - 0.5) * torch.tensor([4.5, 3.2])
    static = GaussianSet.from_tensors(
        # Distinct depths: on an exactly flat sheet a tiny z step would reorder the compositing.
        torch.cat([xy, 4.0 + 0.4 * torch.rand(n_s, 1, generator=g)], 1),
        torch.full((n_s, 3), 0.1),
        torch.full((n_s,), 0.9),
        torch.rand(n_s, 3, generator=g),
    )
    obj = torch.randn(n_d, 3, generator=g) * torch.tensor([0.12, 0.12, 0.05]) + torch.tensor([-0.3, 0.0, 2.5])
    obj_col = torch.tensor([0.9, 0.2, 0.1]).repeat(n_d, 1)
    K = torch.tensor([[40.0, 0, (W - 1) / 2], [0, 40.0, (H - 1) / 2], [0, 0, 1]])
    Ks = K[None].repeat(T, 1, 1)
    w2cs = torch.eye(4)[None].repeat(T, 1, 1)
    w2cs[:, 0, 3] = torch.linspace(-0.1, 0.1, T)
    imgs, depth = [], []
    with torch.no_grad():
        for t in range(T):
            m = torch.cat([static.means, obj + t * VEL])
            q = torch.cat([static.quats, torch.tensor([[1.0, 0, 0, 0]]).repeat(n_d, 1)])
            ls = torch.cat([static.log_scales, torch.full((n_d, 3), float(np.log(0.06)))])
            o = torch.cat([static.opacities, torch.full((n_d,), 0.95)])
            c = torch.cat([static.colors, obj_col])
            out = rasterize(m, q, ls, o, c, K, w2cs[t], W, H)
            imgs.append(out.rgb.clamp(0, 1))
            depth.append(out.depth / out.alpha.clamp_min(1e-6))
    # Scaffold from the true object trajectories (a few tracked points).
    traj = obj[:12][None] + torch.arange(T).float()[:, None, None] * VEL
    scf = build_scaffold(traj, torch.ones(T, 12, dtype=torch.bool), 4.0, ScaffoldConfig(knn_k=8))
    # Dynamic Gaussians: the object at frame 2, grey (the fit must learn its colour).
    dyn = DynamicGaussians.from_points_at(
        obj + 2 * VEL, torch.full((n_d, 3), 0.5), torch.full((n_d,), 2), init_opacity=0.9, skin_k=scf.K
    )
    return torch.stack(imgs), torch.stack(depth), Ks, w2cs, static, dyn, scf


def test_dynamic_gaussians_follow_a_rigid_scaffold_motion():
    _, _, _, _, _, dyn, scf = scene()
    for t in range(T):
        m, q = dyn.at(scf, t, dyn.attach(scf))
        # Every node translates by VEL per frame: the Gaussians must do exactly the same.
        torch.testing.assert_close(m, dyn.means + (t - 2) * VEL, atol=1e-4, rtol=0)
        torch.testing.assert_close(q.abs(), dyn.quats.abs(), atol=1e-4, rtol=0)


def test_ssi_depth_is_invariant_to_scale_and_shift():
    g = torch.Generator().manual_seed(0)
    d = torch.rand(20, 30, generator=g) + 1.0
    alpha = torch.ones(20, 30)
    assert float(ssi_depth_l1(d * alpha, alpha, 3.0 * d + 0.7)) < 1e-5
    assert float(ssi_depth_l1(d * alpha, alpha, torch.rand(20, 30, generator=g) + 1.0)) > 0.1


def test_anchored_depth_l1_closed_form_and_edge_cases():
    g = torch.Generator().manual_seed(1)
    anchor = torch.rand(6, 8, generator=g) + 1.0
    alpha = torch.full((6, 8), 0.8)
    weight = torch.zeros(6, 8)
    weight[:3] = 1.0  # the top half counts, the bottom half not at all
    # 10 % too far everywhere: 0.1 over the weighted half, divided by every pixel -> 0.05.
    far = 1.1 * anchor * alpha
    assert abs(float(anchored_depth_l1(far, alpha, anchor, weight)) - 0.05) < 1e-6
    # Exactly on the anchor, or all weights zero: no cost.
    assert float(anchored_depth_l1(anchor * alpha, alpha, anchor, weight)) < 1e-7
    assert float(anchored_depth_l1(far, alpha, anchor, torch.zeros(6, 8))) == 0.0
    # Pixels the anchor does not cover (0, negative, NaN, Inf) and transparent pixels count 0, and stay finite.
    bad = anchor.clone()
    bad[0, :2], bad[1, :2], bad[2, :2] = 0.0, float("nan"), float("inf")
    bad[0, 2] = -1.0
    thin = alpha.clone()
    thin[1, 3:] = 0.0  # behind no Gaussian: alpha 0, depth 0
    depth = (far * thin / alpha).requires_grad_(True)
    loss = anchored_depth_l1(depth, thin, bad, weight)
    counted = 24 - 7 - 5  # the weighted half less the 7 bad anchors and the 5 transparent pixels
    assert abs(float(loss) - 0.1 * counted / 48) < 1e-6
    loss.backward()
    assert torch.isfinite(depth.grad).all()
    assert float(depth.grad[3:].abs().sum()) == 0.0 and float(depth.grad[0, :3].abs().sum()) == 0.0


def test_anchored_depth_l1_gradient_matches_finite_differences():
    g = torch.Generator().manual_seed(2)
    anchor = torch.rand(5, 7, generator=g, dtype=torch.float64) + 1.0
    alpha = torch.rand(5, 7, generator=g, dtype=torch.float64) * 0.4 + 0.6
    weight = torch.rand(5, 7, generator=g, dtype=torch.float64)
    # Depths kept off the anchor (|d - a| has no kink within the finite-difference step).
    depth = (anchor * (1.0 + 0.3 * torch.sign(torch.randn(5, 7, generator=g, dtype=torch.float64))) * alpha)
    depth.requires_grad_(True)
    anchored_depth_l1(depth, alpha, anchor, weight).backward()
    eps = 1e-6
    for idx in [(0, 0), (2, 3), (4, 6)]:
        up, down = depth.detach().clone(), depth.detach().clone()
        up[idx] += eps
        down[idx] -= eps
        fd = (anchored_depth_l1(up, alpha, anchor, weight) - anchored_depth_l1(down, alpha, anchor, weight)) / (2 * eps)
        assert abs(float(fd) - float(depth.grad[idx])) < 1e-8


def test_photometric_fit_learns_the_object_and_moves_the_scaffold():
    imgs, depth, Ks, w2cs, static, dyn, scf = scene()
    # Density control on the dynamic set only (the static one is already right in this scene).
    off = DensifyStrategy(refine_start=1000, refine_stop=1000, reset_every=0)
    strat = DensifyStrategy(refine_start=30, refine_stop=70, refine_every=30, reset_every=0)
    cfg = PhotometricConfig(
        steps=80,
        camera_start_step=40,
        track_every=0,
        static_strategy=off,
        dynamic_strategy=strat,
        lr_sh0=0.03,  # grey -> red within 80 steps
    )
    fit = PhotometricFit(cfg, imgs, depth, Ks, w2cs, static, dyn, scf, None, None, extent=1.0)
    pos0 = fit.scaffold.pos.detach().clone()

    @torch.no_grad()
    def l1_all():
        return float(np.mean([float((fit.render(Ks[i], fit.camera(i), W, H, i).rgb - imgs[i]).abs().mean())
                              for i in range(T)]))  # fmt: skip

    before = l1_all()
    # One step by hand: gradients reach the scaffold and the dynamic colours.
    out = fit.training_step(1)
    out.loss.backward()
    assert fit.scaffold.pos.grad is not None and float(fit.scaffold.pos.grad.abs().sum()) > 0
    assert float(fit.dynamic.params["sh0"].grad.abs().sum()) > 0
    assert fit.cam_xi.grad is not None
    fit.optimizer_step(1, out)
    Trainer(TrainerConfig(steps=cfg.steps, checkpoint_every=0), fit, progress=False).fit(resume=False)
    after = l1_all()
    assert after < 0.7 * before, (before, after)
    assert len(fit.dynamic) > 60  # the dynamic set was densified...
    assert set(fit.dynamic.t_ref.tolist()) == {2}  # ...and its new members kept their reference frame
    red = fit.dynamic.colors.mean(0)
    assert red[0] > red[1] + 0.2  # learned the object's red
    assert not torch.equal(fit.scaffold.pos.detach(), pos0)
    assert torch.isfinite(fit.cameras()).all()
    # Camera 0 is the gauge; the others moved only after camera_start_step (and stay near the start).
    torch.testing.assert_close(fit.cameras()[0], w2cs[0])


def test_track_loss_is_small_for_true_tracks():
    imgs, depth, Ks, w2cs, static, dyn, scf = scene()
    # True tracks of object points: projections of their trajectories.
    pts = dyn.means.detach()[:20] - 2 * VEL
    tracks = []
    for t in range(T):
        cam = (pts + t * VEL) @ w2cs[t][:3, :3].T + w2cs[t][:3, 3]
        uv = cam[:, :2] / cam[:, 2:] * 40.0 + torch.tensor([(W - 1) / 2, (H - 1) / 2])
        tracks.append(uv)
    tracks = torch.stack(tracks)
    vis = torch.ones(T, 20, dtype=torch.bool)
    fit = PhotometricFit(
        PhotometricConfig(steps=1), imgs, depth, Ks, w2cs, static, dyn, scf, tracks, vis, 1.0
    )
    good = fit.track_loss(1)
    wrong = tracks.clone()
    wrong[torch.arange(T) != 1] += torch.tensor([6.0, 0.0])  # targets in every other frame 6 px off
    fit_bad = PhotometricFit(
        PhotometricConfig(steps=1), imgs, depth, Ks, w2cs, static, dyn, scf, wrong, vis, 1.0
    )
    bad = fit_bad.track_loss(1)
    assert good is not None and bad is not None
    assert float(good.detach()) < 1.5 and 4.5 < float(bad.detach()) < 7.5


def test_scaffold_fit_smooths_noise_and_keeps_observations():
    from worldtree.stages.scaffold_fit import ScaffoldFitConfig, fit_scaffold

    g = torch.Generator().manual_seed(5)
    T_, M = 12, 10
    base = torch.randn(M, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 3.0])
    truth = base[None] + torch.arange(T_).float()[:, None, None] * torch.tensor([0.05, 0.0, 0.0])
    noisy = truth + torch.randn(T_, M, 3, generator=g) * 0.01
    obs = torch.ones(T_, M, dtype=torch.bool)
    scf = build_scaffold(noisy, obs, 3.0, ScaffoldConfig(knn_k=6, node_spacing_units=0.1))
    assert scf.M == M
    order = torch.cdist(scf.pos[0].detach(), noisy[0]).argmin(1)  # node -> track
    err0 = float((scf.pos.detach() - truth[:, order]).norm(dim=-1).mean())
    logged = []
    hist = fit_scaffold(scf, noisy[:, order], obs, ScaffoldFitConfig(steps=150, lr_pos=0.2), on_log=logged.append)
    err1 = float((scf.pos.detach() - truth[:, order]).norm(dim=-1).mean())
    assert hist and all(np.isfinite(h["motion"]) for h in hist)
    assert [h["step"] for h in hist] == [0, 100, 149] and logged == hist  # progress sees each record once
    assert err1 < err0, (err0, err1)  # closer to the smooth truth than the noisy observations were
    assert err1 < 0.03  # and nowhere near diverging


def test_scaffold_nodes_are_densified_for_far_dynamic_gaussians():
    imgs, depth, Ks, w2cs, static, dyn, scf = scene()
    # A second cluster of dynamic Gaussians 0.8 units from every node (the 5-unit threshold is 0.2 here).
    far = dyn.means.detach()[:20] + torch.tensor([0.8, 0.0, 0.0])
    both = DynamicGaussians.from_points_at(
        torch.cat([dyn.means.detach(), far]),
        torch.full((80, 3), 0.5),
        torch.full((80,), 2),
        0.9,
        skin_k=scf.K,
    )
    off = DensifyStrategy(refine_start=1000, refine_stop=1000, reset_every=0)
    cfg = PhotometricConfig(
        steps=6, camera_start_step=100, track_every=0, static_strategy=off, dynamic_strategy=off,
        node_densify_start=2, node_densify_stop=4, node_densify_every=2,
    )  # fmt: skip
    fit = PhotometricFit(cfg, imgs, depth, Ks, w2cs, static, both, scf, None, None, extent=1.0)
    M0 = fit.scaffold.M
    for step in (1, 2):
        out = fit.training_step(step)
        out.loss.backward()
        if step == 2:  # Adam's first moment after this step, for the nodes that exist now
            m1 = fit.other_opt.optimizer.state[fit.scaffold.pos]["exp_avg"]
            moments = 0.9 * m1 + 0.1 * fit.scaffold.pos.grad
        fit.optimizer_step(step, out)
    M1 = fit.scaffold.M
    assert M0 < M1 <= M0 + scf.cfg.densify_max_new
    # Each new node sits on a dynamic Gaussian at its reference frame, and the far cluster got nodes.
    new_at_ref = fit.scaffold.pos.detach()[2, M0:]
    assert float(torch.cdist(new_at_ref, both.means.detach()).min(1).values.max()) < 1e-3
    assert float(torch.cdist(far, new_at_ref).min(1).values.max()) < 0.2
    # Adam moments follow the kept nodes; new nodes start from zero; the optimiser holds the new tensors.
    st = fit.other_opt.optimizer.state[fit.scaffold.pos]
    torch.testing.assert_close(st["exp_avg"][:, :M0], moments)
    assert float(st["exp_avg"][:, M0:].abs().sum()) == 0.0
    assert fit.other_opt.group("node_pos")["params"][0] is fit.scaffold.pos
    # Far Gaussians are now attached to one of the new nodes (before, to a node 0.8 units away).
    cache = fit.dynamic.attach(fit.scaffold)
    assert bool((cache.attach[60:] >= M0).all())
    # Training goes on with finite losses and gradients on the new nodes; a checkpoint round trip keeps M.
    for step in range(3, 7):
        out = fit.training_step(step)
        assert torch.isfinite(out.loss)
        out.loss.backward()
        assert torch.isfinite(fit.scaffold.pos.grad).all()
        fit.optimizer_step(step, out)
    assert fit.scaffold.M >= M1
    state = fit.state_dict()
    fit2 = PhotometricFit(cfg, imgs, depth, Ks, w2cs, static, both, scf, None, None, extent=1.0)
    fit2.load_state_dict(state)
    assert fit2.scaffold.M == fit.scaffold.M
    torch.testing.assert_close(fit2.scaffold.pos.detach(), fit.scaffold.pos.detach())


def test_node_densification_off_keeps_the_scaffold():
    imgs, depth, Ks, w2cs, static, dyn, scf = scene()
    off = DensifyStrategy(refine_start=1000, refine_stop=1000, reset_every=0)
    cfg = PhotometricConfig(
        steps=4, track_every=0, static_strategy=off, dynamic_strategy=off, node_densify_every=0
    )
    far = DynamicGaussians.from_points_at(
        dyn.means.detach() + torch.tensor([0.8, 0.0, 0.0]), torch.full((60, 3), 0.5), torch.full((60,), 2), 0.9,
        skin_k=scf.K,
    )  # fmt: skip
    fit = PhotometricFit(cfg, imgs, depth, Ks, w2cs, static, far, scf, None, None, extent=1.0)
    Trainer(TrainerConfig(steps=4, checkpoint_every=0), fit, progress=False).fit(resume=False)
    assert fit.scaffold.M == scf.M


def test_motion_window_regularises_a_seeded_slice_of_frames():
    from worldtree.motion.regularizers import motion_losses

    imgs, depth, Ks, w2cs, static, dyn, scf = scene()
    # Make the node trajectories non-rigid so every motion term is non-zero and frame-dependent.
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        scf.pos.add_(torch.randn(scf.pos.shape, generator=g) * 0.05 * torch.arange(T).float()[:, None, None])
    cfg = PhotometricConfig(steps=10, track_every=0, lambda_depth=0.0, motion_window=3)
    fit = PhotometricFit(cfg, imgs, depth, Ks, w2cs, static, dyn, scf, None, None, extent=1.0, seed=4)
    starts = set()
    for step in range(1, 9):
        w = fit._motion_window(step)
        assert w.stop - w.start == 3 and 0 <= w.start <= T - 3
        assert w == fit._motion_window(step)  # a function of (seed, step): resumes repeat it
        starts.add(w.start)
        _, parts, _ = fit.frame_losses(0, step)
        pos, quat = scf.pos.detach()[w], scf.quat.detach()[w]
        expect = motion_losses(pos, quat, scf.arap_graphs(), cfg.motion).total
        assert abs(parts["motion"] - float(expect)) < 1e-5
    assert len(starts) > 1
    full = PhotometricFit(
        PhotometricConfig(steps=10, track_every=0, motion_window=0), imgs, depth, Ks, w2cs, static, dyn, scf,
        None, None, extent=1.0,
    )  # fmt: skip
    _, parts, _ = full.frame_losses(0, 1)
    assert (
        abs(
            parts["motion"]
            - float(motion_losses(scf.pos.detach(), scf.quat.detach(), scf.arap_graphs()).total)
        )
        < 1e-5
    )


def test_prune_negligible_keeps_every_contributing_gaussian():
    imgs, depth, Ks, w2cs, static, dyn, scf = scene()
    # 20 static Gaussians behind the camera and 20 nearly transparent ones: nothing any frame sees.
    g = torch.Generator().manual_seed(3)
    extra_m = torch.cat([torch.rand(20, 3, generator=g) - torch.tensor([0.5, 0.5, 3.0]),
                         torch.rand(20, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 3.0])])  # fmt: skip
    extra_o = torch.cat([torch.full((20,), 0.9), torch.full((20,), 1e-4)])
    extra = GaussianSet.from_tensors(
        extra_m, torch.full((40, 3), 0.05), extra_o, torch.rand(40, 3, generator=g)
    )
    both = GaussianSet({k: torch.cat([static.params[k], extra.params[k]]) for k in static.params})
    cfg = PhotometricConfig(steps=10, track_every=0)
    fit = PhotometricFit(cfg, imgs, depth, Ks, w2cs, both, dyn, scf, None, None, extent=1.0)
    n_s = len(fit.static)
    # Brute force: each static Gaussian's total weight per frame from a one-hot red render, largest frame.
    brute = torch.zeros(n_s)
    with torch.no_grad():
        for i in range(T):
            m, q, ls, o, _ = fit.gaussians_at(i)
            for k in range(n_s):
                col = torch.zeros_like(m)
                col[k, 0] = 1.0
                w = float(rasterize(m, q, ls, o, col, Ks[i], w2cs[i], W, H).rgb[..., 0].sum())
                brute[k] = max(brute[k], w)
    before = fit.residuals().mean()
    rep = fit.prune_negligible(1.0)
    kept = int((brute >= 1.0).sum())
    assert rep["static_before"] == n_s and rep["static_after"] == kept
    assert rep["static_after"] <= n_s - 40  # the 40 unseen ones went
    l1 = fit.residuals().mean()
    assert abs(float(l1 - before)) < 0.01  # what went was negligible
    caps = fit.set_budget(10)
    assert caps["static_cap"] == len(fit.static) and caps["dynamic_cap"] == len(fit.dynamic)  # never below
    assert fit.cfg.static_strategy.max_gaussians == len(fit.static)


def test_resumed_fit_keeps_the_skinning_cache_and_ends_identical(tmp_path):
    """Skinning neighbourhoods are recomputed only every ``reattach_every`` steps: a fit resumed from a
    checkpoint whose nodes have moved since the last reattachment must go on with the cache in use, not
    one recomputed from the moved nodes, to end bit-identical to the uninterrupted fit."""
    from worldtree.checkpoint import load_checkpoint

    def make():
        imgs, depth, Ks, w2cs, static, dyn, scf = scene()
        # Large node steps so the nearest node of some Gaussians changes within a few steps.
        cfg = PhotometricConfig(steps=8, track_every=0, lr_node_pos=0.05, reattach_every=1000)
        return PhotometricFit(cfg, imgs, depth, Ks, w2cs, static, dyn, scf, None, None, extent=1.0, seed=2)

    def train(fit, folder):
        Trainer(TrainerConfig(steps=8, checkpoint_every=4), fit, checkpoint_dir=folder, progress=False,
                generators={"frame_order": fit.order}).fit(resume=True)  # fmt: skip

    full = make()
    train(full, tmp_path / "a")
    part = make()
    train(part, tmp_path / "b")
    (tmp_path / "b" / "ckpt_0000008.pt").unlink()
    # The case this test is about: the checkpoint's nodes give other neighbourhoods than the cache in use.
    state = load_checkpoint(tmp_path / "b" / "ckpt_0000004.pt")["task"]
    probe = make()
    probe.load_state_dict(state)
    fresh = probe.dynamic.attach(probe.scaffold)
    assert not torch.equal(fresh.attach, state["cache"]["attach"])
    resumed = make()
    train(resumed, tmp_path / "b")
    for k in ("means", "quats", "skin_corr"):
        assert torch.equal(full.dynamic.params[k], resumed.dynamic.params[k]), k
    assert torch.equal(full.static.params["means"], resumed.static.params["means"])
    assert torch.equal(full.scaffold.pos, resumed.scaffold.pos)


def test_deferred_dynamic_prune_keeps_the_dynamic_set():
    imgs, depth, Ks, w2cs, static, dyn, scf = scene()
    fit = PhotometricFit(PhotometricConfig(steps=10, track_every=0), imgs, depth, Ks, w2cs, static, dyn, scf,
                         None, None, extent=1.0)  # fmt: skip
    n_s, n_d = len(fit.static), len(fit.dynamic)
    assert n_s > 0 and n_d > 0
    # The background kept whole (a tree child's): only the dynamic set goes.
    rep = fit._prune_with(fit.contributions(), 1e12, dynamic=True, static=False)
    assert rep == {"static_before": n_s, "dynamic_before": n_d, "static_after": n_s, "dynamic_after": 0}
    imgs, depth, Ks, w2cs, static, dyn, scf = scene()  # the sets are pruned in place: fresh ones
    fit = PhotometricFit(PhotometricConfig(steps=10, track_every=0), imgs, depth, Ks, w2cs, static, dyn, scf,
                         None, None, extent=1.0)  # fmt: skip
    # A threshold above every contribution: the static set goes, the deferred dynamic set stays whole.
    rep = fit._prune_with(fit.contributions(), 1e12, dynamic=False)
    assert rep == {"static_before": n_s, "dynamic_before": n_d, "static_after": 0, "dynamic_after": n_d}
    rep = fit._prune_with(fit.contributions(), 1e12, dynamic=True)
    assert rep["dynamic_after"] == 0


def test_prune_total_cap_bounds_what_one_pruning_removes():
    imgs, depth, Ks, w2cs, static, dyn, scf = scene()
    fit = PhotometricFit(PhotometricConfig(steps=10, track_every=0), imgs, depth, Ks, w2cs, static, dyn, scf,
                         None, None, extent=1.0)  # fmt: skip
    contrib = fit.contributions()
    n = len(fit.static) + len(fit.dynamic)
    total = 0.02 * H * W
    rep = fit.prune_negligible(1e12, total_frac=0.02)  # everything is "negligible": only the total limits it
    removed = n - rep["static_after"] - rep["dynamic_after"]
    smallest = torch.sort(contrib[:n]).values
    expect = int((torch.cumsum(smallest.double(), 0) <= total).sum())
    assert removed == expect and 0 < removed < n


def test_track_loss_on_the_steps_frame_equals_a_second_motion_evaluation():
    # frame_losses hands its frame's Gaussians to the track loss instead of evaluating the motion model again:
    # the same loss and the same gradient in every parameter as the track loss evaluating them itself.
    imgs, depth, Ks, w2cs, static, dyn, scf = scene()
    pts = dyn.means.detach()[:20] - 2 * VEL
    tracks = []
    for t in range(T):  # the object points' projections, 3 px off
        cam = (pts + t * VEL) @ w2cs[t][:3, :3].T + w2cs[t][:3, 3]
        tracks.append(cam[:, :2] / cam[:, 2:] * 40.0 + torch.tensor([(W - 1) / 2 + 3.0, (H - 1) / 2]))
    tracks = torch.stack(tracks)
    vis = torch.ones(T, 20, dtype=torch.bool)
    fit = PhotometricFit(PhotometricConfig(steps=1), imgs, depth, Ks, w2cs, static, dyn, scf, tracks, vis, 1.0)
    params = [*fit.static.params.values(), fit.dynamic.params["means"], fit.dynamic.params["sh0"], fit.scaffold.pos]
    params = [p for p in params if p.requires_grad]
    state = fit.pairs.get_state()
    results = []
    for shared in (True, False):
        fit.pairs.set_state(state)  # the same random partner frame j
        loss = fit.track_loss(1, fit.gaussians_at(1) if shared else None)
        assert loss is not None
        results.append([loss.detach(), *torch.autograd.grad(loss, params, allow_unused=True)])
    for a, b in zip(*results, strict=True):
        if b is None:
            assert a is None
        else:
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)
    assert results[0][0] > 0 and any(g is not None and g.abs().sum() > 0 for g in results[0][1:])
