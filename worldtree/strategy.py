"""3DGS adaptive density control as a small strategy object with explicit running state.

:class:`DensifyStrategy` holds only hyperparameters. The caller keeps the running state, a dict made by
:meth:`DensifyStrategy.initialize_state`, and calls two hooks around each training step::

    state = strategy.initialize_state(scene_extent)
    out = rasterize(...)
    strategy.step_pre_backward(gaussians, optimizer, state, step, out)   # keeps the 2D-mean gradient
    loss.backward(); optimizer.step(); optimizer.zero_grad()
    strategy.step_post_backward(gaussians, optimizer, state, step, out)  # statistics, clone/split/prune/reset

The rules are those of 3D Gaussian Splatting (Kerbl et al. 2023), with 1-based steps:

- statistics while ``step < refine_stop``: for each Gaussian visible in the render, accumulate the norm of the
  gradient of its projected mean in NDC units (pixel gradient times ``(W/2, H/2)``) and count the views;
- every ``refine_every`` steps when ``refine_start < step < refine_stop``: Gaussians whose mean gradient is at
  least ``grow_grad2d`` are cloned if their largest scale is at most ``grow_scale3d * extent``, otherwise split
  into ``split_children`` children sampled from ``N(mean, Sigma)`` with scales divided by ``split_scale_div``
  (1.6 = 0.8 * 2); then Gaussians with opacity below ``prune_opacity`` are removed, and after the first
  opacity reset also those with a largest scale above ``prune_scale3d * extent`` (and, when enabled, a screen
  radius above ``prune_radius2d``); the statistics restart;
- every ``reset_every`` steps while ``step < refine_stop``: opacities are capped at ``reset_opacity``.

Every in-place operation (:func:`duplicate`, :func:`split`, :func:`remove`, :func:`reset_opacity`) updates the
parameters, their Adam moments and every per-Gaussian tensor of the state together: surviving Gaussians keep
their moments, new ones start from zero moments.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from worldtree.gaussians import GaussianSet, inverse_sigmoid, quat_to_rotmat
from worldtree.optim import GroupedAdam

STATE_KEYS = ("grad2d", "count", "radii")


@dataclass
class DensifyStrategy:
    """Hyperparameters of 3DGS density control (defaults: the 3DGS paper's 30k-step schedule)."""

    prune_opacity: float = 0.005
    """Remove Gaussians whose opacity is below this at each refinement."""
    grow_grad2d: float = 2e-4
    """Clone/split Gaussians whose mean NDC gradient norm of the projected mean is at least this."""
    grow_scale3d: float = 0.01
    """Clone when the largest scale is at most this fraction of the scene extent, else split."""
    prune_scale3d: float = 0.1
    """After the first opacity reset, remove Gaussians larger than this fraction of the scene extent."""
    prune_radius2d: float = 0.0
    """After the first opacity reset, remove Gaussians whose largest screen radius (pixels) since the last
    refinement exceeds this; 0 disables it (the 3DGS code's screen-size test never fires either)."""
    refine_start: int = 500
    """Refinement happens only after this step."""
    refine_stop: int = 15_000
    """No statistics, refinement or reset from this step on."""
    refine_every: int = 100
    """Refinement period in steps."""
    reset_every: int = 3000
    """Opacity-reset period in steps; 0 disables resets."""
    reset_opacity: float = 0.01
    """Opacities are capped at this value by a reset."""
    split_children: int = 2
    """Children made by one split."""
    split_scale_div: float = 1.6
    """Children's scales are the parent's divided by this (3DGS: 0.8 * children)."""
    max_gaussians: int = 0
    """Cap on the number of Gaussians after growth (largest gradients win); 0 means no cap."""

    # ------------------------------------------------------------------ hooks
    def check_sanity(self, gaussians: GaussianSet, optimizer: GroupedAdam) -> None:
        """Raise ``ValueError`` if the set or the optimiser lacks what the strategy needs."""
        for k in ("means", "log_scales", "quats", "opacity_logits"):
            if k not in gaussians.params:
                raise ValueError(f"density control needs parameter {k!r}")
        if "opacity_logits" not in optimizer.names:
            raise ValueError("density control needs an optimiser group named 'opacity_logits'")
        if self.split_children < 1 or self.split_scale_div <= 0:
            raise ValueError("split_children must be >= 1 and split_scale_div > 0")
        if self.refine_every < 1:
            raise ValueError("refine_every must be >= 1")

    def initialize_state(self, scene_extent: float) -> dict[str, Any]:
        """Fresh running state; ``scene_extent`` (world units) scales the 3D size thresholds."""
        if not scene_extent > 0:
            raise ValueError(f"scene_extent must be positive, got {scene_extent}")
        return {"scene_extent": float(scene_extent), "grad2d": None, "count": None, "radii": None}

    def step_pre_backward(
        self, gaussians: GaussianSet, optimizer: GroupedAdam, state: dict, step: int, info: Any
    ) -> None:
        """Ask autograd to keep the gradient of the projected means of ``info`` (one render or a list)."""
        for out in _as_list(info):
            if out.means2d.requires_grad:
                out.means2d.retain_grad()

    def step_post_backward(
        self, gaussians: GaussianSet, optimizer: GroupedAdam, state: dict, step: int, info: Any
    ) -> dict[str, int]:
        """Accumulate statistics from ``info`` and refine/reset when due. Returns counts for logging."""
        report = {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}
        if step >= self.refine_stop:
            return report
        for out in _as_list(info):
            self._accumulate(gaussians, state, out)
        if step > self.refine_start and step % self.refine_every == 0:
            report.update(self._refine(gaussians, optimizer, state, step))
        if self.reset_every > 0 and step % self.reset_every == 0:
            reset_opacity(gaussians, optimizer, state, self.reset_opacity)
            report["reset"] = 1
        return report

    # ------------------------------------------------------------------ internals
    def _accumulate(self, gaussians: GaussianSet, state: dict, out: Any) -> None:
        n = len(gaussians)
        dev = gaussians.device
        if state["grad2d"] is None or state["grad2d"].shape[0] != n:
            state["grad2d"] = torch.zeros(n, device=dev)
            state["count"] = torch.zeros(n, device=dev)
            state["radii"] = torch.zeros(n, device=dev)
        grad = out.means2d.grad
        if grad is None:
            return
        h, w = out.rgb.shape[0], out.rgb.shape[1]
        vis = (out.radii > 0).reshape(-1)
        g = grad.detach().reshape(n, 2)[vis].clone()
        g[:, 0] *= w / 2.0
        g[:, 1] *= h / 2.0
        norm = g.norm(dim=-1)
        # A NaN/Inf gradient must not decide growth; it is counted as zero.
        norm = torch.where(torch.isfinite(norm), norm, torch.zeros_like(norm))
        state["grad2d"][vis] += norm
        state["count"][vis] += 1.0
        r = out.radii.detach().reshape(-1)[vis].to(state["radii"].dtype)
        state["radii"][vis] = torch.maximum(state["radii"][vis], r)

    def _refine(
        self, gaussians: GaussianSet, optimizer: GroupedAdam, state: dict, step: int
    ) -> dict[str, int]:
        n = len(gaussians)
        extent = state["scene_extent"]
        if state["grad2d"] is None or state["grad2d"].shape[0] != n:
            return {}
        avg = state["grad2d"] / state["count"].clamp_min(1.0)
        big = gaussians.scales.detach().max(dim=-1).values > self.grow_scale3d * extent
        want = avg >= self.grow_grad2d
        clone_mask = want & ~big
        split_mask = want & big
        if self.max_gaussians > 0:
            clone_mask, split_mask = self._cap(avg, clone_mask, split_mask, n)
        n_clone, n_split = int(clone_mask.sum()), int(split_mask.sum())
        if n_clone:
            duplicate(gaussians, optimizer, state, clone_mask)
        if n_split:
            # Clones were appended at the end; they are never split in the same round (as in 3DGS).
            pad = torch.zeros(n_clone, dtype=torch.bool, device=split_mask.device)
            split(
                gaussians,
                optimizer,
                state,
                torch.cat([split_mask, pad]),
                self.split_children,
                self.split_scale_div,
            )
        prune_mask = gaussians.opacities.detach() < self.prune_opacity
        if self.reset_every > 0 and step > self.reset_every:
            prune_mask |= gaussians.scales.detach().max(dim=-1).values > self.prune_scale3d * extent
            if self.prune_radius2d > 0:
                prune_mask |= state["radii"] > self.prune_radius2d
        n_prune = int(prune_mask.sum())
        if n_prune:
            remove(gaussians, optimizer, state, prune_mask)
        for k in STATE_KEYS:
            state[k].zero_()
        return {"cloned": n_clone, "split": n_split, "pruned": n_prune}

    def _cap(
        self, avg: torch.Tensor, clone_mask: torch.Tensor, split_mask: torch.Tensor, n: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Keep the largest-gradient candidates whose growth fits under ``max_gaussians``."""
        budget = self.max_gaussians - n
        cand = (clone_mask | split_mask).nonzero().squeeze(-1)
        cost = torch.where(split_mask[cand], self.split_children - 1, 1)
        order = torch.argsort(avg[cand], descending=True, stable=True)
        fits = torch.cumsum(cost[order], 0) <= budget
        keep = torch.zeros_like(clone_mask)
        keep[cand[order[fits]]] = True
        return clone_mask & keep, split_mask & keep


def _as_list(info: Any) -> Sequence[Any]:
    return info if isinstance(info, list | tuple) else [info]


# ---------------------------------------------------------------------- in-place operations
def _apply(
    gaussians: GaussianSet,
    optimizer: GroupedAdam | None,
    state: dict,
    param_fn: Callable[[str, torch.Tensor], torch.Tensor],
    moment_fn: Callable[[torch.Tensor], torch.Tensor],
    state_fn: Callable[[torch.Tensor], torch.Tensor],
) -> None:
    """Replace every parameter by ``param_fn(name, p)``, each Adam moment by ``moment_fn(m)`` and every
    per-Gaussian tensor of ``state`` by ``state_fn(v)``."""
    groups = set(optimizer.names) if optimizer is not None else set()
    for name in list(gaussians.params.keys()):
        old = gaussians.params[name]
        new = nn.Parameter(param_fn(name, old.detach()), requires_grad=old.requires_grad)
        gaussians.params[name] = new
        if name in groups:
            optimizer.replace_param(name, new, lambda _k, m: moment_fn(m))
    for k in STATE_KEYS:
        v = state.get(k)
        if isinstance(v, torch.Tensor):
            state[k] = state_fn(v)


def _zeros_like_rows(v: torch.Tensor, rows: int) -> torch.Tensor:
    return torch.zeros((rows, *v.shape[1:]), dtype=v.dtype, device=v.device)


@torch.no_grad()
def duplicate(gaussians: GaussianSet, optimizer: GroupedAdam | None, state: dict, mask: torch.Tensor) -> None:
    """Append a copy of each Gaussian in ``mask [N]`` (bool); the copies get zero Adam moments."""
    k = int(mask.sum())
    _apply(
        gaussians,
        optimizer,
        state,
        lambda _n, p: torch.cat([p, p[mask]]),
        lambda m: torch.cat([m, _zeros_like_rows(m, k)]),
        lambda v: torch.cat([v, _zeros_like_rows(v, k)]),
    )


@torch.no_grad()
def split(
    gaussians: GaussianSet,
    optimizer: GroupedAdam | None,
    state: dict,
    mask: torch.Tensor,
    children: int = 2,
    scale_div: float = 1.6,
) -> None:
    """Replace each Gaussian in ``mask [N]`` by ``children`` Gaussians.

    Children's means are ``mean + R(q) (s * z)`` with ``z ~ N(0, I)`` (drawn from the global torch RNG),
    their scales ``s / scale_div``; other parameters are copied. Survivors keep their order and moments;
    children are appended (all first children, then all second children, ...) with zero moments.
    """
    rest = ~mask
    k = int(mask.sum())
    sel_scales = gaussians.scales.detach()[mask]  # [k, 3]
    rot = quat_to_rotmat(gaussians.params["quats"].detach()[mask])  # [k, 3, 3]
    z = torch.randn((children, k, 3), device=sel_scales.device, dtype=sel_scales.dtype)
    offsets = torch.einsum("kij,ckj->cki", rot, z * sel_scales[None]).reshape(children * k, 3)

    def param_fn(name: str, p: torch.Tensor) -> torch.Tensor:
        sel = p[mask]
        if name == "means":
            new = sel.repeat(children, 1) + offsets
        elif name == "log_scales":
            new = torch.log(sel_scales / scale_div).repeat(children, 1)
        else:
            new = sel.repeat(children, *([1] * (p.ndim - 1)))
        return torch.cat([p[rest], new])

    _apply(
        gaussians,
        optimizer,
        state,
        param_fn,
        lambda m: torch.cat([m[rest], _zeros_like_rows(m, children * k)]),
        lambda v: torch.cat([v[rest], _zeros_like_rows(v, children * k)]),
    )


@torch.no_grad()
def remove(gaussians: GaussianSet, optimizer: GroupedAdam | None, state: dict, mask: torch.Tensor) -> None:
    """Delete the Gaussians in ``mask [N]``; the others keep their order, moments and statistics."""
    keep = ~mask
    _apply(gaussians, optimizer, state, lambda _n, p: p[keep], lambda m: m[keep], lambda v: v[keep])


@torch.no_grad()
def reset_opacity(gaussians: GaussianSet, optimizer: GroupedAdam | None, state: dict, value: float) -> None:
    """Cap every opacity at ``value`` and zero the opacity group's Adam moments (as 3DGS does)."""
    cap = float(inverse_sigmoid(torch.tensor(value)))
    p = gaussians.params["opacity_logits"]
    new = nn.Parameter(p.detach().clamp_max(cap), requires_grad=p.requires_grad)
    gaussians.params["opacity_logits"] = new
    if optimizer is not None and "opacity_logits" in optimizer.names:
        optimizer.replace_param("opacity_logits", new, lambda _k, m: torch.zeros_like(m))
