"""Gaussians move between the static and the dynamic set during the photometric fit (imperfect masks).

The dynamic masks decide which Gaussians start dynamic. A region the masks missed is fitted by static
Gaussians, which cannot follow it: they settle as a blur at the object's mean position and keep a high
photometric residual in every frame. A Gaussian wrongly made dynamic costs little, but one that never moves is
better static (no skinning, no drift). So, during the fit:

- every rendered step, each visible Gaussian accumulates the residual ``|render - image|`` (mean over
  channels, 3x3 box) at its projected centre, and the frame of its largest residual;
- every ``migrate_every`` steps within ``[migrate_start, migrate_stop]``: a **static** Gaussian seen in at least
  ``migrate_min_views`` renders whose mean residual exceeds ``migrate_residual`` becomes **dynamic**, with its
  reference frame the frame of its largest residual and a zero skinning correction (the scaffold then carries
  it); a **dynamic** Gaussian whose position moves less than ``static_move_frac * extent`` over the video and
  whose mean residual is below half of ``migrate_residual`` becomes **static** (at its reference position).

Moved Gaussians keep their parameters and start with zero Adam moments; the counts are recorded per run
(``method_stats.migration``). Needs a scaffold with nodes (nothing can move without one).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from worldtree.dynamic import TIME_STD, DynamicGaussians
from worldtree.gaussians import GaussianSet
from worldtree.motion.lift import project_points
from worldtree.optim import GroupedAdam
from worldtree.strategy import STATE_KEYS, remove

MIGRATED_TIME_STD = 1e3
"""Temporal std (frames) a static Gaussian gets when it becomes dynamic in a set with temporal opacity."""


class ResidualAccumulator:
    """Per-Gaussian residual statistics of one set (sum, count, largest value and its frame)."""

    def __init__(self, n: int, device: torch.device):
        self.sum = torch.zeros(n, device=device)
        self.count = torch.zeros(n, device=device)
        self.max = torch.full((n,), -1.0, device=device)
        self.frame = torch.zeros(n, dtype=torch.long, device=device)

    def __len__(self) -> int:
        return int(self.sum.shape[0])

    @torch.no_grad()
    def add(
        self,
        residual: torch.Tensor,
        means2d: torch.Tensor,
        radii: torch.Tensor,
        frame: int,
        front: torch.Tensor | None = None,
    ) -> None:
        """Add one render: ``residual`` [H, W], centres ``means2d`` [n, 2] px, ``radii`` [n] (0 = culled) and
        ``front`` [n] bool (not hidden behind the rendered surface; None = all)."""
        H, W = residual.shape
        x, y = means2d[:, 0].round().long(), means2d[:, 1].round().long()
        seen = (radii > 0) & (x >= 0) & (x < W) & (y >= 0) & (y < H)
        if front is not None:
            seen &= front
        r = residual[y.clamp(0, H - 1), x.clamp(0, W - 1)]
        self.sum += torch.where(seen, r, torch.zeros_like(r))
        self.count += seen.float()
        bigger = seen & (r > self.max)
        self.max = torch.where(bigger, r, self.max)
        self.frame = torch.where(bigger, torch.full_like(self.frame, frame), self.frame)

    def mean(self) -> torch.Tensor:
        return self.sum / self.count.clamp_min(1.0)


@torch.no_grad()
def in_front(
    means: torch.Tensor,
    K: torch.Tensor,
    w2c: torch.Tensor,
    depth: torch.Tensor,
    alpha: torch.Tensor,
    tol: float = 0.05,
) -> torch.Tensor:
    """``[n]`` bool: Gaussians whose centre (world ``means`` [n, 3]) is not behind the rendered surface
    ``depth / alpha`` ([H, W]) at its pixel by more than ``tol`` (relative); a hidden Gaussian's pixel shows
    something else, so its residual says nothing about it."""
    H, W = depth.shape
    uv, z = project_points(means, K, w2c)
    x = uv[:, 0].round().long().clamp(0, W - 1)
    y = uv[:, 1].round().long().clamp(0, H - 1)
    surf = (depth / alpha.clamp_min(1e-6))[y, x]
    return (z > 0) & (z <= surf * (1.0 + tol))


def residual_map(rgb: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """``[H, W]`` mean absolute colour residual, 3x3 box-filtered (one pixel's noise is not a region)."""
    r = (rgb.detach() - image).abs().mean(-1)
    return F.avg_pool2d(r[None, None], 3, stride=1, padding=1, count_include_pad=False)[0, 0]


@torch.no_grad()
def append(gaussians: GaussianSet, optimizer: GroupedAdam | None, state: dict, rows: dict) -> None:
    """Append Gaussians given as ``rows`` {param name: [k, ...]} (every parameter of the set); zero moments."""
    k = int(next(iter(rows.values())).shape[0])
    groups = set(optimizer.names) if optimizer is not None else set()
    for name in list(gaussians.params.keys()):
        old = gaussians.params[name]
        new = nn.Parameter(torch.cat([old.detach(), rows[name].to(old)]), requires_grad=old.requires_grad)
        gaussians.params[name] = new
        if name in groups:
            optimizer.replace_param(
                name, new, lambda _k, m, k=k: torch.cat([m, m.new_zeros((k, *m.shape[1:]))])
            )
    for key in STATE_KEYS:
        v = state.get(key)
        if isinstance(v, torch.Tensor):
            state[key] = torch.cat([v, v.new_zeros((k, *v.shape[1:]))])


def compatible(static: GaussianSet, dynamic: DynamicGaussians) -> bool:
    """Whether Gaussians can move between the two sets (same appearance parameters)."""
    extra = {"t_ref", "skin_corr", TIME_STD}
    return set(static.params.keys()) == set(dynamic.params.keys()) - extra


@torch.no_grad()
def static_to_dynamic(
    static: GaussianSet,
    static_opt,
    static_state,
    dynamic: DynamicGaussians,
    dyn_opt,
    dyn_state,
    mask: torch.Tensor,
    t_ref: torch.Tensor,
) -> int:
    """Move the static Gaussians in ``mask`` [Ns] to the dynamic set with reference frames ``t_ref`` [Ns]."""
    k = int(mask.sum())
    if k == 0:
        return 0
    rows = {n: static.params[n].detach()[mask] for n in static.params.keys()}
    rows["t_ref"] = t_ref[mask].long()
    if "skin_corr" in dynamic.params:
        rows["skin_corr"] = torch.zeros(k, dynamic.params["skin_corr"].shape[1], device=mask.device)
    if TIME_STD in dynamic.params:  # a static Gaussian was seen at every frame: start with no falloff
        rows[TIME_STD] = torch.full((k,), math.log(MIGRATED_TIME_STD), device=mask.device)
    append(dynamic, dyn_opt, dyn_state, rows)
    remove(static, static_opt, static_state, mask)
    return k


@torch.no_grad()
def dynamic_to_static(
    static: GaussianSet,
    static_opt,
    static_state,
    dynamic: DynamicGaussians,
    dyn_opt,
    dyn_state,
    mask: torch.Tensor,
) -> int:
    """Move the dynamic Gaussians in ``mask`` [Nd] to the static set (at their reference positions)."""
    k = int(mask.sum())
    if k == 0:
        return 0
    rows = {n: dynamic.params[n].detach()[mask] for n in static.params.keys()}
    append(static, static_opt, static_state, rows)
    remove(dynamic, dyn_opt, dyn_state, mask)
    return k


@torch.no_grad()
def max_displacement(dynamic: DynamicGaussians, scaffold, cache, frames: list[int]) -> torch.Tensor:
    """``[Nd]`` largest distance of each dynamic Gaussian from its reference position over ``frames``."""
    out = torch.zeros(len(dynamic), device=dynamic.means.device)
    for t in frames:
        m, _ = dynamic.at(scaffold, t, cache)
        out = torch.maximum(out, (m - dynamic.means).norm(dim=-1))
    return out
