"""Algorithm 1 (BFS tree building) on top of a trained root: split, inherit, train each layer, repeat.

:func:`grow_tree` takes the trained root :class:`~worldtree.tree.node.NodeState` and, for ``d = 0 ..
depth - 1``, splits every node of layer ``d`` that is long enough (:mod:`worldtree.tree.split`), makes its
children's states (:func:`worldtree.tree.inherit.split_state`), writes them under ``folder/layer<d+1>``, trains
them with the :class:`~worldtree.tree.parallel.LayerRunner` and reads the trained states back.

Node-function contract (the method's part): ``fn(payload, ctx)`` receives :func:`node_input` (``{"state":
NodeState payload, "depth": d}``) and returns :func:`node_output` (the trained state, optionally the node's
per-frame ``profile`` for the ``gradient`` split of its own children, JSON-able ``stats`` and, under
``--depth auto``, the node's measured fit for its children's decisions).

``--depth auto``: a node is split when its own decision says so (``stats["auto_split"]``, the root's given);
then each child is trained only when :func:`worldtree.tree.adaptive.decide_child` finds that the parent's fit
does not already hold the child's frames (one-sided split; a node that reports no measured fit gets both
children). Every decision is recorded: ``TreeResult.decisions[j]`` with ``"applied"`` and ``"children"``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from worldtree.infra.atomic import atomic_write_json
from worldtree.tree.adaptive import AutoSplitConfig, decide_child
from worldtree.tree.inherit import InheritConfig, child_state, split_state
from worldtree.tree.node import NodeState
from worldtree.tree.parallel import LayerReport, LayerRunner, write_input
from worldtree.tree.split import SplitChoice, choose_split
from worldtree.tree.tpt import DEFAULT_MIN_LEN, TemporalPartitionTree

__all__ = ["TreeConfig", "TreeResult", "grow_tree", "node_input", "node_output", "read_node_input"]


@dataclass(frozen=True)
class TreeConfig:
    """Shape of the tree and how children inherit (defaults: the paper's NVIDIA-LS settings)."""

    depth: int = 2
    """Deepest layer (0 = the root only, i.e. the Base method; the paper: 2)."""
    min_len: int = DEFAULT_MIN_LEN
    """Nodes with fewer frames are leaves."""
    split: str = "binary"
    """Split strategy: ``binary``, ``gradient`` (node profiles from training) or ``flow`` (a global profile)."""
    inherit: InheritConfig = InheritConfig()
    """Caps, opacity reset and ancestor policy."""
    auto: AutoSplitConfig | None = None
    """``--depth auto``: a node gets children only when its measured split decision says so
    (:mod:`worldtree.tree.adaptive`), down to ``auto.max_depth``; ``depth`` is then ignored."""

    @property
    def max_depth(self) -> int:
        """Deepest layer the tree may reach (``depth``, or ``auto.max_depth`` in auto mode)."""
        return self.auto.max_depth if self.auto is not None else self.depth

    def __post_init__(self) -> None:
        if self.depth < 0:
            raise ValueError(f"TreeConfig.depth {self.depth}: must be >= 0")
        from worldtree.tree.split import SPLIT_STRATEGIES

        if self.split not in SPLIT_STRATEGIES:
            raise ValueError(f"TreeConfig.split {self.split!r}: choose one of {', '.join(SPLIT_STRATEGIES)}")


@dataclass
class TreeResult:
    """Everything :func:`grow_tree` made."""

    tree: TemporalPartitionTree
    states: dict[int, NodeState]
    """Trained state of every node (the root as given)."""
    layers: list[LayerReport] = field(default_factory=list)
    """One report per trained layer (depth 1 ..)."""
    splits: dict[int, SplitChoice] = field(default_factory=dict)
    """Split decision of every node that has children."""
    stats: dict[int, dict] = field(default_factory=dict)
    """Each trained node's ``stats`` from its function."""
    rejected: list[int] = field(default_factory=list)
    """Children trained but dropped by their held-out validation (their ``stats`` say why)."""
    decisions: dict[int, dict] = field(default_factory=dict)
    """Auto mode: every node's split decision (``SplitDecision.to_dict()`` plus ``"applied"``: whether it got
    children, False e.g. at the depth bound or when neither child needs training, and, for a node whose
    split was tested child by child, ``"children"``: ``{child index: ChildDecision.to_dict()}``)."""


def node_input(state: NodeState, depth: int) -> dict:
    """The payload a node-training function receives."""
    return {"state": state.to_payload(), "depth": int(depth)}


def read_node_input(payload: dict, device: torch.device | str = "cpu") -> tuple[NodeState, int]:
    """``(state, depth)`` from :func:`node_input`'s payload, tensors on ``device``."""
    return NodeState.from_payload(payload["state"], device), int(payload["depth"])


def node_output(
    state: NodeState,
    profile: np.ndarray | torch.Tensor | None = None,
    stats: dict | None = None,
    measured: dict | None = None,
) -> dict:
    """The payload a node-training function returns: the trained state, its per-frame ``profile``
    ``[T_node]`` (for the gradient split, or None), JSON-able ``stats`` and, under ``--depth auto``, its
    measured fit (:meth:`worldtree.tree.adaptive.FitAssessment.to_payload`) for its children's decisions."""
    prof = None
    if profile is not None:
        prof = torch.as_tensor(np.asarray(profile, dtype=np.float64))
        if prof.shape != (state.interval.length,):
            raise ValueError(f"node {state.index}: profile {tuple(prof.shape)} != [{state.interval.length}]")
    return {"state": state.to_payload(), "profile": prof, "stats": dict(stats or {}), "measured": measured}


def _children_to_train(state: NodeState, measured: dict | None, point: int, cfg: AutoSplitConfig,
                       first: int) -> tuple[tuple[bool, bool], dict[str, dict] | None]:  # fmt: skip
    """Auto mode: which of the two children of ``state`` split at ``point`` need training (``first``: the left
    child's index), with each child's decision; both, unrecorded, when the parent reported no measured fit."""
    if measured is None:
        return (True, True), None
    iv = state.interval
    halves = ((iv.start, point - 1), (point, iv.end))
    pos, w2cs = state.scaffold.pos.detach(), state.w2cs.detach()
    decided = [decide_child(pos, w2cs, iv.start, measured, h, cfg) for h in halves]
    keep = (decided[0].train, decided[1].train)
    return keep, {str(first + k): d.to_dict() for k, d in enumerate(decided)}


def grow_tree(
    root: NodeState,
    cfg: TreeConfig,
    runner: LayerRunner,
    folder: str | Path,
    seed: int = 0,
    root_profile: np.ndarray | torch.Tensor | None = None,
    flow: np.ndarray | torch.Tensor | None = None,
    root_decision: dict | None = None,
    root_measured: dict | None = None,
) -> TreeResult:
    """Build and train the tree below ``root`` (already trained; its chain is empty).

    Args:
        root: the trained root state over ``[0, T - 1]``.
        cfg: depth, minimum length, split strategy, inheritance.
        runner: trains each layer (parallel or sequential); its node function follows the module's contract.
        folder: where the layers' files go (``folder/layer<d>/node<j>/...``, ``folder/tree.json``).
        seed: run seed; node ``j`` trains with seed ``seed + j`` and inherits with ``(seed, j)``.
        root_profile: the root's per-frame profile ``[T]`` for the ``gradient`` split.
        flow: global per-frame profile ``[T]`` for the ``flow`` split (:func:`worldtree.tree.split.flow_profile`).
        root_decision: auto mode: the root's ``SplitDecision.to_dict()``; the children's come from their node
            function's ``stats["auto_split"]`` (a node without one is a leaf, recorded as such).
        root_measured: auto mode: the trained root's measured fit (``FitAssessment.to_payload()``) for its
            children's decisions; the other nodes' come from their node function's output (``"measured"``).
    """
    if root.index != 1 or root.chain:
        raise ValueError("grow_tree starts from the root state (index 1, no ancestors)")
    folder = Path(folder)
    T = root.interval.length
    tree = TemporalPartitionTree(T, cfg.min_len)
    if root.interval.start != 0:
        raise ValueError(f"the root interval must start at frame 0, got {root.interval}")
    res = TreeResult(tree, {1: root})
    profiles: dict[int, Any] = {1: root_profile}
    flow_np = None if flow is None else np.asarray(torch.as_tensor(flow, dtype=torch.float64).cpu().numpy())
    decisions: dict[int, dict | None] = {1: root_decision}
    measured: dict[int, dict | None] = {1: root_measured}
    for d in range(cfg.max_depth + 1):
        new: list[int] = []
        for j in tree.layer(d):
            dec = None
            if cfg.auto is not None:
                dec = dict(decisions.get(j) or {"split": False, "reason": "no decision reported"})
                dec["applied"] = bool(dec["split"]) and d < cfg.max_depth and tree.can_split(j)
                if dec["split"] and not dec["applied"]:
                    dec["reason"] += f"; not split: depth bound {cfg.max_depth} or under min_len"
                res.decisions[j] = dec
                if not dec["applied"]:
                    continue
            if d >= cfg.max_depth or not tree.can_split(j):
                continue
            iv = tree.interval(j)
            prof = profiles.get(j) if cfg.split == "gradient" else None
            if cfg.split == "flow" and flow_np is not None:
                prof = flow_np[iv.start : iv.end + 1]
            choice = choose_split(cfg.split, iv, prof, cfg.min_len)
            keep = (True, True)
            if dec is not None:
                keep, dec["children"] = _children_to_train(res.states[j], measured.get(j), choice.point,
                                                           cfg.auto, 2 * j)  # fmt: skip
                if not any(keep):
                    dec["applied"] = False
                    dec["reason"] += (
                        "; not split: the node's own fit holds both halves (no child needs training)"
                    )
                    continue
            added = tree.add_children(j, choice.point, keep)
            res.splits[j] = choice
            layer_dir = folder / f"layer{d + 1}"
            if len(added) == 2:
                states = split_state(res.states[j], *iv.split_at(choice.point), cfg.inherit, seed)
            else:  # one-sided: only the kept child's state is made
                states = (child_state(res.states[j], added[0], tree.interval(added[0]), cfg.inherit, seed),)
            for c, st in zip(added, states, strict=True):
                write_input(layer_dir, c, node_input(st, d + 1))
            new += list(added)
        if not new:
            break
        layer_dir = folder / f"layer{d + 1}"
        rep = runner.run_layer(d + 1, layer_dir, new, seeds=[seed + j for j in new])
        res.layers.append(rep)
        for j in new:
            out = runner.load_output(layer_dir, j)
            res.stats[j] = dict(out.get("stats") or {})
            if (res.stats[j].get("holdout") or {}).get("keep") is False:
                # Held-out validation rejected the child: its parent renders its frames (a leaf, no children).
                tree.remove_leaf(j)
                res.rejected.append(j)
                continue
            res.states[j] = NodeState.from_payload(out["state"])
            profiles[j] = out.get("profile")
            decisions[j] = res.stats[j].get("auto_split")
            measured[j] = out.get("measured")
    atomic_write_json(
        folder / "tree.json",
        {
            "tree": tree.to_dict(),
            "split": cfg.split,
            "splits": {str(j): {"point": c.point, "fallback": c.fallback} for j, c in res.splits.items()},
            "layers": [r.to_dict() for r in res.layers],
            "stats": {str(j): s for j, s in res.stats.items()},
            "rejected": res.rejected,
            "auto": {str(j): dec for j, dec in res.decisions.items()} if cfg.auto is not None else None,
        },
    )
    return res
