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

__all__ = ["NodeState", "load_payload", "save_payload"]

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

    def to_payload(self) -> dict:
        """Plain dict of CPU tensors/numbers (see the module docstring)."""
        return {
            "format": FORMAT,
            "version": worldtree.__version__,
            "index": self.index,
            "interval": [self.interval.start, self.interval.end],
            "scaffold": _cpu(self.scaffold.to_state()),
            "dynamic": {k: v.detach().cpu().clone() for k, v in self.dynamic.params.items()},
            "static": {k: v.detach().cpu().clone() for k, v in self.static.params.items()},
            "w2cs": self.w2cs.detach().cpu().clone(),
            "chain": [a.to_payload() for a in self.chain],
        }

    @classmethod
    def from_payload(cls, d: dict, device: torch.device | str = "cpu") -> NodeState:
        if d.get("format") != FORMAT:
            raise ValueError(f"not a tree node state (format {d.get('format')!r}, expected {FORMAT!r})")
        return cls(
            int(d["index"]),
            Interval(*[int(x) for x in d["interval"]]),
            Scaffold.from_state(d["scaffold"], device),
            DynamicGaussians({k: v.to(device) for k, v in d["dynamic"].items()}),
            GaussianSet({k: v.to(device) for k, v in d["static"].items()}),
            d["w2cs"].to(device),
            [AncestorCopy.from_payload(a, device) for a in d["chain"]],
        )

    def save(self, path: str | Path) -> None:
        """Write the state to ``path`` atomically."""
        save_payload(path, self.to_payload())

    @classmethod
    def load(cls, path: str | Path, device: torch.device | str = "cpu") -> NodeState:
        return cls.from_payload(load_payload(path), device)


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
