"""The model state of one TPT node and its hand-over through files.

A :class:`NodeState` is everything a node trains from and produces: its scaffold and dynamic Gaussians
(node-local frames, see :mod:`worldtree.tree.sac` for the time convention), its static model, its camera poses
for its frames, and its chain of ancestor copies. :meth:`NodeState.save` / :meth:`NodeState.load` move it
between processes (the parallel layer runner) as a ``torch.save`` file of plain dicts and CPU tensors, written
atomically and readable with ``weights_only=True``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch

import worldtree
from worldtree.dynamic import DynamicGaussians, gaussians_at
from worldtree.gaussians import GaussianSet
from worldtree.infra.torchfile import load_torch, save_torch
from worldtree.motion.scaffold import Scaffold, SkinCache
from worldtree.tree.sac import AncestorCopy, _cpu, chain_gaussians_at
from worldtree.tree.tpt import Interval, depth_of

__all__ = [
    "NodeState",
    "distinct_gaussians",
    "load_payload",
    "same_gaussians",
    "save_payload",
    "share_static_model",
]

FORMAT = "worldtree-node-v1"


@dataclass
class NodeState:
    """One node's model (see the module docstring). Shapes: ``w2cs`` [T_node, 4, 4], T_node = interval.length."""

    index: int
    """Tree index (root 1)."""
    interval: Interval
    """Global frames ``[L, R]`` of the node."""
    scaffold: Scaffold
    """Scaffold over the node's frames (node-local indexing)."""
    dynamic: DynamicGaussians
    """The node's own dynamic Gaussians (``t_ref`` node-local)."""
    static: GaussianSet
    """The node's copy of the static (background) model."""
    w2cs: torch.Tensor
    """[T_node, 4, 4] world-to-camera poses of the node's frames."""
    chain: list[AncestorCopy] = field(default_factory=list)
    """The node's own ancestor copies, nearest first."""

    def __post_init__(self) -> None:
        n = self.interval.length
        if self.scaffold.T != n or self.w2cs.shape != (n, 4, 4):
            raise ValueError(
                f"node {self.index} {self.interval}: scaffold has {self.scaffold.T} frames and w2cs "
                f"{tuple(self.w2cs.shape)}; both need {n} frames"
            )
        if len(self.dynamic) and int(self.dynamic.t_ref.max()) >= n:
            raise ValueError(f"node {self.index}: a dynamic Gaussian's t_ref is beyond the node's {n} frames")
        expected = list(range(1, len(self.chain) + 1))
        if [a.level for a in self.chain] != expected:
            raise ValueError(f"node {self.index}: chain levels must be {expected} (nearest first)")

    @property
    def depth(self) -> int:
        return depth_of(self.index)

    def local_time(self, t_global: int) -> int:
        """The node's local frame of global frame ``t_global`` (ValueError outside its interval)."""
        return self.interval.local(int(t_global))

    def gaussians_at(
        self, t_global: int, chain_length: int | None = None, cache: SkinCache | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The render list at global frame ``t_global``: static, the node's dynamic Gaussians (at its local
        time), then its ancestors nearest first (each at its own local time), truncated to ``chain_length``.

        Returns ``(means [N, 3], quats [N, 4], log_scales [N, 3], opacities [N], colours [N, 3])`` for
        :func:`worldtree.render.rasterize`; ``cache`` is the node's own skinning cache (computed when None).
        """
        anc = chain_gaussians_at(self.chain, t_global, chain_length)
        return gaussians_at(self.static, self.dynamic, self.scaffold, self.local_time(t_global), cache, anc)

    def to_payload(self, static_shared_with: int | None = None) -> dict:
        """Plain dict of CPU tensors/numbers (see the module docstring).

        ``static_shared_with``: index of a node whose static model this node's is (the same Gaussians, e.g. the
        root's background that a child renders unchanged); the payload then names that node instead of
        holding a copy, and :meth:`from_payload` needs the model handed back (:meth:`load` reads it from the
        named node's file beside this one).
        """
        static = (
            None
            if static_shared_with is not None
            else {k: v.detach().cpu().clone() for k, v in self.static.params.items()}
        )
        return {
            "format": FORMAT,
            "version": worldtree.__version__,
            "index": self.index,
            "interval": [self.interval.start, self.interval.end],
            "scaffold": _cpu(self.scaffold.to_state()),
            "dynamic": {k: v.detach().cpu().clone() for k, v in self.dynamic.params.items()},
            "static": static,
            "static_shared_with": static_shared_with,
            "static_count": len(self.static),
            "w2cs": self.w2cs.detach().cpu().clone(),
            "chain": [a.to_payload() for a in self.chain],
        }

    @classmethod
    def from_payload(
        cls, d: dict, device: torch.device | str = "cpu", static: GaussianSet | None = None
    ) -> NodeState:
        """The state of a :meth:`to_payload` dict; ``static``: the shared static model a payload written with
        ``static_shared_with`` names (used as is, not copied)."""
        if d.get("format") != FORMAT:
            raise ValueError(f"not a tree node state (format {d.get('format')!r}, expected {FORMAT!r})")
        shared = d.get("static_shared_with")
        if shared is None:
            static = GaussianSet({k: v.to(device) for k, v in d["static"].items()})
        elif static is None:
            raise ValueError(f"node {d['index']}: its static model is node {shared}'s; hand that model over")
        elif len(static) != int(d["static_count"]):
            raise ValueError(
                f"node {d['index']}: node {shared}'s static model has {len(static)} Gaussians, the node was "
                f"saved with {d['static_count']}; the files are from different runs"
            )
        return cls(
            int(d["index"]),
            Interval(*[int(x) for x in d["interval"]]),
            Scaffold.from_state(d["scaffold"], device),
            DynamicGaussians({k: v.to(device) for k, v in d["dynamic"].items()}),
            static,
            d["w2cs"].to(device),
            [AncestorCopy.from_payload(a, device) for a in d["chain"]],
        )

    def save(self, path: str | Path, static_shared_with: int | None = None) -> None:
        """Write the state to ``path`` atomically (``static_shared_with``: see :meth:`to_payload`)."""
        save_payload(path, self.to_payload(static_shared_with))

    @classmethod
    def load(
        cls, path: str | Path, device: torch.device | str = "cpu", static: GaussianSet | None = None
    ) -> NodeState:
        """The state saved at ``path``; a node saved with a shared static model gets ``static`` or, when None,
        that of ``node<k>.pt`` in the same folder (k the node it names)."""
        d = load_payload(path)
        shared = d.get("static_shared_with") if isinstance(d, dict) else None
        if shared is not None and static is None:
            static = cls.load(Path(path).with_name(f"node{int(shared)}.pt"), device).static
        return cls.from_payload(d, device, static)


def same_gaussians(a, b) -> bool:
    """Whether two Gaussian sets hold the same parameters, bit for bit."""
    if a is b:
        return True
    pa, pb = a.params, b.params
    return pa.keys() == pb.keys() and all(
        pa[k].shape == pb[k].shape and torch.equal(pa[k].detach(), pb[k].detach().to(pa[k].device))
        for k in pa
    )


def share_static_model(states: dict[int, NodeState]) -> None:
    """The nodes whose static model is the root's, bit for bit (a child renders the root's background unchanged
    while ``node_static_lr`` is 0), hold one model instead of a copy each: kept once in memory, saved once
    (``NodeState.save(..., static_shared_with=1)`` writes a reference to the root's file) and counted
    once (:func:`distinct_gaussians`). Not the root's own model object: during the run that is the trainable one."""
    root = states.get(1)
    if root is None:
        return
    shared = None
    for j in sorted(states):
        st = states[j]
        if j == 1 or not same_gaussians(st.static, root.static):
            continue
        if shared is None:
            shared = st.static
        st.static = shared


def distinct_gaussians(states: dict[int, NodeState], rendering: list[int]) -> int:
    """Distinct Gaussians the ``rendering`` nodes draw: each one's static model, own dynamic Gaussians and
    ancestor copies, a model shared by several nodes (the root's background) or an ancestor copy identical in
    two nodes (a frozen parent's, in both of its children) counted once."""
    seen_static: list = []
    seen_copies: dict[int, list] = {}
    n = 0
    for j in rendering:
        st = states.get(j)
        if st is None:
            continue
        if not any(same_gaussians(st.static, o) for o in seen_static):
            seen_static.append(st.static)
            n += len(st.static)
        n += len(st.dynamic)
        for a in st.chain:
            kept = seen_copies.setdefault(a.node, [])
            if not any(same_gaussians(a.dynamic, o) for o in kept):
                kept.append(a.dynamic)
                n += len(a.dynamic)
    return n


def save_payload(path: str | Path, payload) -> None:
    """``torch.save`` ``payload`` to ``path`` through a temporary file and a rename."""
    save_torch(path, payload)


def load_payload(path: str | Path, device: torch.device | str = "cpu"):
    """Read a file written by :func:`save_payload` (tensors onto ``device``; plain data only)."""
    return load_torch(
        path,
        device,
        missing="no such node state file; re-run the tree stage",
        unreadable="not a readable node state ({error}); delete it and re-run",
    )
