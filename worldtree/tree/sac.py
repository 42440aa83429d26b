"""Spatial Ancestral Chains (SAC): every node renders its own dynamic Gaussians plus its ancestors'.

Chain of node ``j``: ``[parent, grandparent, ..., root]`` (nearest first, :func:`worldtree.tree.tpt.ancestors`).
Each node holds its OWN copies of its ancestors (:class:`AncestorCopy`): siblings start from the same copies
(the parent's trained model and the parent's own, trained, chain) and optimise them independently
(Algorithm 1: ``C_2j = C_2j+1 = Append(C_j, zeta_j)``, each a deep copy).

Time convention (the whole tree package):

- *global frame* ``g``: index of a training frame of the scene, ``0 .. T-1``; intervals are in global frames.
- *node-local frame* of node ``j`` with interval ``[L_j, R_j]``: ``g - L_j`` in ``0 .. R_j - L_j``. A node's
  scaffold trajectories (``Scaffold.pos[t_local]``), its dynamic Gaussians' reference times ``t_ref`` and its
  camera poses are all indexed by node-local frames (:meth:`worldtree.motion.scaffold.Scaffold.slice_time`
  renumbers ``start`` to 0).
- An ancestor copy keeps its ancestor's full interval and node-local indexing; at global frame ``g`` it is
  evaluated at ITS local time ``g - L_ancestor`` (always valid: a descendant's frames lie in its ancestors'
  intervals).

Which ancestors are optimised (:class:`AncestorPolicy`, REFERENCE section 1): the nearest two get their own
optimiser over the Gaussian position/rotation/scale/opacity/colour, the skinning correction and the scaffold
node positions/rotations/radii, with constant learning rates (no decay), no ARAP/velocity/acceleration
regularisation and no densification or pruning; deeper ancestors are frozen. ``chain_length`` (the paper's
chain-length study, ``--chain-length K``) truncates the chain at *render* time only: ``K = 0`` renders no
ancestor, ``None`` the whole chain.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import torch
from torch import nn

from worldtree.dynamic import DynamicGaussians
from worldtree.motion.scaffold import Scaffold, SkinCache
from worldtree.optim import ConstantLR, GroupedAdam
from worldtree.tree.tpt import Interval

__all__ = [
    "GAUSSIAN_PARAMS",
    "SCAFFOLD_PARAMS",
    "AncestorCopy",
    "AncestorPolicy",
    "ancestor_optimizer",
    "chain_gaussians_at",
    "clone_dynamic",
    "clone_scaffold",
    "truncate_chain",
]

GAUSSIAN_PARAMS = ("means", "quats", "log_scales", "opacity_logits", "sh0", "skin_corr")
"""Dynamic-Gaussian entries an optimised ancestor trains (``skin_corr`` when present)."""
SCAFFOLD_PARAMS = ("pos", "quat", "sigma_logit")
"""Scaffold parameters an optimised ancestor trains (node positions, rotations, radii)."""


@dataclass(frozen=True)
class AncestorPolicy:
    """How the ancestors of a node are treated while it trains (defaults: REFERENCE section 1)."""

    optimised_nearest: int = 2
    """The nearest this many ancestors (parent = 1) are optimised with the node; deeper ones are frozen."""
    gaussian_params: tuple[str, ...] = GAUSSIAN_PARAMS
    """Entries of an optimised ancestor's dynamic Gaussians that train (missing entries are skipped)."""
    scaffold_params: tuple[str, ...] = SCAFFOLD_PARAMS
    """Parameters of an optimised ancestor's scaffold that train."""
    lr_decay: bool = False
    """Whether ancestors' learning rates decay (the authors: constant)."""
    regularise: bool = False
    """Whether ancestors' scaffolds get the ARAP/velocity/acceleration terms (the authors: no)."""
    densify: bool = False
    """Whether density control (clone/split/prune) touches ancestors (the authors: no)."""

    def __post_init__(self) -> None:
        if self.optimised_nearest < 0:
            raise ValueError(f"AncestorPolicy.optimised_nearest must be >= 0, got {self.optimised_nearest}")
        bad = set(self.scaffold_params) - set(SCAFFOLD_PARAMS)
        if bad:
            raise ValueError(f"AncestorPolicy.scaffold_params: unknown {sorted(bad)}; use {SCAFFOLD_PARAMS}")

    def is_optimised(self, level: int) -> bool:
        """Whether the ancestor ``level`` steps up (1 = parent) is optimised."""
        if level < 1:
            raise ValueError(f"ancestor level starts at 1 (parent), got {level}")
        return level <= self.optimised_nearest


def clone_scaffold(scf: Scaffold, device: torch.device | str | None = None) -> Scaffold:
    """An independent copy (no shared storage, no autograd history)."""
    return Scaffold.from_state(scf.to_state(), device if device is not None else scf.pos.device)


def clone_dynamic(dyn: DynamicGaussians, device: torch.device | str | None = None) -> DynamicGaussians:
    """An independent copy of dynamic Gaussians (every entry cloned, ``t_ref`` kept frozen)."""
    dev = device if device is not None else dyn.device
    return DynamicGaussians({k: v.detach().clone().to(dev) for k, v in dyn.params.items()})


@dataclass
class AncestorCopy:
    """A node's own copy of one ancestor: its scaffold and dynamic Gaussians over the ancestor's interval."""

    node: int
    """The ancestor's tree index."""
    interval: Interval
    """The ancestor's interval (global frames); its scaffold has ``interval.length`` frames."""
    scaffold: Scaffold
    """Scaffold in the ancestor's node-local frames."""
    dynamic: DynamicGaussians
    """Dynamic Gaussians, ``t_ref`` in the ancestor's node-local frames."""
    level: int = 1
    """Steps up from the node holding this copy (1 = parent)."""
    trainable: bool = False
    """Set by :meth:`apply_policy`: whether the copy is optimised with its node."""
    cache: SkinCache | None = field(default=None, repr=False)
    """Skinning neighbourhoods (computed by :meth:`refresh_cache`)."""

    def __post_init__(self) -> None:
        if self.scaffold.T != self.interval.length:
            raise ValueError(
                f"ancestor {self.node}: scaffold has {self.scaffold.T} frames, interval {self.interval} has "
                f"{self.interval.length}"
            )

    def local_time(self, t_global: int) -> int:
        """This ancestor's node-local frame of global frame ``t_global``."""
        return self.interval.local(int(t_global))

    def refresh_cache(self) -> SkinCache:
        """Recompute the skinning neighbourhoods (after the means moved far, or after loading)."""
        self.cache = self.dynamic.attach(self.scaffold)
        return self.cache

    def at(self, t_global: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``(means [N, 3], quats [N, 4])`` of the ancestor's Gaussians at global frame ``t_global``."""
        if self.cache is None:
            self.refresh_cache()
        return self.dynamic.at(self.scaffold, self.local_time(t_global), self.cache)

    def apply_policy(self, policy: AncestorPolicy) -> None:
        """Mark the copy trainable or frozen from its ``level`` and set ``requires_grad`` accordingly."""
        self.trainable = policy.is_optimised(self.level)
        for k, p in self.dynamic.params.items():
            p.requires_grad_(self.trainable and k in policy.gaussian_params and p.is_floating_point())
        for k in SCAFFOLD_PARAMS:
            getattr(self.scaffold, k).requires_grad_(self.trainable and k in policy.scaffold_params)

    def parameters(self, policy: AncestorPolicy) -> dict[str, nn.Parameter]:
        """Named parameters to optimise (empty when frozen): ``gauss.<entry>`` and ``scaffold.<name>``."""
        if not policy.is_optimised(self.level):
            return {}
        out: dict[str, nn.Parameter] = {}
        for k in policy.gaussian_params:
            if k in self.dynamic.params:
                out[f"gauss.{k}"] = self.dynamic.params[k]
        for k in policy.scaffold_params:
            out[f"scaffold.{k}"] = getattr(self.scaffold, k)
        return out

    def copy(self, level: int | None = None) -> AncestorCopy:
        """A deep, independent copy (optionally one level further up, for a child's chain)."""
        return AncestorCopy(
            self.node,
            self.interval,
            clone_scaffold(self.scaffold),
            clone_dynamic(self.dynamic),
            self.level if level is None else level,
            self.trainable,
        )

    def to_payload(self) -> dict:
        """Plain dict of CPU tensors and numbers (loadable with ``torch.load(weights_only=True)``)."""
        return {
            "node": self.node,
            "interval": [self.interval.start, self.interval.end],
            "level": self.level,
            "trainable": self.trainable,
            "scaffold": _cpu(self.scaffold.to_state()),
            "dynamic": {k: v.detach().cpu().clone() for k, v in self.dynamic.params.items()},
        }

    @classmethod
    def from_payload(cls, d: dict, device: torch.device | str = "cpu") -> AncestorCopy:
        return cls(
            int(d["node"]),
            Interval(*[int(x) for x in d["interval"]]),
            Scaffold.from_state(d["scaffold"], device),
            DynamicGaussians({k: v.to(device) for k, v in d["dynamic"].items()}),
            int(d["level"]),
            bool(d["trainable"]),
        )


def chain_cache_states(chain: list[AncestorCopy]) -> list[dict[str, torch.Tensor]]:
    """The skinning caches the copies use now (computed where missing), for a checkpoint."""
    return [(a.cache if a.cache is not None else a.refresh_cache()).to_state() for a in chain]


def restore_chain_caches(
    chain: list[AncestorCopy], states: list[dict[str, torch.Tensor]] | None, device: torch.device | str
) -> None:
    """Put the checkpoint's skinning caches back (None, from an older checkpoint: keep the recomputed ones).

    A copy's cache is recomputed only every ``reattach_every`` steps, so a resumed node must use the one the
    uninterrupted run still holds rather than one computed from the checkpoint's moved node positions."""
    if states is None:
        return
    if len(states) != len(chain):
        raise ValueError(f"checkpoint holds {len(states)} ancestor caches for a chain of {len(chain)}")
    for a, st in zip(chain, states, strict=True):
        a.cache = SkinCache.from_state(st, device)


def _cpu(obj):
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu().clone()
    if isinstance(obj, dict):
        return {k: _cpu(v) for k, v in obj.items()}
    return obj


def truncate_chain(chain: Sequence[AncestorCopy], chain_length: int | None) -> list[AncestorCopy]:
    """The first ``chain_length`` ancestors (nearest first); ``None`` keeps all, ``0`` none."""
    if chain_length is None:
        return list(chain)
    if chain_length < 0:
        raise ValueError(f"chain_length {chain_length}: must be >= 0 (0 = no ancestor) or None (all)")
    return list(chain[:chain_length])


def chain_gaussians_at(
    chain: Sequence[AncestorCopy], t_global: int, chain_length: int | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """The ancestors' Gaussians at global frame ``t_global``, concatenated nearest first.

    Returns ``(means [N, 3], quats [N, 4], log_scales [N, 3], opacities [N], colours [N, 3])`` ready to be
    appended to the node's own (static + dynamic) tensors for :func:`worldtree.render.rasterize`, or None when
    the (truncated) chain is empty. Each ancestor is deformed at its own local time; gradients reach the
    trainable copies' parameters.
    """
    used = truncate_chain(chain, chain_length)
    if not used:
        return None
    parts: list[tuple[torch.Tensor, ...]] = []
    for anc in used:
        m, q = anc.at(t_global)
        d = anc.dynamic
        parts.append((m, q, d.log_scales, d.opacities_at(anc.local_time(t_global)), d.colors))
    return tuple(torch.cat(xs) for xs in zip(*parts, strict=True))  # type: ignore[return-value]


def ancestor_optimizer(
    chain: Sequence[AncestorCopy], policy: AncestorPolicy, lrs: Mapping[str, float]
) -> GroupedAdam | None:
    """One Adam over every trainable copy of ``chain``, constant learning rates (``policy.lr_decay`` is
    False for the authors; a decaying schedule is the caller's to build when it is True).

    ``lrs`` maps the names of :meth:`AncestorCopy.parameters` (``gauss.means``, ``scaffold.pos``, ...) to
    learning rates (already multiplied by the scene extent where the method does so); a name missing from it
    is an error. Groups are named ``a<node>.<name>``. Returns None when no copy trains.
    """
    params: dict[str, nn.Parameter] = {}
    sched: dict[str, ConstantLR] = {}
    for anc in chain:
        for name, p in anc.parameters(policy).items():
            if name not in lrs:
                raise ValueError(f"ancestor_optimizer: no learning rate for {name!r}")
            params[f"a{anc.node}.{name}"] = p
            sched[f"a{anc.node}.{name}"] = ConstantLR(float(lrs[name]))
    return GroupedAdam(params, sched) if params else None
