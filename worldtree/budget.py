"""Gaussian budget: how many Gaussians a model may grow to, and which ones contribute nothing.

**Contribution.** The rasterizer composites a pixel as ``C = sum_i w_i c_i + T_final * background`` with
blending weights ``w_i = alpha_i prod_{j<i} (1 - alpha_j)``. The derivative of the rendered image with respect
to a Gaussian's colour is therefore its weight, so ``d(sum over pixels of C_red) / d c_i,red = sum_px w_i``:
one backward pass through the renderer itself (any backend) gives every Gaussian's total weight in a view,
in pixels of full coverage. The *contribution* of a Gaussian over a set of training views is the largest of
its per-view totals (:func:`render_contributions`).

**Why that threshold is safe.** Removing Gaussian ``i`` changes a pixel by ``w_i (c_i - C_behind)``, whose size
is at most ``w_i`` for colours in [0, 1]; so over a view the image changes by at most ``sum_px w_i`` (L1 summed
over the pixels, per channel). A Gaussian whose contribution is below ``prune_contribution`` (default 1.0,
one pixel's worth) changes no training view by more than one pixel of colour in total: it is *negligible*.
Pruning (:func:`negligible`) removes only those, never one at or above the threshold, and at most as many
(smallest first) as keep their summed contributions within ``prune_total_frac`` of a view's pixels (1 %).

**Inherited Gaussians recover first.** A tree child inherits its parent's dynamic Gaussians with their
opacity reset low (``inherit_opacity``, 0.05): right after inheritance most of them are below the threshold
only because of the reset. Their post-training pruning is therefore deferred (:func:`inherited_prune_due`)
until the node has trained ``prune_min_epochs`` passes over its frames; a node that stopped earlier keeps
them (the pruning at inheritance, with the parent's opacities, has already removed what its frames do not
see).

**Budget.** A model's Gaussians are capped at growth time (``DensifyStrategy.max_gaussians``) by
:func:`node_budget`: ``gaussians_per_pixel * H * W * clamp(error / error_ref, min_scale, 1)``, the pixels of
one of its views scaled down when its photometric error is already low (an easy node gets less), or a fixed
``override``. The cap only stops growth (:func:`growth_cap` never goes below the current count), so the budget
never removes a Gaussian either.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from worldtree.render import rasterize

__all__ = [
    "BudgetConfig",
    "growth_cap",
    "inherited_prune_due",
    "negligible",
    "node_budget",
    "render_contributions",
    "total_px",
]

GaussiansFn = Callable[[int], tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]
"""``fn(t) -> (means [N,3], quats [N,4], log_scales [N,3], opacities [N], colors [N,3])`` at frame ``t``."""


@dataclass(frozen=True)
class BudgetConfig:
    """Gaussian budget and pruning settings (see the module docstring)."""

    enabled: bool | None = None
    """Apply the budget and contribution pruning; None: only with WorldTree's ``--depth auto`` (off: the fixed
    caps of the preset)."""
    gaussians_per_pixel: float = 2.0
    """Growth cap per pixel of one view at full error."""
    error_ref: float = 0.05
    """Mean L1 photometric error (colour units) at which the full per-pixel budget is granted."""
    min_scale: float = 0.25
    """Smallest fraction of the full budget (however low the error)."""
    override: int | None = None
    """A fixed budget instead of the derived one."""
    prune_contribution: float = 1.0
    """A Gaussian whose total blending weight stays below this (pixels) in every training view is removed."""
    prune_total_frac: float = 0.01
    """One pruning removes Gaussians (smallest contribution first) only while their contributions add up to at
    most this fraction of a view's pixels: each one alone changes a view by less than ``prune_contribution``, but
    thousands together (small images, many Gaussians) can change it a lot. The sum is a first-order bound on
    the total change of any training view (exact for Gaussians that do not overlap; a removed Gaussian lets the
    ones behind it show through more)."""
    prune_min_epochs: float = 10.0
    """Inherited (opacity-reset) dynamic Gaussians are pruned after training only once the node has trained at
    least this many passes over its frames (:func:`inherited_prune_due`)."""

    def __post_init__(self) -> None:
        if not (self.gaussians_per_pixel > 0 and self.error_ref > 0 and 0 < self.min_scale <= 1):
            raise ValueError(
                "BudgetConfig needs gaussians_per_pixel > 0, error_ref > 0 and 0 < min_scale <= 1, got "
                f"{self.gaussians_per_pixel}, {self.error_ref}, {self.min_scale}"
            )
        if self.override is not None and self.override < 1:
            raise ValueError(f"BudgetConfig.override must be >= 1, got {self.override}")
        if not self.prune_contribution >= 0:
            raise ValueError(f"BudgetConfig.prune_contribution must be >= 0, got {self.prune_contribution}")
        if not 0 <= self.prune_total_frac:
            raise ValueError(f"BudgetConfig.prune_total_frac must be >= 0, got {self.prune_total_frac}")
        if not self.prune_min_epochs >= 0:
            raise ValueError(f"BudgetConfig.prune_min_epochs must be >= 0, got {self.prune_min_epochs}")


def node_budget(width: int, height: int, error: float, cfg: BudgetConfig) -> int:
    """Gaussians a model of ``width x height`` views with mean L1 ``error`` may grow to (>= 1).

    A non-finite error counts as the reference error (full budget).
    """
    if cfg.override is not None:
        return int(cfg.override)
    e = float(error) if math.isfinite(float(error)) else cfg.error_ref
    scale = min(1.0, max(cfg.min_scale, e / cfg.error_ref))
    return max(1, math.ceil(cfg.gaussians_per_pixel * int(width) * int(height) * scale))


def inherited_prune_due(steps: int, frames: int, cfg: BudgetConfig) -> bool:
    """Whether a node that trained ``steps`` steps (one frame each) over ``frames`` frames may prune the
    dynamic Gaussians it inherited with a reset opacity: ``steps / frames >= cfg.prune_min_epochs``."""
    return int(steps) >= cfg.prune_min_epochs * max(int(frames), 1)


def growth_cap(budget: int, current: int) -> int:
    """``DensifyStrategy.max_gaussians`` for a set holding ``current`` Gaussians: the budget, but never below
    what it holds (the cap stops growth; it does not remove anything)."""
    return max(int(budget), int(current), 1)


def render_contributions(
    gaussians_at: GaussiansFn,
    views: Sequence[tuple[int, torch.Tensor, torch.Tensor]],
    width: int,
    height: int,
    backend: str = "auto",
) -> torch.Tensor:
    """``[N]`` contribution of every Gaussian: the largest over ``views`` of its summed blending weights.

    Args:
        gaussians_at: the rendered Gaussians at frame ``t`` (see :data:`GaussiansFn`); N must not change
            between frames.
        views: ``(t, K [3,3], w2c [4,4])`` per training view.
        width, height: image size in pixels.
        backend: rasterizer backend.

    The weights are the renderer's own (one backward pass per view through :func:`worldtree.render.rasterize`
    with unit colours); non-finite values count as 0.
    """
    best: torch.Tensor | None = None
    for t, K, w2c in views:
        with torch.no_grad():
            m, q, ls, o, _ = (x.detach() for x in gaussians_at(int(t)))
        if m.shape[0] == 0:
            return torch.zeros(0, device=m.device)
        col = torch.ones_like(m).requires_grad_(True)
        with torch.enable_grad():
            out = rasterize(m, q, ls, o, col, K, w2c, width, height, backend=backend)
            (g,) = torch.autograd.grad(out.rgb[..., 0].sum(), [col], allow_unused=True)
        w = torch.zeros(m.shape[0], device=m.device) if g is None else g[:, 0].detach()
        w = torch.where(torch.isfinite(w), w, torch.zeros_like(w)).clamp_min(0.0)
        best = w if best is None else torch.maximum(best, w)
    if best is None:
        raise ValueError("render_contributions needs at least one view")
    return best


def negligible(contribution: torch.Tensor, threshold: float, total: float | None = None) -> torch.Tensor:
    """``[N]`` bool: the Gaussians to prune, strictly below ``threshold`` each; with ``total``, only the
    smallest of them whose contributions add up to at most ``total`` (see ``BudgetConfig.prune_total_frac``)."""
    below = contribution < float(threshold)
    if total is None or not bool(below.any()):
        return below
    vals = torch.where(below, contribution, torch.full_like(contribution, float("inf")))
    order = torch.argsort(vals, stable=True)
    within = torch.cumsum(vals[order].double(), 0) <= float(total)
    out = torch.zeros_like(below)
    out[order[within]] = True
    return out & below


def total_px(cfg: BudgetConfig, width: int, height: int) -> float:
    """The summed contribution pruning may remove from a model of ``width x height`` views (pixels)."""
    return cfg.prune_total_frac * int(width) * int(height)
