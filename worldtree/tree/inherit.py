"""Split a trained node's state into its children's starting states (REFERENCE section 1, paper Eq. 5-6).

For a child with interval ``[a, b]`` of a parent ``[L, R]``, with ``offset = a - L`` (the child's first frame
in the parent's node-local frames) and ``n = b - a + 1``:

- scaffold: every node kept, trajectories of the parent's local frames ``[offset, offset + n)``
  (:meth:`Scaffold.slice_time`; child-local frame 0 = global frame ``a``);
- dynamic Gaussians: those whose reference time ``t_ref`` (parent-local) lies in ``[offset, offset + n)``,
  randomly subsampled without replacement (seeded by ``(seed, child index)``) to the cap of the child's depth
  (5000 at depth 1, 2000 at depth 2 and deeper; the root starts from 30000, the Base method's cap), kept in
  their original order; ``t_ref`` shifted by ``-offset``; opacity reset ``o = min(o, 0.05)``, done on the
  logits as ``min(logit, logit(0.05))`` (the sigmoid is monotonic, so this is exact);
- static model: a full copy of the parent's (its opacities untouched unless ``reset_static_opacity``);
- camera poses: the parent's rows ``[offset, offset + n)``;
- chain: a copy of the parent (its trained scaffold and dynamic Gaussians over the parent's interval, no
  subsampling, no reset) at level 1, followed by copies of the parent's own chain one level further up;
  trainable or frozen by the :class:`~worldtree.tree.sac.AncestorPolicy`.

Every tensor of a child is a fresh copy: training one child (or its ancestor copies) never changes its sibling.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from worldtree.dynamic import DynamicGaussians
from worldtree.gaussians import GaussianSet, inverse_sigmoid
from worldtree.tree.node import NodeState
from worldtree.tree.sac import AncestorCopy, AncestorPolicy, clone_dynamic, clone_scaffold
from worldtree.tree.tpt import Interval, children, depth_of

__all__ = ["InheritConfig", "child_cap", "child_state", "select_inherited", "split_state"]


@dataclass(frozen=True)
class InheritConfig:
    """How children inherit from their parent (defaults: REFERENCE section 1)."""

    caps: tuple[int, ...] = (5000, 2000)
    """Most dynamic Gaussians a child inherits, by child depth 1, 2, ...; deeper layers use the last value
    (the root's 30000 is the Base method's ``dynamic_max_init``)."""
    opacity_cap: float = 0.05
    """Inherited dynamic opacities are reset to ``min(o, opacity_cap)``; 1.0 disables the reset."""
    reset_static_opacity: bool = False
    """Also reset the static copy's opacities (the authors reset only what the child inherits to refine)."""
    policy: AncestorPolicy = AncestorPolicy()
    """Which ancestor copies train with the child."""

    def __post_init__(self) -> None:
        if not self.caps or min(self.caps) < 0:
            raise ValueError(f"InheritConfig.caps must be non-empty and >= 0, got {self.caps}")
        if not 0.0 < self.opacity_cap <= 1.0:
            raise ValueError(f"InheritConfig.opacity_cap must be in (0, 1], got {self.opacity_cap}")
        object.__setattr__(self, "caps", tuple(int(c) for c in self.caps))


def child_cap(cfg: InheritConfig, depth: int) -> int:
    """Cap on inherited dynamic Gaussians for a child of ``depth`` (>= 1)."""
    if depth < 1:
        raise ValueError(f"children have depth >= 1, got {depth}")
    return cfg.caps[min(depth, len(cfg.caps)) - 1]


def _seed(seed: int, child: int) -> int:
    # Independent streams per (run seed, child) that do not depend on the order children are made in.
    return int(
        np.random.SeedSequence([int(seed) & 0xFFFFFFFF, int(child)]).generate_state(1, np.uint64)[0] >> 1
    )


def select_inherited(t_ref: torch.Tensor, offset: int, length: int, cap: int, seed: int) -> torch.Tensor:
    """Indices [S] (ascending) of the Gaussians a child keeps: ``offset <= t_ref < offset + length``,
    subsampled without replacement to ``cap`` with a generator seeded by ``seed``."""
    inside = torch.nonzero((t_ref >= offset) & (t_ref < offset + length)).flatten().cpu()
    if inside.numel() > cap:
        g = torch.Generator().manual_seed(seed)
        pick = torch.randperm(inside.numel(), generator=g)[:cap]
        inside = torch.sort(inside[pick]).values
    return inside.to(t_ref.device)


def _reset_opacity(logits: torch.Tensor, cap: float) -> torch.Tensor:
    if cap >= 1.0:
        return logits.clone()
    limit = inverse_sigmoid(torch.tensor(cap, dtype=logits.dtype, device=logits.device))
    return torch.minimum(logits, limit)


def child_state(
    parent: NodeState, child: int, interval: Interval, cfg: InheritConfig, seed: int = 0
) -> NodeState:
    """The starting state of child ``child`` (``2j`` or ``2j + 1`` of ``parent.index``) over ``interval``."""
    if child // 2 != parent.index:
        raise ValueError(f"node {child} is not a child of node {parent.index}")
    pv = parent.interval
    if not (pv.start <= interval.start and interval.end <= pv.end):
        raise ValueError(f"child interval {interval} is not inside the parent's {pv}")
    offset, n = interval.start - pv.start, interval.length
    scaffold = parent.scaffold.slice_time(offset, offset + n)
    dyn = parent.dynamic
    keep = select_inherited(dyn.t_ref, offset, n, child_cap(cfg, depth_of(child)), _seed(seed, child))
    params: dict[str, torch.Tensor] = {k: v.detach()[keep].clone() for k, v in dyn.params.items()}
    params["t_ref"] = params["t_ref"] - offset
    params["opacity_logits"] = _reset_opacity(params["opacity_logits"], cfg.opacity_cap)
    static_params = {k: v.detach().clone() for k, v in parent.static.params.items()}
    if cfg.reset_static_opacity:
        static_params["opacity_logits"] = _reset_opacity(static_params["opacity_logits"], cfg.opacity_cap)
    chain = [
        AncestorCopy(
            parent.index, pv, clone_scaffold(parent.scaffold), clone_dynamic(parent.dynamic), level=1
        )
    ]
    chain += [a.copy(level=a.level + 1) for a in parent.chain]
    for a in chain:
        a.apply_policy(cfg.policy)
    return NodeState(
        child,
        interval,
        scaffold,
        DynamicGaussians(params),
        GaussianSet(static_params),
        parent.w2cs.detach()[offset : offset + n].clone(),
        chain,
    )


def split_state(
    parent: NodeState, left: Interval, right: Interval, cfg: InheritConfig, seed: int = 0
) -> tuple[NodeState, NodeState]:
    """Both children of ``parent`` (intervals as given by the tree); see the module docstring."""
    if left.end + 1 != right.start or left.start != parent.interval.start or right.end != parent.interval.end:
        raise ValueError(f"children {left}, {right} do not partition the parent's {parent.interval}")
    a, b = children(parent.index)
    return child_state(parent, a, left, cfg, seed), child_state(parent, b, right, cfg, seed)
