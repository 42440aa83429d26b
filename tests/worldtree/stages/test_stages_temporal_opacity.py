"""Temporal opacity of dynamic Gaussians (``t_logstd``): closed form, migration, and the case it is for -- a
scaffold whose motion is wrong no longer smears every frame's Gaussians over the others."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import torch

from worldtree.dynamic import TIME_STD, DynamicGaussians, gaussians_at
from worldtree.gaussians import GaussianSet
from worldtree.motion.scaffold import ScaffoldConfig, build_scaffold
from worldtree.optim import GroupedAdam, gaussian_schedules
from worldtree.stages import set_migration as mig
from worldtree.stages.photometric import PhotometricConfig, PhotometricFit
from worldtree.strategy import DensifyStrategy
from worldtree.trainer import Trainer, TrainerConfig

sys.path.insert(0, str(Path(__file__).parent))
from test_stages_photometric import VEL, H, T, W, scene  # the tiny scene with a moving object


def test_opacity_falls_off_as_a_gaussian_in_time():
    g = torch.Generator().manual_seed(0)
    n = 7
    t_ref = torch.tensor([0, 1, 2, 3, 4, 2, 2])
    d = DynamicGaussians.from_points_at(torch.rand(n, 3, generator=g), torch.rand(n, 3, generator=g), t_ref,
                                        init_opacity=0.6, time_std=1.5)  # fmt: skip
    std = np.array([1.5, 1.5, 1.5, 1.5, 1.5, 0.5, 40.0])
    with torch.no_grad():
        d.params[TIME_STD].copy_(torch.tensor(np.log(std)))
    o = d.opacities.detach().numpy().astype(np.float64)
    for t in (0.0, 2.0, 2.5, 4.0, 7.25):
        want = o * np.exp(-((t - t_ref.numpy()) ** 2) / (2 * std**2))
        np.testing.assert_allclose(d.opacities_at(t).detach().numpy(), want, rtol=1e-5, atol=1e-7)
    # Without the entry the opacity does not change with time (the paper's model).
    plain = DynamicGaussians.from_points_at(torch.rand(n, 3, generator=g), torch.rand(n, 3, generator=g), t_ref)
    assert TIME_STD not in plain.params
    torch.testing.assert_close(plain.opacities_at(3.0), plain.opacities)
    # A runaway log std stays finite and differentiable.
    with torch.no_grad():
        d.params[TIME_STD].copy_(torch.tensor([-1e4, 1e4, 0, 0, 0, 0, 0], dtype=torch.float32))
    v = d.opacities_at(1.0)
    v.sum().backward()
    assert torch.isfinite(v).all() and torch.isfinite(d.params[TIME_STD].grad).all()


def test_a_static_gaussian_made_dynamic_stays_visible_at_every_frame():
    g = torch.Generator().manual_seed(1)
    static = GaussianSet.from_points(torch.rand(6, 3, generator=g), torch.rand(6, 3, generator=g), 0.7)
    dyn = DynamicGaussians.from_points_at(torch.rand(4, 3, generator=g), torch.rand(4, 3, generator=g),
                                          torch.zeros(4, dtype=torch.long), 0.5, skin_k=2, time_std=1.0)  # fmt: skip
    assert mig.compatible(static, dyn)
    s_opt = GroupedAdam(dict(static.params.items()), gaussian_schedules(1e-3, 1e-5, 10, 1e-3, 1e-3, 1e-2, 1e-3))
    d_sched = gaussian_schedules(1e-3, 1e-5, 10, 1e-3, 1e-3, 1e-2, 1e-3)
    d_sched.update({"skin_corr": lambda _s: 1e-3, TIME_STD: lambda _s: 1e-2})
    d_opt = GroupedAdam({k: dyn.params[k] for k in d_sched}, d_sched)
    st = DensifyStrategy().initialize_state(1.0)
    moved = torch.tensor([False, True, False, True, False, False])
    o_moved = static.opacities.detach()[moved].clone()
    assert mig.static_to_dynamic(static, s_opt, st, dyn, d_opt, dict(st), moved, torch.full((6,), 3)) == 2
    assert dyn.params[TIME_STD].shape == (6,)
    for t in (0, 3, 11):
        got = dyn.opacities_at(float(t)).detach()[4:]
        torch.testing.assert_close(got, o_moved * math.exp(-((t - 3) ** 2) / (2 * mig.MIGRATED_TIME_STD**2)))
        assert float((got / o_moved).min()) > 0.999


def _fit_with_a_frozen_wrong_scaffold(time_std: float) -> float:
    """Mean L1 over the frames after fitting per-frame dynamic Gaussians carried by a scaffold that holds
    still while the object moves by ``VEL`` per frame."""
    imgs, depth, Ks, w2cs, static, _, _ = scene()
    g = torch.Generator().manual_seed(2)
    obj = torch.randn(40, 3, generator=g) * torch.tensor([0.12, 0.12, 0.05]) + torch.tensor([-0.3, 0.0, 2.5])
    pts = torch.cat([obj + t * VEL for t in range(T)])
    frames = torch.arange(T).repeat_interleave(40)
    still = obj[:12][None].repeat(T, 1, 1)  # the scaffold's (wrong) motion: none
    scf = build_scaffold(still, torch.ones(T, 12, dtype=torch.bool), 4.0, ScaffoldConfig(knn_k=8))
    dyn = DynamicGaussians.from_points_at(pts, torch.full((len(pts), 3), 0.5), frames, init_opacity=0.9,
                                          skin_k=scf.K, time_std=time_std)  # fmt: skip
    off = DensifyStrategy(refine_start=1000, refine_stop=1000, reset_every=0)
    cfg = PhotometricConfig(steps=100, camera_start_step=1000, track_every=0, lambda_depth=0.0, lr_node_pos=0.0,
                            static_strategy=off, dynamic_strategy=off, lr_sh0=0.03, lr_time_std=0.05)  # fmt: skip
    fit = PhotometricFit(cfg, imgs, depth, Ks, w2cs, static, dyn, scf, None, None, extent=1.0)
    Trainer(TrainerConfig(steps=cfg.steps, checkpoint_every=0), fit, progress=False).fit(resume=False)
    with torch.no_grad():
        errs = [float((fit.render(Ks[i], fit.camera(i), W, H, i).rgb - imgs[i]).abs().mean()) for i in range(T)]
    return float(np.mean(errs))


def test_temporal_opacity_keeps_each_frame_sharp_under_a_wrong_scaffold():
    # Without it every frame shows the 5 frames' copies of the object smeared along its path; with it each
    # frame's own copy dominates. The object covers ~4% of the image and moves ~5 px per frame.
    plain, temporal = _fit_with_a_frozen_wrong_scaffold(0.0), _fit_with_a_frozen_wrong_scaffold(1.0)
    assert temporal < 0.75 * plain, (plain, temporal)


def test_gaussians_at_uses_the_opacity_of_the_frame():
    _, _, _, _, static, dyn, scf = scene()
    d = DynamicGaussians.from_points_at(dyn.means.detach(), dyn.colors.detach(), dyn.t_ref, 0.9,
                                        skin_k=scf.K, time_std=0.5)  # fmt: skip
    for t in range(T):
        o = gaussians_at(static, d, scf, t, d.attach(scf))[3][len(static):]
        want = d.opacities * torch.exp(torch.tensor(-((t - 2) ** 2) / (2 * 0.25)))
        torch.testing.assert_close(o, want)
