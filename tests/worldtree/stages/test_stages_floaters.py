"""Static floaters: the photometric fit removes static Gaussians in front of the depth prior seen from the
training frames (closed-form placements on the tiny scene of the photometric tests)."""

from __future__ import annotations

import torch

from tests.worldtree.stages.test_stages_photometric import scene
from worldtree.gaussians import GaussianSet
from worldtree.stages.photometric import PhotometricConfig, PhotometricFit


def _with_floaters(static: GaussianSet, points: torch.Tensor) -> GaussianSet:
    """``static`` with Gaussians at ``points`` [K, 3] appended (small, opaque, grey)."""
    k = points.shape[0]
    extra = GaussianSet.from_tensors(
        points, torch.full((k, 3), 0.1), torch.full((k,), 0.9), torch.full((k, 3), 0.5)
    )
    return GaussianSet.from_tensors(
        torch.cat([static.means, extra.means]).detach(),
        torch.cat([static.scales, extra.scales]).detach(),
        torch.cat([static.opacities, extra.opacities]).detach(),
        torch.cat([static.colors, extra.colors]).detach(),
    )


def _fit(every: int, floaters: torch.Tensor):
    imgs, depth, Ks, w2cs, static, dyn, scf = scene()
    cfg = PhotometricConfig(steps=1, floater_every=every)
    return PhotometricFit(
        cfg, imgs, depth, Ks, w2cs, _with_floaters(static, floaters), dyn, scf, None, None, 1.0
    )


# In front of the sheet (z 4.0-4.4) and of the moving object (z ~2.5), inside every camera's view.
FLOATERS = torch.tensor([[0.3, 0.2, 1.0], [-0.5, -0.3, 0.8]])


def test_static_gaussians_in_front_of_the_depth_are_removed_and_the_sheet_kept():
    fit = _fit(100, FLOATERS)
    fit.training_step(0).loss.backward()
    fit.static_opt.step()  # Adam moments to carry
    assert len(fit.static_opt.optimizer.state) > 0
    n = len(fit.static)
    start = fit.cfg.static_strategy.refine_start
    assert fit._remove_floaters(start + 1) == 0  # not on its schedule
    assert fit._remove_floaters(start) == 2
    assert len(fit.static) == n - 2 and fit.floaters == 2
    # Exactly the two floaters went: every Gaussian left lies at the sheet's depth.
    assert float(fit.static.means[:, 2].detach().min()) >= 4.0
    # The optimiser's rows follow the Gaussians.
    for st in fit.static_opt.optimizer.state.values():
        for v in st.values():
            if torch.is_tensor(v) and v.dim() >= 1:
                assert v.shape[0] == len(fit.static)
    assert fit._remove_floaters(start + 100) == 0  # nothing left to remove


def test_off_before_the_density_control_and_when_switched_off():
    fit = _fit(100, FLOATERS)
    assert fit._remove_floaters(0) == 0
    fit = _fit(0, FLOATERS)
    assert fit._remove_floaters(fit.cfg.static_strategy.refine_start) == 0
    assert fit.floaters == 0


def test_a_static_gaussian_behind_the_sheet_is_occluded_not_removed():
    fit = _fit(100, torch.tensor([[0.1, 0.1, 6.0]]))
    assert fit._remove_floaters(fit.cfg.static_strategy.refine_start) == 0
