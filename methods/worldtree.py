"""The WorldTree method: the Base method's root optimisation, then the Temporal Partition Tree (docs/worldtree.md).

1. Root: the Base method's stages (priors -> BA -> SW -> scaffold -> photometric, :mod:`methods.base`) train
   node 1 over every frame.
2. Tree: :func:`worldtree.tree.build.grow_tree` splits, inherits and trains the layers ``1 .. depth`` with the
   :class:`~worldtree.tree.parallel.LayerRunner` (one worker process per node, or ``sequential``). Each child
   runs :func:`train_node`: the photometric fit of :mod:`worldtree.stages.photometric` on its own frames
   (RGB, SSIM, depth, track and motion terms as at the root) rendering its Spatial Ancestral Chain, with the
   cameras fixed and no density control (REFERENCE section 1: both only at the root); the nearest ancestors
   train with it (:class:`~worldtree.tree.sac.AncestorPolicy`).
3. Test: every test time is rendered by the deepest node covering it plus its chain (truncated to
   ``chain_length``); the test camera is aligned and refined as in the Base method, through the tree's render.

Worker hand-over: ``checkpoints/tree/context.pt`` holds what every node trains on (images, depth priors,
intrinsics, dynamic tracks; plain tensors) and ``checkpoints/tree/node_config.json`` the node settings; a node
finds them two folders above its own (``tree/layer<d>/node<j>``).

Ablations (``ablate``): ``ba`` / ``sw`` as in the Base method; ``tpt`` trains the root only (depth 0, the Base
method); ``sac`` grows the tree but every node trains and renders without ancestors.

The method is :data:`WORLDTREE_STAGES` over a :class:`WorldTreeState`: the Base method's stages with ``tree``
before ``test_pose`` (:mod:`methods.stages`). ``--depth auto`` decides the root's split inside ``tree`` (after
the root's fit) and each child's in :func:`train_node`; each would-be child is then trained only when its
parent's fit does not already hold its frames (one-sided split, :func:`worldtree.tree.adaptive.decide_child`):
the parent renders the frames of a child left out.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import tempfile
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Literal

import torch

from methods.base import (
    BASE_ABLATIONS,
    BASE_STAGES,
    ROOT_STAGES,
    BaseConfig,
    BaseMethod,
    BaseState,
    bracket_time,
    paper_config,
    quick_config,
    smoke_config,
    steps_for_frames,
)
from methods.model_folder import read_model_json
from methods.plugin import Grid, GridPoint, MethodOption
from methods.registry import MethodSpec, register_method, settings_of
from methods.stages import Ablation, Stage
from worldtree.budget import BudgetConfig, inherited_prune_due, negligible
from worldtree.dynamic import between_path, gaussians_at, halfway
from worldtree.gaussians import GaussianSet, inverse_sigmoid
from worldtree.infra.atomic import atomic_write_json
from worldtree.infra.config_json import read_config, write_config
from worldtree.infra.errors import SettingError, UserError
from worldtree.infra.torchfile import save_torch
from worldtree.optim import GroupedAdam, ScaledLR
from worldtree.pixels import unit_float
from worldtree.plateau import PlateauRule
from worldtree.render import rasterize
from worldtree.stages.photometric import PhotometricConfig, PhotometricFit, anchored_depth_l1
from worldtree.strategy import DensifyStrategy, remove
from worldtree.trainer import TrainContext, Trainer, TrainerConfig, TrainSummary
from worldtree.tree.adaptive import AutoSplitConfig, assess_fit, moving_depth_conf
from worldtree.tree.build import TreeConfig, TreeResult, grow_tree, node_output, read_node_input
from worldtree.tree.inherit import InheritConfig
from worldtree.tree.node import NodeState, distinct_gaussians, same_gaussians, share_static_model
from worldtree.tree.parallel import LayerRunner, NodeContext, ParallelConfig
from worldtree.tree.sac import (
    AncestorCopy,
    AncestorPolicy,
    ancestor_optimizer,
    chain_cache_states,
    chain_gaussians_at,
    restore_chain_caches,
    truncate_chain,
)
from worldtree.tree.split import SPLIT_STRATEGIES, ProfileAccumulator, flow_profile
from worldtree.tree.tpt import Interval, TemporalPartitionTree, depth_of, parent
from worldtree.tree.validate import HoldoutConfig, Verdict, holdout_frames, keep_child

__all__ = ["ABLATIONS", "NodeFit", "NodeTrainConfig", "WorldTreeConfig", "WorldTreeMethod", "train_node"]

ABLATIONS = ("ba", "sw", "tpt", "sac")
"""Ablation names of ``--ablate`` (the paper's ablation table columns)."""


#: Settings of the children only (a tree that does not grow never reads them).
NODE_FIELDS = ("chain_length", "split", "layer_steps", "min_len", "inherit_caps", "inherit_opacity",
               "ancestors_optimised", "max_workers", "sequential", "node_steps_per_frame", "node_static_lr",
               "ancestor_lr", "lambda_parent_depth", "node_densify")  # fmt: skip
#: Every setting read only from the tree stage on: two runs that differ in these alone train the same root.
TREE_FIELDS = ("depth", "auto_depth", "auto_split", "holdout", *NODE_FIELDS)


@dataclass
class WorldTreeConfig(BaseConfig):
    """WorldTree settings: the Base method's (root) plus the tree's. ``steps`` is the root's photometric fit.

    The tree's defaults are the library's (``TreeConfig``, ``InheritConfig``, ``AncestorPolicy``): declared
    there once and read here, so the two cannot drift apart."""

    depth: int | Literal["auto"] = TreeConfig.depth
    """Deepest tree layer (0: the root only; the paper: 2), or auto: split a trained node only where the
    measured criterion of auto_split says its frames need it (also turns on the Gaussian budget, early stop
    and node_steps_per_frame of the children unless they are set; the root keeps them off unless set)."""
    auto_depth: bool = field(init=False, default=False, metadata={"derived_from": "depth"})
    """Whether ``depth`` is ``"auto"`` (derived, not a setting: set ``depth``; kept as a field so that the
    recorded config of a run, and its folder's check on resuming, stay as they were)."""
    auto_split: AutoSplitConfig = field(default_factory=AutoSplitConfig)
    """Thresholds of the ``--depth auto`` criterion and its depth bound."""
    chain_length: int | None = None
    """Ancestors rendered at test time (None: the whole chain; 0: none). Training always uses the chain."""
    split: str = TreeConfig.split
    """Split strategy: ``binary``, ``gradient`` (position-gradient profile of the node) or ``flow``."""
    sequential: bool = False
    """Train each layer's nodes one after another in this process instead of in worker processes."""
    max_workers: int | None = None
    """Most nodes trained at once (None: the CPU cores, or the GPUs)."""
    layer_steps: tuple[int, ...] = (2000, 2000)
    """Photometric steps of a child node by its depth 1, 2, ... (deeper layers: the last value). The root's
    are ``steps`` (paper NVIDIA-LS: 4000 / 2000 / 2000)."""
    node_steps_per_frame: bool | None = None
    """Cap a child node's steps at the root's steps per frame times its own frames, ``ceil(steps * T_node /
    T)``, so every node gets at most the root's epochs over its frames (quick preset, 40 frames: a 20-frame
    node keeps its 300 steps, a 10-frame one trains 150); ``layer_steps`` stays the upper bound and the
    plateau stop still applies. None: on with ``--depth auto``, off for fixed depths (the paper's steps)."""
    min_len: int = TreeConfig.min_len
    """Nodes with fewer frames are leaves (12)."""
    inherit_caps: tuple[int, ...] = InheritConfig.caps
    """Most dynamic Gaussians a child inherits, by depth 1, 2, ... (the root's cap is ``dynamic_max_init``)."""
    inherit_opacity: float = InheritConfig.opacity_cap
    """Inherited dynamic opacities are reset to at most this."""
    ancestors_optimised: int = 0
    """The nearest this many ancestors train with a node; deeper ones are frozen. 0: none (the authors
    optimise the nearest two, :class:`~worldtree.tree.sac.AncestorPolicy`; measured here to over-fit a
    child's few views, docs/worldtree_method.md "The tree against its root")."""
    node_static_lr: float = 0.0
    """Learning rates of a child node's copy of the static background, as a fraction of the root's. 0: every
    node renders the background the root fitted from all frames, unchanged (the authors re-fit it per node:
    1.0; measured here to smear the background seen from the test camera)."""
    ancestor_lr: float = 1.0
    """Learning rates of the optimised ancestors, as a fraction of the root's initial ones (constant)."""
    lambda_parent_depth: float = 1.0
    """Weight of a child's depth anchor (not in the paper): the relative L1 of its rendered depth to its
    parent's at each of its frames, per pixel weighted by one minus the depth prior's confidence, so that
    where the prior measures no depth (classical priors: moving and filled pixels) a child keeps the depth
    its parent fitted over more frames and cameras, and where it does (exact or imported depth) the child
    follows the prior. 0 = off (the paper's children). Measured in docs/worldtree_method.md."""
    node_densify: bool = False
    """Density control in each child over its own dynamic Gaussians: the root's dynamic schedule scaled to the
    child's steps (never the background or the ancestors). Off: a child only refines the Gaussians it
    inherits, at most ``inherit_caps`` (the paper's children re-run 3DGS's density control)."""
    holdout: HoldoutConfig = field(default_factory=HoldoutConfig)
    """Held-out validation of each child (:mod:`worldtree.tree.validate`): some of its frames are kept from
    its training and it is kept only where it draws them better than its parent."""

    @classmethod
    def ablation_names(cls) -> tuple[str, ...]:
        """``ba``, ``sw`` as in Base, plus ``tpt`` (root only) and ``sac`` (no ancestors)."""
        return ABLATIONS

    def adaptive_default(self) -> bool:
        """Budget and early stop follow ``--depth auto`` unless set explicitly."""
        return self.auto_depth

    def __post_init__(self) -> None:
        super().__post_init__()
        if isinstance(self.depth, str):
            if self.depth.strip().lower() == "auto":
                self.depth = "auto"
            elif self.depth.strip().isdigit():
                self.depth = int(self.depth)
            else:
                raise SettingError.of_field(self, "depth", "give an integer >= 0 or 'auto'")
        self.auto_depth = self.depth == "auto"
        if isinstance(self.depth, int) and self.depth < 0:
            raise SettingError.of_field(self, "depth", "must be >= 0 (0 = the root only)")
        if self.chain_length is not None and self.chain_length < 0:
            raise SettingError.of_field(self, "chain_length", "must be >= 0, or None for the whole chain")
        if self.split not in SPLIT_STRATEGIES:
            raise SettingError.of_field(self, "split", f"choose one of {', '.join(SPLIT_STRATEGIES)}")
        if not self.layer_steps or min(self.layer_steps) < 1:
            raise SettingError.of_field(self, "layer_steps", "need one or more values >= 1")
        self.layer_steps = tuple(int(s) for s in self.layer_steps)
        self.inherit_caps = tuple(int(c) for c in self.inherit_caps)

    @property
    def tree_depth(self) -> int:
        """The depth actually grown (0 under ``ablate tpt``)."""
        if "tpt" in self.ablate:
            return 0
        return self.auto_split.max_depth if self.auto_depth else int(self.depth)

    def steps_at(self, depth: int) -> int:
        """Photometric steps of a node at ``depth`` (>= 1)."""
        return self.layer_steps[min(depth, len(self.layer_steps)) - 1]

    def root_budget_on(self) -> bool:
        """The root keeps the budget only when ``budget.enabled`` is set: ``--depth auto`` alone applies it to the
        children. The root's background is what every node and every test view draws; capped by the budget it
        stays below what the scene needs (docs/worldtree_method.md, the family at full size)."""
        return bool(self.budget.enabled)

    def root_early_stop_on(self) -> bool:
        """The root stops at a plateau only when ``early_stop.enabled`` is set (as :meth:`root_budget_on`)."""
        return bool(self.early_stop.enabled)

    def holdout_on(self) -> bool:
        """Whether children are validated on held-out frames (``holdout.enabled``). Never under ``ablate
        sac``: a child without ancestors has no parent render to compare with."""
        return bool(self.holdout.enabled) and "sac" not in self.ablate

    def node_steps_per_frame_on(self) -> bool:
        """Whether children's steps follow their frame count (``node_steps_per_frame``)."""
        return self.auto_depth if self.node_steps_per_frame is None else bool(self.node_steps_per_frame)

    def ignored_settings(self) -> dict[str, str]:
        """The Base method's plus the tree's: every tree setting when no tree grows (depth 0 or ``ablate
        tpt``), ``auto_split`` without ``--depth auto``, ``inherit_caps`` under the Gaussian budget (children
        then inherit everything their frames see)."""
        out = super().ignored_settings()
        if not self.auto_depth:
            out.update(
                settings_of("auto_split", self.auto_split, "the tree's depth is fixed; --depth auto", ())
            )
        if not self.holdout_on():
            out.update(
                settings_of("holdout", self.holdout, "held-out validation is off; --set holdout.enabled=true")
            )
        if self.budget_on():
            out["inherit_caps"] = "the Gaussian budget replaces the caps; --set budget.enabled=false"
        if self.tree_depth == 0:
            why = "no tree grows (depth 0 or --ablate tpt)"
            out.update({k: why for k in NODE_FIELDS})
        return out

    def tree_config(self) -> TreeConfig:
        policy = AncestorPolicy(optimised_nearest=self.ancestors_optimised)
        if self.budget_on():
            # The child keeps what its own frames see (train_node prunes by contribution, then resets the
            # opacities), so it inherits every Gaussian of its interval with the parent's opacities.
            inherit = InheritConfig(caps=(2**62,), opacity_cap=1.0, policy=policy)
        else:
            inherit = InheritConfig(caps=self.inherit_caps, opacity_cap=self.inherit_opacity, policy=policy)
        auto = self.auto_split if self.auto_depth and "tpt" not in self.ablate else None
        return TreeConfig(depth=self.tree_depth, min_len=self.min_len, split=self.split, inherit=inherit,
                          auto=auto)  # fmt: skip


# ------------------------------------------------------------------------------------------ node training
_NO_DENSIFY = DensifyStrategy(refine_start=10**9, refine_stop=10**9, reset_every=0)


@dataclass(frozen=True)
class NodeTrainConfig:
    """What every child node's training needs besides its state (written once per run for the workers)."""

    photometric: PhotometricConfig
    """The root's photometric settings; ``steps``, cameras and density control are set per node."""
    layer_steps: tuple[int, ...]
    """Steps by depth 1, 2, ..."""
    policy: AncestorPolicy
    """Which ancestors train."""
    no_ancestors: bool
    """``ablate sac``: train (and render) without the chain."""
    extent: float
    """Scene extent (world units) for the learning rates."""
    checkpoint_every: int
    log_every: int
    min_len: int = TreeConfig.min_len
    """The tree's minimum interval (for the auto criterion)."""
    auto: AutoSplitConfig | None = None
    """``--depth auto``: decide the node's split after training (None: fixed depth)."""
    budget: BudgetConfig | None = None
    """Contribution pruning of the inherited and trained Gaussians (None: off)."""
    inherit_opacity: float = 0.05
    """Opacity cap applied to the inherited dynamic Gaussians after the contribution pruning (budget on)."""
    early_stop: PlateauRule | None = None
    """Stop the node at a loss plateau (None: run ``steps_at(depth)``)."""
    node_static_lr: float = 1.0
    """Static learning rates of a node as a fraction of the root's (0: the root's background, frozen)."""
    ancestor_lr: float = 1.0
    """The optimised ancestors' constant learning rates as a fraction of the root's initial ones."""
    holdout: HoldoutConfig | None = None
    """Held-out validation of the node (None: off)."""
    lambda_parent_depth: float = 0.0
    """Weight of the node's depth anchor to its parent (``WorldTreeConfig.lambda_parent_depth``, which every
    run writes; 0 here only for node settings written before the anchor existed)."""
    steps_per_frame: float | None = None
    """The root's steps per training frame: a node of ``n`` frames trains at most ``ceil(steps_per_frame *
    n)`` steps (None: ``steps_at(depth)`` whatever its length)."""
    node_densify: bool = False
    """Density control over the node's own dynamic Gaussians (``WorldTreeConfig.node_densify``)."""

    def steps_at(self, depth: int) -> int:
        return self.layer_steps[min(depth, len(self.layer_steps)) - 1]

    def node_steps(self, depth: int, frames: int) -> int:
        """Steps of a node at ``depth`` over ``frames`` frames: ``steps_at(depth)``, capped by
        ``steps_per_frame`` (at least 1)."""
        steps = self.steps_at(depth)
        if self.steps_per_frame is not None:
            steps = min(steps, steps_for_frames(self.steps_per_frame, frames))
        return steps


#: Most memory the frozen ancestors' per-frame Gaussians may hold in a node's memo (14 floats a Gaussian).
_ANCESTOR_MEMO_BYTES = 512 * 2**20


class NodeFit(PhotometricFit):
    """The photometric fit of one tree node: its own static/dynamic/scaffold plus its ancestor chain.

    ``images`` etc. are the node's frames (node-local indexing); ``t0`` is the node's first global frame, at
    which ancestors are evaluated (each at its own local time). The trainable ancestors get one Adam with
    constant rates (:func:`worldtree.tree.sac.ancestor_optimizer`); they are not regularised or densified.
    A per-frame position-gradient profile of the node's dynamic Gaussians is gathered for the gradient split.
    """

    def __init__(self, *args, t0: int, chain: list[AncestorCopy], policy: AncestorPolicy,
                 static_lr: float = 1.0, ancestor_lr: float = 1.0, holdout: tuple[int, ...] = (),
                 **kwargs):  # fmt: skip
        self.holdout = frozenset(int(i) for i in holdout)
        self.t0 = int(t0)
        self.chain = chain
        self.policy = policy
        self.static_lr = float(static_lr)
        self.ancestor_lr = float(ancestor_lr)
        super().__init__(*args, **kwargs)
        self.profile = ProfileAccumulator(self.T)
        self._frame = 0
        self.anchor: tuple[float, torch.Tensor, torch.Tensor] | None = None
        self._build_ancestor_optimizer()

    def _build_ancestor_optimizer(self) -> None:
        c = self.cfg
        lrs = {
            "gauss.means": c.lr_means * self.extent,
            "gauss.quats": c.lr_quats,
            "gauss.log_scales": c.lr_scales,
            "gauss.opacity_logits": c.lr_opacity,
            "gauss.sh0": c.lr_sh0,
            "gauss.skin_corr": c.lr_skin_corr,
            "scaffold.pos": c.lr_node_pos * self.extent,
            "scaffold.quat": c.lr_node_quat,
            "scaffold.sigma_logit": c.lr_node_sigma,
        }
        lrs = {k: v * self.ancestor_lr for k, v in lrs.items()}
        for a in self.chain:
            a.apply_policy(self.policy)
            a.refresh_cache()
        self.anc_opt = ancestor_optimizer(self.chain, self.policy, lrs)
        # Frozen ancestors draw the same Gaussians at a frame every step: deform them once per frame (their
        # re-attachment is deterministic, so the memo stays exact) unless that would hold too much memory.
        n = sum(len(a.dynamic) for a in self.chain)
        frozen = not any(a.trainable for a in self.chain)
        self._anc_memo: dict[int, tuple[torch.Tensor, ...]] | None = (
            {} if frozen and n * self.T * 14 * 4 <= _ANCESTOR_MEMO_BYTES else None
        )

    def _build_optimizers(self) -> None:
        super()._build_optimizers()
        # A frozen background (rate 0) needs no gradient: Adam skips parameters without one, which leaves them
        # exactly as a zero step would, and the backward pass no longer accumulates into them.
        for v in self.static.params.values():
            v.requires_grad_(self.static_lr != 0.0 and v.is_floating_point())
        if self.static_lr != 1.0:
            # The node's copy of the background trains at a fraction of the root's rates (0: kept as the root
            # fitted it from every frame; a node sees a few cameras only and would over-fit them).
            st = {k: ScaledLR(v, self.static_lr) for k, v in self._gauss_schedules(self.static).items()}
            self.static_opt = GroupedAdam({k: self.static.params[k] for k in st}, st)

    def gaussians_at(self, t: int, cache=None):
        """Static + own dynamic at node-local frame ``t``, then the ancestors at global ``t0 + t``."""
        anc = self._ancestors_at(int(t))
        own_cache = cache if cache is not None else self.cache
        return gaussians_at(self.static, self.dynamic, self.scaffold, t, own_cache, anc)

    def _ancestors_at(self, t: int):
        """The chain's Gaussians at node-local frame ``t`` (memoised per frame while the chain is frozen)."""
        if self._anc_memo is None:
            return chain_gaussians_at(self.chain, self.t0 + t)
        if t not in self._anc_memo:
            with torch.no_grad():
                self._anc_memo[t] = chain_gaussians_at(self.chain, self.t0 + t)
        return self._anc_memo[t]

    def coupling_extra(self, j: int):
        """The ancestors as they draw node-local frame ``j`` (fixed in the neighbour coupling)."""
        with torch.no_grad():
            return self._ancestors_at(int(j))

    def track_means_at(self, j: int) -> torch.Tensor:
        """The root's track loss also colours the ancestors' Gaussians by their pixel in frame ``j``."""
        return self.gaussians_at(j)[0]

    def _next_frame(self) -> int:
        if not self.holdout:
            self._frame = super()._next_frame()
            return self._frame
        if not self.queue:  # one pass over the training frames, the held-out ones left out
            perm = torch.randperm(self.T, generator=self.order).tolist()
            self.queue = [i for i in perm if i not in self.holdout]
        self._frame = self.queue.pop()
        return self._frame

    @torch.no_grad()
    def render_frame(self, i: int, gaussians=None) -> torch.Tensor:
        """``[H, W, 3]`` render of node-local frame ``i`` from its camera (``gaussians``: another render list,
        e.g. the parent's)."""
        H, W = self.images.shape[1:3]
        return self.render(self.Ks[i], self.cameras_detached(i), W, H, i, gaussians=gaussians).rgb.clamp(0, 1)

    def set_depth_anchor(self, weight: float, depth: torch.Tensor, pixel_weight: torch.Tensor) -> None:
        """Hold the node's rendered depth near ``depth`` ``[T, H, W]`` (world units, 0 = none) with per-pixel
        weights ``pixel_weight`` ``[T, H, W]`` in [0, 1], the term weighted ``weight``
        (:func:`anchored_depth_l1`; ``lambda_parent_depth``)."""
        self.anchor = (float(weight), depth, pixel_weight)

    def frame_losses(self, i: int, step: int):
        loss, parts, out = super().frame_losses(i, step)
        if self.anchor is not None:
            lam, depth, pixel_weight = self.anchor
            la = anchored_depth_l1(out.depth, out.alpha, depth[i], pixel_weight[i])
            loss = loss + lam * la
            parts["parent_depth"] = float(la.detach())
        return loss, parts, out

    def optimizer_step(self, step: int, out) -> dict[str, float]:
        g = self.dynamic.params["means"].grad if len(self.dynamic) else None
        if g is not None:
            self.profile.add(self._frame, g.norm(dim=-1).sum())
        if self.anc_opt is not None:
            self.anc_opt.set_step(step)
            self.anc_opt.step()
            self.anc_opt.zero_grad()
        res = super().optimizer_step(step, out)
        if self.cfg.reattach_every > 0 and step % self.cfg.reattach_every == 0:
            for a in self.chain:
                a.refresh_cache()
        return res

    def prune_chain(self, threshold: float, total_frac: float | None = None) -> dict[str, list[int]]:
        """Remove from this node's ancestor copies the Gaussians whose contribution over the node's frames is
        below ``threshold`` (the copies only ever render this node's frames, and its children's, which lie
        inside), with ``total_frac`` at most as many as sum to that fraction of a frame's pixels over the whole
        chain. Call after training: the ancestor optimiser is rebuilt without moments."""
        contrib = self.contributions()
        at = len(self.static) + len(self.dynamic)
        H, W = self.images.shape[1:3]
        total = None if total_frac is None else float(total_frac) * H * W
        chosen = negligible(contrib[at:], threshold, total)  # one shared total for the whole chain
        before, after, k = [], [], 0
        for a in self.chain:
            n = len(a.dynamic)
            drop = chosen[k : k + n]
            k += n
            before.append(n)
            if bool(drop.any()):
                remove(a.dynamic, None, {}, drop)
                a.refresh_cache()
            after.append(len(a.dynamic))
        self._build_ancestor_optimizer()
        return {"nodes": [a.node for a in self.chain], "before": before, "after": after}

    def state_dict(self) -> dict[str, Any]:
        d = super().state_dict()
        d["chain"] = [a.to_payload() for a in self.chain]
        d["anc_opt"] = self.anc_opt.state_dict() if self.anc_opt is not None else None
        d["profile"] = self.profile.state_dict()
        d["chain_caches"] = chain_cache_states(self.chain)
        return d

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        dev = self.images.device
        self.chain[:] = [AncestorCopy.from_payload(a, dev) for a in state["chain"]]
        self._build_ancestor_optimizer()
        restore_chain_caches(self.chain, state.get("chain_caches"), dev)
        if self.anc_opt is not None and state["anc_opt"] is not None:
            self.anc_opt.load_state_dict(state["anc_opt"])
        self.profile.load_state_dict(state["profile"])


_CONTEXT: dict[str, Any] = {}


def _load_context(tree_dir: Path, device: str) -> tuple[dict[str, torch.Tensor], NodeTrainConfig]:
    """The run's node context (cached per worker process: a worker trains several nodes)."""
    key = f"{tree_dir.resolve()}|{device}"
    if key not in _CONTEXT:
        data = torch.load(tree_dir / "context.pt", map_location=device, weights_only=True)
        cfg = read_config(tree_dir / "node_config.json", NodeTrainConfig)
        _CONTEXT.clear()
        _CONTEXT[key] = (data, cfg)
    return _CONTEXT[key]


def scaled_schedule(strategy: DensifyStrategy, root_steps: int, steps: int) -> DensifyStrategy:
    """``strategy`` with its refine window and period scaled from ``root_steps`` to ``steps`` (the same
    fractions of the fit; a period of at least one step), no opacity reset."""
    f = steps / max(int(root_steps), 1)
    return dataclasses.replace(
        strategy,
        refine_start=round(strategy.refine_start * f),
        refine_stop=round(strategy.refine_stop * f),
        refine_every=max(1, round(strategy.refine_every * f)),
        reset_every=0,
    )


def _node_photometric(cfg: NodeTrainConfig, steps: int) -> PhotometricConfig:
    """The root's photometric settings for a child node of ``steps`` steps: cameras fixed, no migration, and
    no density control unless ``node_densify`` (then over the node's own dynamic Gaussians only: the
    background is shared and the ancestors are tied to their own nodes)."""
    dyn = _NO_DENSIFY
    if cfg.node_densify:
        dyn = scaled_schedule(cfg.photometric.dynamic_strategy, cfg.photometric.steps, steps)
    return dataclasses.replace(
        cfg.photometric,
        steps=steps,
        camera_start_step=steps + 1,
        static_strategy=_NO_DENSIFY,
        dynamic_strategy=dyn,
        node_densify_every=0,
        migrate_every=0,
    )


def _node_fit(state: NodeState, pcfg: PhotometricConfig, data: dict, cfg: NodeTrainConfig, seed: int,
              with_tracks: bool = True, holdout: tuple[int, ...] = ()) -> NodeFit:  # fmt: skip
    """The photometric fit of ``state`` on its own frames of the run's context ``data``."""
    iv = state.interval
    sl = slice(iv.start, iv.end + 1)
    tracks = data["tracks"][sl] if with_tracks and data["tracks"].shape[1] else None
    vis = data["track_vis"][sl] if tracks is not None else None
    return NodeFit(
        pcfg, data["images"][sl], data["depth"][sl], data["Ks"][sl], state.w2cs, state.static, state.dynamic,
        state.scaffold, tracks, vis, cfg.extent, seed=seed, t0=iv.start, chain=state.chain, policy=cfg.policy,
        static_lr=cfg.node_static_lr, ancestor_lr=cfg.ancestor_lr, holdout=holdout,
    )  # fmt: skip


def _prune_inherited(state: NodeState, pcfg: PhotometricConfig, data: dict, cfg: NodeTrainConfig, seed: int):
    """Budget on: keep the dynamic Gaussians this node's frames see (contributions with the parent's
    opacities), then reset the inherited opacities to ``inherit_opacity`` as without the budget. The static
    background is never pruned in a child: the test cameras see parts of it that none of a child's few frames
    do. Returns the pruning counts."""
    pre = _node_fit(state, pcfg, data, cfg, seed, with_tracks=False)
    counts = pre.prune_negligible(
        cfg.budget.prune_contribution, total_frac=cfg.budget.prune_total_frac, static=False
    )
    state.static, state.dynamic = pre.static, pre.dynamic
    cap = inverse_sigmoid(torch.tensor(cfg.inherit_opacity)).item()
    with torch.no_grad():
        state.dynamic.params["opacity_logits"].clamp_(max=cap)
    return counts


def _parent_view(state: NodeState):
    """``at(t_global)``: the render list of the node's parent as it is now (before the node trains): the
    static copy and the ancestor chain, snapshotted (training the node changes its copies)."""
    static = GaussianSet({k: v.detach().clone() for k, v in state.static.params.items()})
    chain = [a.copy() for a in state.chain]

    def at(t_global: int):
        anc = chain_gaussians_at(chain, int(t_global))
        own = (static.means, static.quats, static.log_scales, static.opacities, static.colors)
        parts = [own] if anc is None else [own, anc]
        return tuple(torch.cat(xs) for xs in zip(*parts, strict=True))

    return at


@torch.no_grad()
def _rendered_depths(fit: NodeFit, render_list_at) -> torch.Tensor:
    """``[T, H, W]`` depth (world units; 0 where the accumulated opacity is at most 0.5) of
    ``render_list_at(global frame)`` seen from each of the node's cameras at its frames."""
    H, W = fit.images.shape[1:3]
    out = []
    for i in range(fit.T):
        o = fit.render(fit.Ks[i], fit.cameras_detached(i), W, H, i, gaussians=render_list_at(fit.t0 + i))
        out.append(torch.where(o.alpha > 0.5, o.depth / o.alpha.clamp_min(1e-6), torch.zeros_like(o.depth)))
    return torch.stack(out)


def _validate(fit: NodeFit, parent_at, hold: list[int], hcfg: HoldoutConfig, record: Path,
              summary: TrainSummary) -> tuple[Verdict, int]:  # fmt: skip
    """The node's verdict on its held-out frames against its parent (:func:`keep_child`) and the step it was
    taken at. Written to ``record`` once, so a node resumed after it (while refitting on every frame) reuses it
    instead of judging a model that has seen the held-out frames."""
    if record.exists():
        d = json.loads(record.read_text())
        return Verdict(**{k: d[k] for k in Verdict.__dataclass_fields__}), int(d["end_step"])
    with torch.no_grad():
        # Both models predict frame i from their states at i - 1 and i + 1 (the parent trained on frame i, so
        # its own state at i would be a fit, not a prediction); the opacities are each model's at i.
        child, parent = [], []
        for i in hold:
            mid = fit.gaussians_at(i)
            child.append(
                fit.render_frame(i, halfway(fit.gaussians_at(i - 1), fit.gaussians_at(i + 1), mid[3]))
            )
            g = fit.t0 + i
            pmid = parent_at(g)
            parent.append(fit.render_frame(i, halfway(parent_at(g - 1), parent_at(g + 1), pmid[3])))
    target = [unit_float(fit.images[i]) for i in hold]
    verdict = keep_child(child, parent, target, hold, hcfg.margin)
    atomic_write_json(record, {**verdict.to_dict(), "end_step": summary.end_step})
    return verdict, summary.end_step


def train_node(payload: dict, ctx: NodeContext) -> dict:
    """Train one child node (the :mod:`worldtree.tree.build` node-function contract).

    The node's frames ``[L, R]`` of the run's context are its training data; checkpoints go to
    ``ctx.folder/checkpoints`` so an interrupted node resumes.
    """
    state, depth = read_node_input(payload, ctx.device)
    data, cfg = _load_context(Path(ctx.folder).parent.parent, ctx.device)
    iv = state.interval
    lam = cfg.lambda_parent_depth
    # The parent as handed over (its chain, before ``ablate sac`` drops it): what the depth anchor renders and
    # held-out validation compares with; one snapshot serves both.
    parent_view = _parent_view(state) if state.chain and (lam > 0 or cfg.holdout is not None) else None
    if cfg.no_ancestors:
        state.chain = []
    steps = cfg.node_steps(depth, iv.length)
    pcfg = _node_photometric(cfg, steps)
    t0 = time.perf_counter()
    adaptive: dict[str, Any] = {}
    if cfg.budget is not None:
        adaptive["inherit_prune"] = _prune_inherited(state, pcfg, data, cfg, ctx.seed)
    hold = holdout_frames(iv.length, cfg.holdout.frac) if cfg.holdout is not None and state.chain else []
    parent_at = parent_view if hold else None
    fit = _node_fit(state, pcfg, data, cfg, ctx.seed, holdout=tuple(hold))
    if lam > 0 and parent_view is not None:
        sl = slice(iv.start, iv.end + 1)
        pixel_weight = 1.0 - data["depth_conf"][sl].clamp(0.0, 1.0)
        adaptive["parent_depth_weight_mean"] = float(pixel_weight.mean())
        if adaptive["parent_depth_weight_mean"] > 0:  # a prior that measures every pixel leaves nothing to anchor
            fit.set_depth_anchor(lam, _rendered_depths(fit, parent_view), pixel_weight)
    stop = cfg.early_stop.detector(iv.length) if cfg.early_stop is not None else None

    def train(total: int, rule) -> TrainSummary:
        return Trainer(
            TrainerConfig(steps=total, checkpoint_every=cfg.checkpoint_every, log_every=cfg.log_every),
            fit,
            checkpoint_dir=Path(ctx.folder) / "checkpoints",
            generators={"frame_order": fit.order},
            progress=False,
            description=f"node {state.index}",
            stop=rule,
        ).fit(resume=True)

    summary = train(steps, stop)
    if stop is not None:
        adaptive["early_stop"] = stop.report()
    verdict, refit_steps = None, 0
    if hold:
        verdict, judged = _validate(fit, parent_at, hold, cfg.holdout, Path(ctx.folder) / "holdout.json",
                                    summary)  # fmt: skip
        if verdict.keep and cfg.holdout.refit:
            # The kept child now also trains on the frames it was judged on (at the schedule's final rates).
            fit.holdout = frozenset()
            fit.queue = []
            refit_steps = math.ceil(judged * cfg.holdout.frac)
            summary = train(judged + refit_steps, None)
    if cfg.budget is not None:
        # Inherited dynamic Gaussians (opacity reset) are pruned only once they had steps to recover.
        due = inherited_prune_due(summary.end_step, fit.T, cfg.budget)
        b = cfg.budget
        pruned = fit.prune_negligible(
            b.prune_contribution, dynamic=due, total_frac=b.prune_total_frac, static=False
        )
        adaptive["prune"] = {**pruned, "dynamic_due": due}
        adaptive["prune_ancestors"] = fit.prune_chain(b.prune_contribution, b.prune_total_frac)
    state.static, state.dynamic, state.scaffold = fit.static, fit.dynamic, fit.scaffold
    state.chain = fit.chain
    stats = {
        "node": state.index,
        "depth": depth,
        "frames": [iv.start, iv.end],
        "steps": summary.end_step,
        "train_s": time.perf_counter() - t0,
        "final_loss": summary.final_loss,
        "num_static": len(state.static),
        "num_dynamic": len(state.dynamic),
        "num_ancestor_gaussians": sum(len(a.dynamic) for a in state.chain),
        "ancestors": [a.node for a in state.chain],
        "steps_max": steps,
        "steps_layer": cfg.steps_at(depth),
        "steps_per_frame": cfg.steps_per_frame,
        "adaptive": adaptive,
    }
    if verdict is not None:
        stats["holdout"] = verdict.to_dict()
        stats["steps_refit"] = refit_steps
    measured = None
    if cfg.auto is not None:
        sl = slice(iv.start, iv.end + 1)
        assessment = assess_fit(fit, data["masks"][sl], cfg.min_len, cfg.auto, data["depth_conf"][sl])
        stats["auto_split"] = assessment.decision.to_dict()
        measured = assessment.to_payload()
    return node_output(state, fit.profile.profile(), stats, measured)


# ------------------------------------------------------------------------------------------------ method
def _frozen(state: NodeState) -> NodeState:
    """``state`` with no parameter requiring gradients (trained nodes are only rendered from here on; the
    test-pose refinement then back-propagates to the pose alone)."""
    tensors = [*state.static.params.values(), *state.dynamic.params.values()]
    scaffolds = [state.scaffold] + [a.scaffold for a in state.chain]
    for a in state.chain:
        tensors += list(a.dynamic.params.values())
    for scf in scaffolds:
        tensors += [scf.pos, scf.quat, scf.sigma_logit]
    for t in tensors:
        t.requires_grad_(False)
    return state


@dataclass
class WorldTreeState(BaseState):
    """The Base method's state plus the tree's (stage ``tree``)."""

    runner: LayerRunner | None = None
    """Worker pool that trains each layer's nodes (open while the stages run)."""
    tree: TemporalPartitionTree | None = None
    states: dict[int, NodeState] = field(default_factory=dict)
    """Trained node states by node index (1 = the root), rendered from here on."""
    result: TreeResult | None = None
    caches: dict[int, Any] = field(default_factory=dict)
    """Per-node skinning caches of the renderer."""


def _root_state(s: WorldTreeState) -> NodeState:
    fit = s.fit
    T = s.scene.num_frames
    return NodeState(1, Interval(0, T - 1), fit.scaffold, fit.dynamic, fit.static, fit.cameras(), [])


def _node_at(s: WorldTreeState, t: int) -> int:
    """The node that renders frame ``t``: the deepest covering it (a child without a trained state, which an
    older run's model may lack, hands its frames to its parent)."""
    t = min(max(int(t), 0), s.scene.num_frames - 1)
    j = s.tree.covering(t) if s.tree is not None else 1
    while j > 1 and j not in s.states:
        j //= 2
    return j


def tree_node_between(tree: TemporalPartitionTree, a: int) -> int:
    """Index of the node of ``tree`` that renders the time between frames ``a`` and ``a + 1``: the deepest node
    covering ``a`` whose interval also holds ``a + 1`` (its parent chain is walked up when a split falls
    between them)."""
    j = tree.covering(a)
    while j != 1 and not tree.interval(j).contains(a + 1):
        j = parent(j)
    return j


def node_between(s: WorldTreeState, a: int) -> int:
    """The node that draws the time between frames ``a`` and ``a + 1``: :func:`tree_node_between` (the root
    without a tree), its parent where it has no trained state (as :func:`_node_at`)."""
    j = tree_node_between(s.tree, a) if s.tree is not None else 1
    while j > 1 and j not in s.states:
        j //= 2
    return j


def node_opacities_at(st: NodeState, a: int, frac: float, chain_length: int | None) -> torch.Tensor:
    """``[N]`` opacities of tree node ``st``'s render list (static, own dynamic, ancestors nearest first) at the
    time ``a + frac`` (global frames), each set's at its own local time: the temporal falloff evaluated there
    (as the Base method's ``render_between``), not the average of the two frames'."""
    parts = [st.static.opacities, st.dynamic.opacities_at(st.local_time(a) + frac)]
    parts += [c.dynamic.opacities_at(c.local_time(a) + frac) for c in truncate_chain(st.chain, chain_length)]
    return torch.cat(parts)


def _tree_gaussians(s: WorldTreeState):
    """``gaussians_at(t)``: the deepest node covering frame ``t`` with its chain (``chain_length``)."""

    def gaussians_at(t: int):
        t = min(max(int(t), 0), s.scene.num_frames - 1)
        j = _node_at(s, t)
        st = s.states[j]
        if j not in s.caches:
            s.caches[j] = st.dynamic.attach(st.scaffold)
        return st.gaussians_at(t, s.cfg.chain_length, s.caches[j])

    return gaussians_at


def _tree_renderer(s: WorldTreeState):
    """``renderer(K, w2c, W, H, t)``: the deepest node covering frame ``t`` with its chain (``chain_length``);
    sets ``s.gaussians_at`` to the same model."""
    s.gaussians_at = _tree_gaussians(s)

    def render(K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, t: int):
        m, q, ls, o, col = s.gaussians_at(t)
        return rasterize(m, q, ls, o, col, K, w2c, width, height, backend=s.cfg.photometric.backend)

    return render


def _root_only(s: WorldTreeState, root_decision: dict[str, Any] | None = None) -> None:
    """No child: the trained root renders every frame (``root_decision``: the ``--depth auto`` decision that
    kept it a leaf, recorded in ``info["tree"]["auto"]``)."""
    s.tree = TemporalPartitionTree(s.scene.num_frames, s.cfg.min_len)
    s.states = {1: _root_state(s)}
    s.info["tree"] = {"nodes": [1], "layers": [], "note": "root only"}
    if root_decision is not None:
        s.info["tree"]["auto"] = {"1": {**root_decision, "applied": False}}
    s.renderer = _tree_renderer(s)


#: Said once when a fixed-depth tree grows over moving pixels whose depth the prior does not measure.
UNMEASURED_NOTE = (
    "note: the depth prior measures {conf:.0%} of the moving pixels' depth; children have gained over their "
    "root only where it is measured (docs/worldtree_method.md, \"How good a depth the tree's gain needs\"): "
    "import a depth with --depth-maps, or --depth auto keeps the root here"
)


def _grow(s: WorldTreeState, no_ancestors: bool) -> None:
    c = s.cfg
    tcfg = c.tree_config()
    root_decision = root_measured = None
    if tcfg.auto is not None:  # --depth auto: does the trained root need children?
        assessment = assess_fit(s.fit, s.P["epi_mask"].bool(), tcfg.min_len, tcfg.auto, s.P["depth_conf"])
        root_decision, root_measured = assessment.decision.to_dict(), assessment.to_payload()
    conf = moving_depth_conf(s.P["depth_conf"], s.P["epi_mask"])
    if (
        tcfg.max_depth == 0
        or s.scene.num_frames < tcfg.min_len
        or (root_decision is not None and not root_decision["split"])
    ):
        _root_only(s, root_decision)
        s.info["tree"]["moving_depth_conf"] = conf
        return
    if tcfg.auto is None and conf is not None and conf < c.auto_split.min_depth_conf:
        print(UNMEASURED_NOTE.format(conf=conf), file=sys.stderr, flush=True)
    ckpt = s.checkpoint_dir
    tree_dir = (ckpt if ckpt is not None else Path(tempfile.mkdtemp(prefix="worldtree-tree-"))) / "tree"
    tree_dir.mkdir(parents=True, exist_ok=True)
    _write_context(s, tree_dir, no_ancestors)
    root = _root_state(s)
    root_cpu = NodeState.from_payload(root.to_payload(), "cpu")
    flow = flow_profile(s.priors.flow, s.priors.epi_mask) if c.split == "flow" else None
    prof = _root_profile(s.fit) if c.split == "gradient" else None
    res = grow_tree(root_cpu, tcfg, s.runner, tree_dir, seed=c.seed, root_profile=prof, flow=flow,
                    root_decision=root_decision, root_measured=root_measured)  # fmt: skip
    s.result, s.tree = res, res.tree
    s.states = {1: root}
    for j, st in res.states.items():
        if j != 1:
            s.states[j] = _frozen(NodeState.from_payload(st.to_payload(), s.device))
    share_static_model(s.states)
    s.info["tree"] = _tree_info(s, res)
    s.info["tree"]["moving_depth_conf"] = conf
    if tcfg.auto is not None:
        s.info["tree"]["auto"] = {str(j): d for j, d in res.decisions.items()}
    s.renderer = _tree_renderer(s)


def _tree_info(s: WorldTreeState, res: TreeResult) -> dict[str, Any]:
    tree = s.tree
    return {
        "nodes": sorted(s.states),
        "intervals": {str(j): [tree.interval(j).start, tree.interval(j).end] for j in s.states},
        "renders": {
            str(j): [[iv.start, iv.end] for iv in tree.own_frames(j)] for j in tree.rendering_nodes()
        },
        "splits": {str(j): {"point": ch.point, "fallback": ch.fallback} for j, ch in res.splits.items()},
        "rejected": res.rejected,
        "layers": [
            {
                "depth": r.depth,
                "mode": r.mode,
                "workers": r.workers,
                "wall_s": r.wall_s,
                "node_seconds": r.node_seconds,
                "nodes_s": {str(n.node): n.wall_s for n in r.nodes},
                "nodes_cpu_s": {str(n.node): n.cpu_s for n in r.nodes},
            }
            for r in res.layers
        ],
        "node_stats": {str(j): st for j, st in res.stats.items()},
    }


def _write_context(s: WorldTreeState, tree_dir: Path, no_ancestors: bool) -> None:
    """What every node trains on (``context.pt``, plain tensors) and its settings (``node_config.json``)."""
    sc, c = s.scene, s.cfg
    data = {
        "images": sc.images.detach().cpu().contiguous(),
        "depth": s.depth.detach().float().cpu().contiguous(),
        "Ks": sc.Ks.detach().float().cpu(),
        "tracks": s.tracks.detach().float().cpu().contiguous(),
        "track_vis": s.track_vis.detach().cpu().contiguous(),
        "masks": s.P["epi_mask"].detach().bool().cpu().contiguous(),
        "depth_conf": s.P["depth_conf"].detach().float().cpu().contiguous(),
    }
    save_torch(tree_dir / "context.pt", data)
    tcfg = c.tree_config()
    ncfg = NodeTrainConfig(
        photometric=c.photometric_config(),
        layer_steps=c.layer_steps,
        policy=tcfg.inherit.policy,
        no_ancestors=no_ancestors,
        extent=s.fit.extent,
        checkpoint_every=c.checkpoint_every,
        log_every=c.log_every,
        min_len=c.min_len,
        auto=tcfg.auto,
        budget=c.budget if c.budget_on() else None,
        inherit_opacity=c.inherit_opacity,
        early_stop=c.early_stop if c.early_stop_on() else None,
        steps_per_frame=c.photometric_steps(sc.num_frames) / sc.num_frames if c.node_steps_per_frame_on() else None,
        node_static_lr=c.node_static_lr,
        ancestor_lr=c.ancestor_lr,
        holdout=c.holdout if c.holdout_on() else None,
        lambda_parent_depth=c.lambda_parent_depth,
        node_densify=c.node_densify,
    )
    write_config(tree_dir / "node_config.json", ncfg)


def _root_profile(fit: PhotometricFit) -> torch.Tensor:
    """``[T]`` position-gradient profile of the trained root for the gradient split: the norm of the
    dynamic means' gradient of each frame's photometric loss, summed over Gaussians (one pass over the
    frames; the Base method's fit does not gather it while training)."""
    acc = ProfileAccumulator(fit.T)
    means = fit.dynamic.params["means"]
    if len(fit.dynamic) == 0:
        return acc.profile()
    for i in range(fit.T):
        loss, _, _ = fit.frame_losses(i, 1)  # step 1: no track term, as in most steps
        (g,) = torch.autograd.grad(loss, [means], allow_unused=True)
        if g is not None:
            acc.add(i, g.norm(dim=-1).sum())
    return acc.profile()


def stage_tree(s: WorldTreeState) -> None:
    """Split, inherit and train the layers ``1 .. depth`` below the trained root; render through the tree."""
    _grow(s, no_ancestors=False)


def stage_tree_no_ancestors(s: WorldTreeState) -> None:
    """``ablate sac``: the tree grows, but every node trains and renders without its ancestors."""
    _grow(s, no_ancestors=True)


def stage_tree_root_only(s: WorldTreeState) -> None:
    """``ablate tpt``: no tree; the root renders every frame (the Base method's model, rendered as node 1)."""
    _root_only(s)


#: WorldTree: the Base method's stages with ``tree`` before ``test_pose``.
WORLDTREE_STAGES: tuple[Stage, ...] = (*BASE_STAGES[:-1], Stage("tree", stage_tree), BASE_STAGES[-1])
#: The Base ablations plus ``sac`` and ``tpt`` (``tpt`` last: with both, no tree grows).
WORLDTREE_ABLATIONS: dict[str, Ablation] = {
    **BASE_ABLATIONS,
    "sac": Ablation("tree", Stage("tree", stage_tree_no_ancestors)),
    "tpt": Ablation("tree", Stage("tree", stage_tree_root_only)),
}


class WorldTreeMethod(BaseMethod):
    """The WorldTree method for one scene; implements :class:`methods.registry.Method`."""

    STAGES = WORLDTREE_STAGES
    ABLATIONS = WORLDTREE_ABLATIONS
    STATE = WorldTreeState
    MODEL_NAME = "worldtree"
    cfg: WorldTreeConfig
    state: WorldTreeState

    def fit(self, ctx: TrainContext) -> TrainSummary:
        """The stages with the tree's worker pool open (its workers start while the root trains)."""
        c = self.cfg
        pcfg = ParallelConfig(sequential=c.sequential, max_workers=c.max_workers, device=self.device.type)
        with LayerRunner(pcfg, train_node) as runner:
            self.state.runner = runner
            if c.tree_depth >= 1:
                runner.warm_up(2)  # worker start-up overlaps the root's training
            try:
                return super().fit(ctx)
            finally:
                self.state.runner = None

    # ------------------------------------------------------------------ outputs
    def node_at(self, time: float) -> int | None:
        """The tree node (1 = root) that renders ``time`` (clamped to the training frames); for a fractional
        ``time``, the node that :meth:`render_between` draws it with (:func:`node_between`)."""
        a, frac = bracket_time(time, self.state.scene.num_frames)
        return _node_at(self.state, a) if frac == 0.0 else node_between(self.state, a)

    @torch.no_grad()
    def render_between(
        self, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, time: float
    ) -> torch.Tensor:
        """The Base method's :meth:`~methods.base.BaseMethod.render_between`, drawn by the node that holds both
        frames ``a = floor(time)`` and ``a + 1`` (:func:`node_between`) with its chain (``chain_length``),
        every Gaussian between its two positions (on the cubic through the frames around them too, those of
        the node's interval, with ``between_frames`` 4) and the opacities at ``time``, each set's at its own
        local time (:func:`node_opacities_at`)."""
        s = self.state
        a, frac = bracket_time(time, s.scene.num_frames)
        if frac == 0.0:
            return self.render(K, w2c, width, height, a)
        j = node_between(s, a)
        st = s.states[j]
        if j not in s.caches:
            s.caches[j] = st.dynamic.attach(st.scaffold)
        offsets = (-1, 0, 1, 2) if s.cfg.between_frames == 4 else (0, 1)
        lists = {
            d: st.gaussians_at(a + d, s.cfg.chain_length, s.caches[j])
            for d in offsets
            if st.interval.start <= a + d <= st.interval.end  # the node's own frames only
        }
        m, q, ls, o, c = between_path(lists, node_opacities_at(st, a, frac, s.cfg.chain_length), frac)
        pose = self.model_w2c(w2c, time)  # placed at the fractional time: the residuals drift with it
        out = rasterize(m, q, ls, o, c, K.to(self.device, torch.float32), pose, width, height,
                        backend=s.cfg.photometric.backend)  # fmt: skip
        return out.rgb.clamp(0.0, 1.0)

    def _frame_colours(self, t: int) -> tuple[torch.Tensor, int, int | None]:
        s = self.state
        j = _node_at(s, t)
        st = s.states[j]
        chain = truncate_chain(st.chain, self.cfg.chain_length)  # as NodeState.gaussians_at
        sh0 = [st.static.params["sh0"], st.dynamic.params["sh0"], *[a.dynamic.params["sh0"] for a in chain]]
        return torch.cat(sh0), len(st.static), j

    def _train_w2c(self, frame: int) -> torch.Tensor:
        """The pose of training frame ``frame`` in the node that renders it (children keep their cameras)."""
        st = self.state.states[_node_at(self.state, frame)]
        return st.w2cs[st.local_time(min(max(frame, st.interval.start), st.interval.end))]

    def load_model(self, folder: Path) -> None:
        """The Base method's files (the root, the refined test poses, the Sim(3)), then every node's state from
        ``tree/node<j>.pt`` and the tree from ``model.json``; frames render through the tree as in the run."""
        folder = Path(folder)
        super().load_model(folder)
        s = self.state
        info = read_model_json(folder, self.MODEL_NAME)
        s.tree = TemporalPartitionTree.from_dict(info["tree"]) if info.get("tree") else None
        nodes = sorted((folder / "tree").glob("node*.pt"))
        if not nodes:
            raise UserError(f"{folder / 'tree'}: no node states; finish the run with `wtbench run` first")
        if not (folder / "tree" / "node1.pt").is_file():
            raise UserError(f"{folder / 'tree' / 'node1.pt'}: missing; re-run with `wtbench run --force`")
        root = _frozen(NodeState.load(folder / "tree" / "node1.pt", self.device))
        s.states = {1: root}
        for p in nodes:
            if p.stem != "node1":  # a child saved with the shared background gets the root's, loaded once above
                s.states[int(p.stem[4:])] = _frozen(NodeState.load(p, self.device, root.static))
        share_static_model(s.states)  # files written before the sharing hold copies: one model again
        s.caches = {}
        s.renderer = _tree_renderer(s)

    def save_model(self, folder: Path) -> None:
        folder = Path(folder)
        s = self.state
        super().save_model(folder)  # the root (node 1) in the Base method's files
        root = s.states.get(1)
        for j, st in s.states.items():
            shared = 1 if j != 1 and root is not None and same_gaussians(st.static, root.static) else None
            st.save(folder / "tree" / f"node{j}.pt", static_shared_with=shared)
        atomic_write_json(
            folder / "model.json",
            {
                "method": "worldtree",
                "frames": s.scene.num_frames,
                "tree": s.tree.to_dict() if s.tree is not None else None,
                "nodes": sorted(s.states),
                "chain_length": self.cfg.chain_length,
                "ablate": list(self.cfg.ablate),
                "sim3_given_to_optimised": s.sim3.to_dict() if s.sim3 is not None else None,
                "files": {
                    "tree/node<j>.pt": "worldtree.tree.node.NodeState.load (node j with its ancestor copies)",
                    "static_gaussians.pt, dynamic_gaussians.pt, scaffold_cameras.pt": "the root (Base method)",
                },
            },
        )

    def stats(self) -> dict[str, Any]:
        s = self.state
        out = super().stats()
        rendering = s.tree.rendering_nodes() if s.tree is not None else [1]
        rendering = [j for j in rendering if j in s.states] or [1]
        # Model size: the distinct Gaussians the rendering nodes draw (the leaves, and the parent of a one-sided
        # split, which renders the frames of the child left out): the shared background once.
        n_g = distinct_gaussians(s.states, rendering)
        root = s.states.get(1)
        out.update(
            {
                "num_gaussians": n_g if s.states else out["num_gaussians"],
                "num_scaffold_nodes": root.scaffold.M if root is not None else 0,
                "num_tree_nodes": len(s.states),
                "tree_depth": max((depth_of(j) for j in s.states), default=0),
                "ablate": list(self.cfg.ablate),
                "chain_length": self.cfg.chain_length,
                "split": self.cfg.split,
                "sequential": self.cfg.sequential,
            }
        )
        return out


# --------------------------------------------------------------------------------------------- the plug-in
#: `wtbench run` options of their own, in run-folder-name order (``quick-noba-depth3-chain1-splitflow-seq``).
OPTIONS = (
    MethodOption("depth", "depth"),
    MethodOption("chain_length", "chain"),
    MethodOption("split", "split"),
    MethodOption("sequential", "seq"),
)


def _ablation_rows() -> list[GridPoint]:
    """The paper's ablation table, (BA, SW) x (TPT, SAC): BA/SW in {off/off, on/off, on/on}, TPT/SAC likewise."""
    rows = []
    for ba, sw in ((False, False), (True, False), (True, True)):
        for tpt, sac in ((False, False), (True, False), (True, True)):
            ablate = [n for n, on in (("ba", ba), ("sw", sw), ("tpt", tpt), ("sac", sac)) if not on]
            if not tpt:
                ablate.remove("sac")  # root only: SAC has no ancestors to use, `tpt` says it all
            flags = "".join("+" if on else "-" for on in (ba, sw, tpt, sac))
            label = f"BA{flags[0]} SW{flags[1]} TPT{flags[2]} SAC{flags[3]}"
            rows.append(GridPoint(label, {"ablate": sorted(ablate)} if ablate else {}))
    return rows


def _depths(depths) -> list[GridPoint]:
    return [GridPoint(f"depth {d}", {"depth": d}) for d in depths]


#: `wtbench sweep --grid NAME` (the first is the default of `--method worldtree`).
GRIDS = {
    "paper-ablation": Grid("the paper's 9-row ablation: (BA, SW) x (TPT, SAC)", _ablation_rows),
    "depth": Grid("tree depth 0..4 (the paper's depth study)", partial(_depths, range(5))),
    "adaptive": Grid(
        "fixed tree depths 0..3 and --depth auto (criterion-grown tree, Gaussian budget, early stop)",
        partial(_depths, (0, 1, 2, 3, "auto")),
    ),
    "tree": Grid(
        "the root alone (depth 0), fixed depths 1 and 2, and --depth auto: does the tree beat its root?",
        partial(_depths, (0, 1, 2, "auto")),
    ),
    "chain": Grid(
        "chain length 0..4 at depth 4 (the paper's chain-length study)",
        lambda: [GridPoint(f"chain {k}", {"depth": 4, "chain_length": k}) for k in range(5)],
    ),
    "split": Grid(
        "split strategies binary, gradient, flow",
        lambda: [GridPoint(f"split {s}", {"split": s}) for s in SPLIT_STRATEGIES],
    ),
}

register_method(
    MethodSpec(
        name="worldtree",
        description="WorldTree: Base root + Temporal Partition Tree with Spatial Ancestral Chains",
        config_cls=WorldTreeConfig,
        presets={
            "paper": partial(paper_config, WorldTreeConfig, layer_steps=(2000, 2000)),
            "quick": partial(quick_config, WorldTreeConfig, layer_steps=(300, 300), inherit_caps=(1500, 800)),
            "smoke": partial(smoke_config, WorldTreeConfig, layer_steps=(10, 10), inherit_caps=(500, 300)),
        },
        build=WorldTreeMethod,
        options=OPTIONS,
        grids=GRIDS,
        shared_root=dataclasses.replace(ROOT_STAGES, free_fields=TREE_FIELDS),
    )
)
