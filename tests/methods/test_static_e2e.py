"""The static baseline learns the tiny analytic scene: its test-camera PSNR is well above the PSNR of the
mean-colour image (the best constant prediction from the training video)."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from skimage.metrics import peak_signal_noise_ratio

from methods.static3dgs import StaticConfig, StaticGaussians, scene_extent
from worldtree.checkpoint import seed_everything
from worldtree.pixels import unit_float
from worldtree.scene import load_scene
from worldtree.strategy import DensifyStrategy
from worldtree.trainer import TrainContext


def tiny_config(**kw) -> StaticConfig:
    """A few hundred steps on few Gaussians: enough to fit 64x36 images, small enough for CI."""
    base = StaticConfig(
        steps=250,
        init_num_points=400,
        strategy=DensifyStrategy(
            refine_start=100, refine_stop=200, refine_every=50, reset_every=0, max_gaussians=1500
        ),
        checkpoint_every=100,
    )
    return dataclasses.replace(base, **kw)


def test_static_psnr_well_above_mean_colour(tiny_scene):
    scene = load_scene(tiny_scene)
    seed_everything(0)
    model = StaticGaussians(tiny_config(), scene, torch.device("cpu"))
    n0 = len(model.gaussians)
    summary = model.fit(TrainContext(progress=False))
    assert summary.end_step == 250 and np.isfinite(summary.final_loss)
    assert len(model.gaussians) != n0, "density control should have changed the set"
    img = model.render(scene.test_K, scene.test_w2c, scene.width, scene.height, time=0).numpy()
    mean_img = np.broadcast_to(unit_float(scene.images).numpy().mean(axis=(0, 1, 2)), img.shape)
    gts = unit_float(scene.test_images).numpy()
    p_model = np.mean([peak_signal_noise_ratio(g, img, data_range=1.0) for g in gts])
    p_mean = np.mean([peak_signal_noise_ratio(g, mean_img, data_range=1.0) for g in gts])
    assert p_model > p_mean + 4.0, (p_model, p_mean)


def test_scene_extent_closed_form():
    w2cs = torch.eye(4).repeat(3, 1, 1)
    w2cs[:, :3, 3] = -torch.tensor([[0.0, 0, 0], [2.0, 0, 0], [1.0, 0, 0]])  # centres at x = 0, 2, 1
    assert abs(scene_extent(w2cs, 0.1, 1.0) - 1.1 * 1.0) < 1e-9
    # Coincident cameras fall back to a tenth of the mean depth.
    assert abs(scene_extent(torch.eye(4).repeat(2, 1, 1), 1.0, 9.0) - 1.1 * 0.5) < 1e-9


def test_static_budget_and_early_stop(tiny_scene):
    """Budget, pruning and early stop on the static baseline: the growth cap is the closed-form budget, every
    kept Gaussian contributes at least the threshold (a fresh contribution pass), the plateau rule's steps are
    recorded, and the fit still beats the mean colour."""
    from worldtree.budget import BudgetConfig, node_budget, render_contributions
    from worldtree.plateau import PlateauRule

    scene = load_scene(tiny_scene)
    seed_everything(0)
    # No total cap (tested in tests/worldtree/test_budget_prune.py): every negligible Gaussian goes.
    budget = BudgetConfig(enabled=True, prune_total_frac=1e9)
    cfg = tiny_config(budget=budget, early_stop=PlateauRule(enabled=True, min_window=10))
    model = StaticGaussians(cfg, scene, torch.device("cpu"))
    summary = model.fit(TrainContext(progress=False))
    ad = model.stats()["adaptive"]
    b = ad["budget"]
    assert b["budget"] == node_budget(scene.width, scene.height, b["error_start"], BudgetConfig())
    assert model.cfg.strategy.max_gaussians == b["cap"] >= 400
    assert ad["steps_taken"] == summary.end_step <= 250 and ad["steps_taken"] >= 200  # not before refine_stop
    assert ad["prune"]["after"] == len(model.gaussians) <= ad["prune"]["before"]
    gs = model.gaussians
    views = [(i, scene.Ks[i], scene.w2cs[i]) for i in range(scene.num_frames)]
    with torch.no_grad():
        contrib = render_contributions(
            lambda _t: (gs.means, gs.quats, gs.log_scales, gs.opacities, gs.colors),
            views,
            scene.width,
            scene.height,
        )
    assert bool((contrib >= 1.0 - 1e-3).all())
    img = model.render(scene.test_K, scene.test_w2c, scene.width, scene.height, time=0).numpy()
    mean_img = np.broadcast_to(unit_float(scene.images).numpy().mean(axis=(0, 1, 2)), img.shape)
    gts = unit_float(scene.test_images).numpy()
    p_model = np.mean([peak_signal_noise_ratio(g, img, data_range=1.0) for g in gts])
    p_mean = np.mean([peak_signal_noise_ratio(g, mean_img, data_range=1.0) for g in gts])
    assert p_model > p_mean + 4.0, (p_model, p_mean)
