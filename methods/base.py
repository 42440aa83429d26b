"""The Base dynamic method (MoSca-style global optimisation; the first row group of the paper's ablation).

The method is the ordered list :data:`BASE_STAGES` of named stage functions over one :class:`BaseState`; each
is timed (``method_stats.stages_s`` in ``timing.json``; docs/base_method.md, docs/adding_a_method.md):

1. priors -- :func:`worldtree.priors.compute_priors` (cached under ``SCENE/priors/x<downscale>``, as
   ``wtbench prep``);
2. ba -- :func:`worldtree.stages.bundle_adjust.bundle_adjust` on the static tracks (``ablate ba`` replaces
   it by the given cameras);
3. sw -- static warm-up of the background Gaussians on static pixels (``ablate sw``: no warm-up steps, the
   background starts from the lifted static depth);
4. motion -- the dynamic masks refined with the warm-up model's residual, dynamic tracks relabelled and
   re-chained inside them (``refine_masks`` with ``priors.motion.enabled``; otherwise it keeps the priors');
5. scaffold -- dynamic tracks lifted with the adjusted depth and cameras, gaps filled, scaffold built
   (:func:`worldtree.motion.scaffold.build_scaffold`) and fitted (:mod:`worldtree.stages.scaffold_fit`);
   dynamic Gaussians lifted from the dynamic-mask pixels, each at its own frame;
6. photometric -- joint fit of static + dynamic Gaussians, scaffold and (from a set step) cameras, under the
   Gaussian budget and the loss-plateau stop when they are on (``budget`` / ``early_stop``);
7. prune -- (budget on only) Gaussians of negligible contribution removed;
8. test_pose -- Sim(3) of the given training poses onto the optimised ones and the frames' residuals near
   each time (how any camera the model did not train with is placed), applied to the test camera, then
   photometric refinement per test frame on the test images.

A scene without dynamic content (no dynamic track) gets an empty scaffold and no dynamic Gaussian: the model
is then a static one, and every stage still runs.
"""

from __future__ import annotations

import dataclasses
import io
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from methods.model_folder import read_model_json
from methods.plugin import SharedRoot
from methods.registry import QUICK_FULL_SIZE_PIXELS, CommonConfig, MethodSpec, register_method, settings_of
from methods.stages import Ablation, Stage, run_stages, with_ablations
from methods.static3dgs import scene_extent
from worldtree.budget import BudgetConfig, node_budget
from worldtree.dynamic import DynamicGaussians, between_path, gaussians_at
from worldtree.gaussian_frame import GaussianFrame, RenderMode, render_frame
from worldtree.gaussians import GaussianSet
from worldtree.infra.atomic import atomic_write_bytes, atomic_write_json
from worldtree.infra.errors import SettingError, UserError
from worldtree.infra.heap import release_freed_memory
from worldtree.infra.timing import StageClock
from worldtree.infra.torchfile import load_torch, save_torch
from worldtree.motion.lift import lift_tracks, sample_depth
from worldtree.motion.object_depth import ObjectDepthConfig, object_depths
from worldtree.motion.scaffold import Scaffold, ScaffoldConfig, SkinCache, build_scaffold
from worldtree.motion.track_completion import complete_trajectories
from worldtree.motion.track_depth import ratio_map, smooth_trajectory_depths
from worldtree.plateau import PlateauDetector
from worldtree.priors import Priors, PriorsConfig, compute_priors
from worldtree.priors.api import add_chained_tracks
from worldtree.priors.config import FreeSpaceConfig
from worldtree.priors.dynamic_masks import refine_with_residual
from worldtree.priors.epipolar import label_dynamic_tracks
from worldtree.priors.free_space import free_space_violations
from worldtree.render import rasterize
from worldtree.scene import Scene
from worldtree.stages.bundle_adjust import BAResult, BundleAdjustConfig, bundle_adjust
from worldtree.stages.cameras import Sim3
from worldtree.stages.photometric import (
    PRESET_MOTION_WINDOW,
    PhotometricConfig,
    PhotometricFit,
    quick_photometric_config,
)
from worldtree.stages.scaffold_fit import ScaffoldFitConfig, fit_scaffold
from worldtree.stages.static_warmup import (
    StaticWarmup,
    StaticWarmupConfig,
    lift_pixels,
    quick_static_warmup_config,
)
from worldtree.stages.testview_pose import (
    CameraPlacement,
    FrozenModelRenderer,
    PoseRefineConfig,
    align_sim3,
    coinciding_frame,
    quick_pose_refine_config,
    refine_test_poses,
)
from worldtree.strategy import DensifyStrategy
from worldtree.trainer import Progress, TrainContext, Trainer, TrainerConfig, TrainSummary


def steps_for_frames(per_frame: float, frames: int) -> int:
    """``ceil(per_frame * frames)`` steps for ``frames`` training frames at ``per_frame`` steps each, at least 1."""
    # A hair below the product before rounding up, so that e.g. 15.0 * 40 stays 600 in floating point.
    return max(1, math.ceil(float(per_frame) * int(frames) - 1e-9))


@dataclass
class BaseConfig(CommonConfig):
    """Base method settings (defaults: the ``paper`` preset). ``steps`` is the photometric fit's."""

    steps: int = 4000
    """Photometric-fit steps (NVIDIA-LS root: 4000); with ``steps_per_frame`` the least number."""
    steps_per_frame: float = 0.0
    """When > 0 the photometric fit runs ``max(steps, ceil(steps_per_frame * frames))`` steps, so that a long
    video gets as many visits per frame as a short one (each step fits one frame). 0: ``steps`` whatever the
    video's length (the paper preset). An explicit ``--steps N`` sets it to 0 (exactly N steps)."""
    ablate: tuple[str, ...] = ()
    """Ablated stages (``--ablate``): ``ba`` and/or ``sw`` (the one spelling: ``ba.enabled=false`` /
    ``sw.enabled=false`` are folded in here). Subclasses widen the choice through :meth:`ablation_names`."""
    priors: PriorsConfig = field(default_factory=PriorsConfig)
    """2D priors (sources and settings)."""
    priors_cache: bool = True
    """Cache priors under SCENE/priors/x<downscale> (shared with ``wtbench prep``)."""
    ba: BundleAdjustConfig = field(default_factory=BundleAdjustConfig)
    """Bundle adjustment (2000 steps)."""
    sw: StaticWarmupConfig = field(default_factory=StaticWarmupConfig)
    """Static warm-up (6000 steps)."""
    scaffold: ScaffoldConfig = field(default_factory=ScaffoldConfig)
    """Scaffold construction."""
    scaffold_fit: ScaffoldFitConfig = field(default_factory=ScaffoldFitConfig)
    """Geometric scaffold fit."""
    object_depth: ObjectDepthConfig = field(default_factory=ObjectDepthConfig)
    """Outlined moving objects placed by their size and path (imported masks with the classical depth)."""
    depth_free_space: FreeSpaceConfig = field(default_factory=FreeSpaceConfig)
    """Imported depth outside the dynamic masks that floats in front of the scene, left out of the photometric
    fit's depth loss (a moving object the masks missed; classical depth is never checked). Off by default."""
    photometric: PhotometricConfig = field(default_factory=PhotometricConfig)
    """Joint fit (its ``steps`` field is replaced by ``steps`` above)."""
    test_pose: PoseRefineConfig = field(default_factory=PoseRefineConfig)
    """Test-camera pose refinement (300 / 30 steps)."""
    dynamic_init_stride_px: int = 2
    """Dynamic Gaussians are lifted at dynamic-mask pixels on a grid of this stride in every frame."""
    dynamic_max_init: int = 30_000
    """At most this many initial dynamic Gaussians (the root of the authors' tree starts from 30000)."""
    dynamic_init_opacity: float = 0.1
    """Opacity of the initial dynamic Gaussians."""
    dynamic_time_std: float = 1.0
    """Temporal opacity of the dynamic Gaussians (``worldtree.dynamic``): each starts visible with a Gaussian
    falloff of this standard deviation (frames) around its own frame, learned in the photometric fit; 0 = off
    (the paper's model: visible at every frame). On by default in every preset: it keeps wrongly carried
    copies from blurring every frame (docs/base_method.md, "Temporal opacity")."""
    between_frames: int = 4
    """Frames a time between two training frames is drawn through (:meth:`BaseMethod.render_between`, e.g.
    the leave-one-out protocol's held-out time): 4, every Gaussian on the cubic through its positions at the
    two frames and the ones before and after them (a parabola through three at either end of the video), which
    follows a path that curves (:func:`worldtree.dynamic.between_path`); 2, on the straight line between its
    two positions (before 2026-11-28). Measured: docs/base_method.md, "A time between two frames"."""
    refine_masks: bool = True
    """After the static warm-up, refine the dynamic masks with the warm-up model's residual on every training
    frame (``worldtree.priors.dynamic_masks.refine_with_residual``) and re-chain the dynamic tracks inside
    them; needs ``priors.motion.enabled`` and no imported masks."""
    checkpoint_every: int = 500
    """Checkpoint period of the warm-up and photometric stages."""
    log_every: int = 100
    """Progress period (when not on a terminal)."""

    @classmethod
    def ablation_names(cls) -> tuple[str, ...]:
        """Names accepted by ``--ablate``, in display order."""
        return ("ba", "sw")

    def photometric_steps(self, frames: int) -> int:
        """Steps of the photometric fit on a video of ``frames`` training frames (``steps``, raised by
        ``steps_per_frame``)."""
        if self.steps_per_frame > 0:
            return max(int(self.steps), steps_for_frames(self.steps_per_frame, frames))
        return int(self.steps)

    def photometric_config(self) -> PhotometricConfig:
        """The photometric settings every fit of this run uses (the root and a tree's nodes): the static
        floater removal (``photometric.floater_every``) only with an imported depth, which can measure moving
        objects; the classical depth is a static-world estimate and leaves it off."""
        if self.priors.depth_source == "classical" and self.photometric.floater_every:
            return dataclasses.replace(self.photometric, floater_every=0)
        return self.photometric

    def with_exact_steps(self) -> BaseConfig:
        """``steps`` exactly: ``steps_per_frame`` off (it would raise the count on a long video)."""
        return dataclasses.replace(self, steps_per_frame=0.0) if self.steps_per_frame else self

    def root_budget_on(self) -> bool:
        """Whether these stages (the Base model, a tree's root) fit under the Gaussian budget and prune."""
        return self.budget_on()

    def root_early_stop_on(self) -> bool:
        """Whether the photometric fit of these stages stops at a loss plateau."""
        return self.early_stop_on()

    def reestimates_fitted_import(self) -> bool:
        """Whether the trajectory depth also re-estimates an imported depth: one fitted to the classical depth
        (``priors.depth_import.fit_scale_shift``) under ``scaffold.trajectory_depth_imported``."""
        return self.scaffold.trajectory_depth_imported and self.priors.depth_import.fit_scale_shift

    def ignored_settings(self) -> dict[str, str]:
        """:meth:`CommonConfig.ignored_settings` plus the Base method's: ``photometric.steps`` (filled in from
        ``steps``), ``sw.steps`` under ``ablate sw``, the density caps the Gaussian budget sets, the motion
        discovery settings (and ``refine_masks``) while it is off, the migration settings while it is off, the
        trajectory-depth settings with imported depth (its prior weight while it is off; the fitted-import switch
        without a fitted import), the temporal-std learning rate while temporal opacity is off."""
        out = super().ignored_settings()
        out["photometric.steps"] = "this method sets it from steps; --steps N or --set steps=N"
        if "sw" in self.ablate:
            out["sw.steps"] = "the static warm-up is ablated (0 steps); drop --ablate sw"
        if self.root_budget_on():
            why = "the Gaussian budget sets it; --set budget.enabled=false to cap by hand"
            for part in ("static_strategy", "dynamic_strategy"):
                out[f"photometric.{part}.max_gaussians"] = why
            out["sw.strategy.max_gaussians"] = why
        if not self.priors.motion.enabled:
            why = "motion discovery is off; --set priors.motion.enabled=true"
            out.update(settings_of("priors.motion", self.priors.motion, why))
            out["refine_masks"] = why
        if self.priors.depth_source != "classical" and not self.reestimates_fitted_import():
            why = (
                "trajectory depth re-estimates classical depth only; imported depth is kept on moving objects "
                "(--set scaffold.trajectory_depth_imported=true re-estimates a fitted import too)"
            )
            out["scaffold.trajectory_depth"] = why
            out["scaffold.trajectory_depth_prior"] = why
        elif not self.scaffold.trajectory_depth:
            out["scaffold.trajectory_depth_prior"] = "trajectory depth is off; --set scaffold.trajectory_depth=true"
        if self.priors.depth_source == "classical" or not self.priors.depth_import.fit_scale_shift:
            out["scaffold.trajectory_depth_imported"] = (
                "applies to imported depth fitted to the classical one only (--depth-maps with --depth-fit)"
            )
        if self.priors.depth_source == "classical":
            why = "the classical depth is a static-world estimate and is not checked; applies to --depth-maps"
            out.update(settings_of("depth_free_space", self.depth_free_space, why, skip=()))
            out["photometric.floater_every"] = why
            out["photometric.floater_tolerance"] = why
        else:
            if not self.depth_free_space.enabled:
                why = "--set depth_free_space.enabled=true"
                out.update(settings_of("depth_free_space", self.depth_free_space, why))
            if self.photometric.floater_every <= 0:
                out["photometric.floater_tolerance"] = "floater removal is off; --set photometric.floater_every=N"
        if self.priors.masks_source is None or self.priors.depth_source != "classical":
            why = (
                "objects are placed by size and path only with imported masks (--masks) and the classical depth"
            )
            out.update(settings_of("object_depth", self.object_depth, why, skip=()))
        elif not self.object_depth.enabled:
            out.update(settings_of("object_depth", self.object_depth, "--set object_depth.enabled=true"))
        if self.photometric.migrate_every <= 0:
            why = "static<->dynamic migration is off; --set photometric.migrate_every=N"
            for k in ("migrate_start", "migrate_stop", "migrate_frames", "migrate_residual", "migrate_min_views",
                      "static_move_frac"):  # fmt: skip
                out[f"photometric.{k}"] = why
        if self.dynamic_time_std <= 0:
            out["photometric.lr_time_std"] = "temporal opacity is off; --set dynamic_time_std=S (frames)"
        return out

    def __post_init__(self) -> None:
        allowed = self.ablation_names()
        bad = [a for a in self.ablate if a not in allowed]
        if bad:
            raise SettingError.of_field(self, "ablate", f"choose among {', '.join(allowed)}", shown=bad[0])
        names = set(self.ablate)
        # A stage switched off in its own settings is that stage's ablation: one spelling in the config.
        if not self.ba.enabled:
            names.add("ba")
            self.ba = dataclasses.replace(self.ba, enabled=True)
        if not self.sw.enabled:
            names.add("sw")
            self.sw = dataclasses.replace(self.sw, enabled=True)
        self.ablate = tuple(a for a in allowed if a in names)
        if self.between_frames not in (2, 4):
            raise SettingError.of_field(self, "between_frames", "choose 2 (straight line) or 4 (cubic)")


def paper_config(cls: type[BaseConfig] = BaseConfig, **fields: Any) -> BaseConfig:
    """The paper's schedule: BA 2000, SW 6000, photometric 4000 (cameras from 1500), test pose 300/30, with
    two changes that are not in the paper, both measured in docs/cost.md:

    - the Gaussian budget on (uncapped, the 6,000 warm-up steps grow 4-5 times the Gaussians for no gain; on
      four generated scenes the budget kept a quarter of them at mPSNR +0.02 to +0.28 and PSNR -0.18 to
      +0.19; ``--set budget.enabled=false`` is the paper's model);
    - the photometric fit's motion regularisers on a window of 12 frames per step, as the quick preset's
      (over every frame their cost grows with frames x nodes and dominates the step: 3.4 times the CPU on a
      40-frame scene, most of an hour at 160; ``--set photometric.motion_window=0`` is every frame).

    ``cls`` (a subclass, e.g. WorldTree's) and ``fields`` (its own settings) let a method extend a preset
    without copying it; the same holds for :func:`quick_config` and :func:`smoke_config`."""
    fields.setdefault("budget", BudgetConfig(enabled=True))
    fields.setdefault("photometric", PhotometricConfig(motion_window=PRESET_MOTION_WINDOW))
    return cls(**fields)


#: The quick preset's photometric steps per training frame on videos longer than 40 frames: its 600 steps' rate
#: on 40 frames. At 600 steps whatever the length, a 160-frame video's root saw each frame under 4 times and
#: stayed under-fitted (docs/base_method.md, "Steps per frame on long videos").
QUICK_STEPS_PER_FRAME = 15.0


def quick_config(cls: type[BaseConfig] = BaseConfig, **fields: Any) -> BaseConfig:
    """CPU-friendly schedule for a small scene: BA 300, SW 300, scaffold fit 100, photometric 600 (15 per frame
    on videos of more than 40 frames), test pose 60/10, half resolution (full resolution for a video of at most
    2,000,000 pixels), fewer initial Gaussians."""
    return cls(
        steps=600,
        steps_per_frame=QUICK_STEPS_PER_FRAME,
        downscale=2,
        full_size_pixels=QUICK_FULL_SIZE_PIXELS,
        ba=BundleAdjustConfig(steps=300, max_tracks=4000),
        sw=quick_static_warmup_config(),
        scaffold_fit=ScaffoldFitConfig(steps=100),
        photometric=quick_photometric_config(),
        test_pose=quick_pose_refine_config(),
        dynamic_max_init=4000,
        checkpoint_every=200,
        log_every=50,
        **fields,
    )


def smoke_config(cls: type[BaseConfig] = BaseConfig, **fields: Any) -> BaseConfig:
    """A few steps of every stage (tests and smoke runs; not a meaningful reconstruction)."""
    no_densify = DensifyStrategy(refine_start=10_000, refine_stop=10_000, reset_every=0)
    return cls(
        steps=20,
        ba=BundleAdjustConfig(steps=20),
        sw=dataclasses.replace(
            quick_static_warmup_config(), steps=20, init_max_points=1500, strategy=no_densify
        ),
        scaffold_fit=ScaffoldFitConfig(steps=10),
        photometric=dataclasses.replace(
            quick_photometric_config(),
            camera_start_step=10,
            static_strategy=no_densify,
            dynamic_strategy=DensifyStrategy(refine_start=5, refine_stop=15, refine_every=10, reset_every=0),
        ),
        test_pose=PoseRefineConfig(first_steps=5, next_steps=2),
        dynamic_max_init=1000,
        checkpoint_every=10,
        log_every=10,
        **fields,
    )


@dataclass
class BaseState:
    """The one state the Base method's stages fill in, in stage order (:data:`BASE_STAGES`).

    Tensors live on the method's device; ``T`` training frames of ``H x W`` (the training downscale).
    """

    cfg: BaseConfig
    scene: Scene
    device: torch.device
    ctx: TrainContext = field(default_factory=TrainContext)
    info: dict[str, Any] = field(default_factory=dict)
    """Numbers for ``timing.json``'s method stats."""
    priors: Priors | None = None
    """The 2D priors (stage ``priors``)."""
    P: dict[str, torch.Tensor] = field(default_factory=dict)
    """The priors as tensors: depth [T,H,W], tracks [T,N,2], track_vis [T,N], masks... (stage ``priors``)."""
    ba: BAResult | None = None
    """Bundle adjustment result (stage ``ba``)."""
    w2cs: torch.Tensor | None = None
    """[T, 4, 4] training cameras after BA (world-to-camera)."""
    depth: torch.Tensor | None = None
    """[T, H, W] depth priors times BA's per-frame scale (world units)."""
    extent: float = 1.0
    """Scene extent (world units) from the adjusted cameras."""
    static: GaussianSet | None = None
    """Background Gaussians after the static warm-up (stage ``sw``)."""
    sw_summary: TrainSummary | None = None
    scaffold: Scaffold | None = None
    """Motion scaffold (stage ``scaffold``)."""
    dynamic: DynamicGaussians | None = None
    """Initial dynamic Gaussians (stage ``scaffold``)."""
    tracks: torch.Tensor | None = None
    """[T, N_dyn, 2] dynamic tracks (pixels), with ``track_vis`` [T, N_dyn]."""
    track_vis: torch.Tensor | None = None
    fit: PhotometricFit | None = None
    """The jointly fitted model (stage ``photometric``)."""
    stop: PlateauDetector | None = None
    """The photometric fit's loss-plateau detector (``early_stop`` on; stage ``photometric``)."""
    summary: TrainSummary | None = None
    """The photometric trainer's summary (the run's main training loop)."""
    renderer: Callable[..., Any] | None = None
    """``renderer(K [3,3], w2c [4,4], width, height, t) -> rasterizer output``: the model that renders
    frame ``t`` (the photometric fit; WorldTree's ``tree`` stage replaces it by the tree's)."""
    gaussians_at: Callable[[int], tuple[torch.Tensor, ...]] | None = None
    """``gaussians_at(t) -> (means, quats, log_scales, opacities, colours)``: what ``renderer`` rasterizes at
    frame ``t`` (set with it), so a stage that renders a fixed model many times per frame computes it once."""
    sim3: Any = None
    """Sim(3) from the given training poses to the optimised ones (stage ``test_pose``)."""
    placement: CameraPlacement | None = None
    """How a camera the model did not train with is placed: the Sim(3), then the training frames' residuals
    near its time (stage ``test_pose``, or :meth:`BaseMethod.load_model`)."""
    test_poses: dict[int, torch.Tensor] = field(default_factory=dict)
    """Refined test-camera pose [4, 4] by test time (stage ``test_pose``)."""

    @property
    def checkpoint_dir(self) -> Path | None:
        return self.ctx.checkpoint_dir


def stage_priors(s: BaseState) -> None:
    """2D priors (cached under ``SCENE/priors/x<downscale>``, as ``wtbench prep``)."""
    c = s.cfg
    cache = s.scene.root / "priors" / f"x{c.downscale}" if c.priors_cache else None
    s.priors = compute_priors(s.scene, c.priors, cache)
    s.info["priors"] = dict(s.priors.sources)
    s.info["prior_use"] = prior_use(c, s.priors.sources)
    s.P = s.priors.torch(s.device)


def prior_use(c: BaseConfig, sources: dict[str, str]) -> dict[str, dict[str, Any]]:
    """Where each 2D prior enters the Base stages and with which weight, as this config runs them (recorded
    in ``timing.json`` as ``method_stats.prior_use``): ``{prior: {"source": ..., "used_in": {stage: what}}}``.

    ``what`` names the use and its weight (the config field and its value); a stage switched off by an
    ablation or a zero weight is left out. ``flow`` enters only through the masks and tracks it is chained
    into (stage ``priors``, and ``motion`` when the masks are refined)."""
    # A stage switched off in its own settings is already in ``ablate`` (BaseConfig.__post_init__).
    ba, sw = "ba" not in c.ablate, "sw" not in c.ablate
    ph = c.photometric
    refine = _refines_masks(c)
    depth: dict[str, str] = {}
    if ba:
        depth["ba"] = f"per-frame depth scales of the static tracks, ba.lambda_depth {c.ba.lambda_depth}"
    if sw:
        depth["sw"] = "static Gaussians lifted from it"
        if c.sw.lambda_depth > 0:
            depth["sw"] += f"; relative depth loss, sw.lambda_depth {c.sw.lambda_depth}"
    depth["scaffold"] = (
        "dynamic tracks and Gaussians lifted from it"
        + ("; on moving pixels replaced by the tracks' trajectory depth" if _uses_trajectory_depth(c, sources)
           else "")
    )  # fmt: skip
    if ph.lambda_depth > 0:
        depth["photometric"] = f"scale-and-shift-invariant depth L1, photometric.lambda_depth {ph.lambda_depth}"
        imported = sources.get("depth", "classical") != "classical"
        if imported and ph.floater_every > 0:
            depth["photometric"] += (
                f"; static Gaussians in front of it removed every {ph.floater_every} steps "
                f"(photometric.floater_every, tolerance {ph.floater_tolerance})"
            )
        if c.depth_free_space.enabled and imported:
            depth["photometric"] += (
                "; pixels outside the dynamic masks that float in front of what other frames see left out "
                f"(depth_free_space.tolerance {c.depth_free_space.tolerance})"
            )
    masks = {"sw": f"moving pixels (dilated {c.sw.dilate_px} px) left out of the static warm-up"} if sw else {}
    masks["scaffold"] = "pixels the dynamic Gaussians are lifted from"
    if _uses_object_depth(c, sources):
        masks["scaffold"] += (
            f"; each outlined object's size and path set its depth where the path fit >= {c.object_depth.min_fit}"
        )
        depth["scaffold"] += "; on outlined objects whose path fits, replaced by their size and path"
    if refine:
        masks["motion"] = "refined with the warm-up model's residual"
    tracks = {"ba": f"static tracks, ba.lambda_reproj {c.ba.lambda_reproj}"} if ba else {}
    tracks["scaffold"] = f"dynamic tracks: scaffold nodes and paths, scaffold_fit.lambda_data {c.scaffold_fit.lambda_data}"
    if ph.lambda_track > 0 and ph.track_every > 0:
        tracks["photometric"] = (
            f"rendered correspondence loss every {ph.track_every} steps, photometric.lambda_track {ph.lambda_track}"
        )
    flow = {"priors": "chained into the tracks; epipolar and flow cues of the motion masks"}
    if refine:
        flow["motion"] = "tracks re-chained inside the refined masks"
    out = {"depth": depth, "masks": masks, "tracks": tracks, "flow": flow}
    return {k: {"source": sources.get(k, "classical"), "used_in": v} for k, v in out.items()}


def _refines_masks(c: BaseConfig) -> bool:
    """Whether the motion stage refines the priors' masks (given motion evidence): ``refine_masks`` with motion
    discovery on and no imported masks."""
    return c.refine_masks and c.priors.motion.enabled and c.priors.masks_source is None


def _uses_trajectory_depth(c: BaseConfig, sources: dict[str, str]) -> bool:
    """Whether the scaffold stage replaces the depth of moving pixels by the tracks' trajectory depth: the
    classical prior is a static-world estimate there; imported depth measures the moving objects, unless it was
    fitted to the classical depth and ``scaffold.trajectory_depth_imported`` asks for the re-estimate."""
    if not c.scaffold.trajectory_depth:
        return False
    if sources.get("depth") == "classical":
        return True
    return c.reestimates_fitted_import()


def _uses_object_depth(c: BaseConfig, sources: dict[str, str]) -> bool:
    """Whether outlined objects are placed by size and path: the masks are imported (the classical ones cut
    an object into parts, whose areas say nothing) and the depth is the classical one, which fills moving
    pixels from their static surroundings."""
    return (
        c.object_depth.enabled
        and sources.get("masks", "classical") != "classical"
        and sources.get("depth", "classical") == "classical"
    )


def _object_depth(s: BaseState) -> torch.Tensor:
    """The depth prior ``[T, H, W]`` with the placed objects' pixels set by :func:`object_depths`;
    ``info["object_depth"]``."""
    z, objects = object_depths(s.P["epi_mask"].bool(), s.scene.Ks, s.w2cs, s.cfg.object_depth)
    s.info["object_depth"] = {"objects": objects, "placed": sum(o["placed"] for o in objects)}
    placed = z > 0
    # A placed object's depth is a measurement now: what reads the prior's confidence (a tree child's hold on
    # its parent's depth, `lambda_parent_depth`) follows it there as it follows an imported depth.
    s.P = {**s.P, "depth_conf": torch.where(placed, torch.ones_like(s.P["depth_conf"]), s.P["depth_conf"])}
    return torch.where(placed, z.to(s.depth.dtype), s.depth)


def _adjust(s: BaseState, enabled: bool) -> None:
    ckpt = s.checkpoint_dir
    path = ckpt / "ba.pt" if ckpt is not None else None
    if path is not None and path.is_file():
        d = load_torch(
            path, s.device, missing="no BA result",
            unreadable="unreadable BA result ({error}); delete it to run BA again",
        )  # fmt: skip
        res = BAResult(d["w2cs"], d["depth_scale"], d["track_ids"], d["points"], d["before"], d["after"])
    else:
        P, sc = s.P, s.scene
        res = bundle_adjust(
            P["tracks"].float(), P["track_vis"], ~P["track_dynamic"], P["depth"].float(), sc.Ks, sc.w2cs,
            dataclasses.replace(s.cfg.ba, enabled=enabled), depth_conf=P["depth_conf"].float(),
        )  # fmt: skip
        if path is not None:
            save_torch(
                path,
                {"w2cs": res.w2cs.cpu(), "depth_scale": res.depth_scale.cpu(), "track_ids": res.track_ids.cpu(),
                 "points": res.points.cpu(), "before": res.reproj_px_before, "after": res.reproj_px_after},
            )  # fmt: skip
    s.ba = res
    s.info["ba"] = res.stats()
    s.w2cs = res.w2cs.float()
    s.depth = s.P["depth"].float() * res.depth_scale.float()[:, None, None]
    s.extent = scene_extent(s.w2cs, s.scene.near, s.scene.far)


def stage_ba(s: BaseState) -> None:
    """Tracklet bundle adjustment of the cameras and per-frame depth scales on the static tracks."""
    _adjust(s, enabled=True)


def stage_ba_ablated(s: BaseState) -> None:
    """``ablate ba``: the given cameras and unit depth scales (BA's bookkeeping, no optimisation)."""
    _adjust(s, enabled=False)


def warmup_config(c: BaseConfig, steps: int, height: int, width: int) -> StaticWarmupConfig:
    """The static warm-up's settings for ``steps`` steps on ``height x width`` training images: with the
    Gaussian budget on, its density control stops at the full budget of one view (``node_budget`` at the
    reference error, ``gaussians_per_pixel * H * W``). Uncapped, the paper schedule's 6,000 steps grew 7.5
    Gaussians per pixel of a 160x90 video (docs/cost.md)."""
    sw = dataclasses.replace(c.sw, steps=steps)
    if c.root_budget_on():
        cap = node_budget(width, height, math.inf, c.budget)
        sw = dataclasses.replace(sw, strategy=dataclasses.replace(sw.strategy, max_gaussians=cap))
    return sw


def _warm_up(s: BaseState, steps: int) -> None:
    c = s.cfg
    H, W = s.scene.images.shape[1:3]
    sw_cfg = warmup_config(c, steps, int(H), int(W))
    if c.root_budget_on():
        s.info["sw_max_gaussians"] = sw_cfg.strategy.max_gaussians
    sw = StaticWarmup(
        sw_cfg, s.scene.images, s.P["epi_mask"], s.depth, s.scene.Ks, s.w2cs, s.extent, seed=c.seed
    )
    trainer = Trainer(
        TrainerConfig(steps=sw_cfg.steps, checkpoint_every=c.checkpoint_every, log_every=c.log_every),
        sw,
        checkpoint_dir=s.checkpoint_dir / "sw" if s.checkpoint_dir is not None else None,
        progress=s.ctx.progress,
        description="static warm-up",
    )
    s.sw_summary = trainer.fit(resume=s.ctx.resume)
    s.static = sw.gaussians
    s.info["sw_steps"] = s.sw_summary.end_step


def stage_sw(s: BaseState) -> None:
    """Static warm-up of the background Gaussians on static pixels."""
    _warm_up(s, s.cfg.sw.steps)


def stage_sw_ablated(s: BaseState) -> None:
    """``ablate sw``: no warm-up step; the background starts from the lifted static depth."""
    _warm_up(s, 0)


@torch.no_grad()
def stage_motion(s: BaseState) -> None:
    """Dynamic masks refined with the warm-up model's residual, tracks relabelled and re-chained inside them
    (``refine_masks`` with ``priors.motion.enabled`` and no imported masks; otherwise nothing changes).

    With a checkpoint folder, ``motion.npz`` there keeps the result (masks ``[T, H, W]``, confidence,
    tracks ``[T, N, 2]``, visibility, dynamic labels, the track pieces linked into each track ``[N]``): previews
    and the motion proof read it."""
    c, sc, pri = s.cfg, s.scene, s.priors
    pc = c.priors
    if not (_refines_masks(c) and pri.motion_evidence):
        return
    T, H, W = sc.images.shape[:3]
    st = s.static
    renders = torch.stack(
        [rasterize(st.means, st.quats, st.log_scales, st.opacities, st.colors,
                   sc.Ks[t], s.w2cs[t], W, H, backend=c.sw.backend).rgb.clamp(0, 1) for t in range(T)]
    ).cpu().numpy()  # fmt: skip
    before = pri.epi_mask
    fused = refine_with_residual(
        pri.motion_evidence, sc.images.cpu().numpy(), renders, pri.flow, before, pc.motion, pc.epi
    )
    mask = fused.mask
    n_lk = pri.tracks.shape[1] - pri.num_chained_tracks
    xy, vis = pri.tracks[:, :n_lk], pri.track_vis[:, :n_lk]
    dyn = label_dynamic_tracks(xy, vis, mask, pc.epi.track_min_frames)
    links: dict[str, int] = {}
    depth = s.depth.cpu().numpy() if pri.depth_metric else None
    xy, vis, dyn, n_ch, pieces = add_chained_tracks(
        xy, vis, dyn, pri.flow, mask, pc, sc.images.cpu().numpy(), depth, sc.Ks.cpu().numpy(),
        s.w2cs.cpu().numpy(), links,
    )  # fmt: skip
    s.info["motion_refine"] = {
        "mask_fraction_before": float(before.mean()),
        "mask_fraction_after": float(mask.mean()),
        "dynamic_tracks_before": int(pri.track_dynamic.sum()),
        "dynamic_tracks_after": int(dyn.sum()),
        "chained_tracks": int(n_ch),
        "chained_track_links": links,
    }
    if s.checkpoint_dir is not None:
        buf = io.BytesIO()
        np.savez_compressed(
            buf, mask=mask, confidence=fused.confidence.astype(np.float16), tracks=xy, visible=vis,
            dynamic=dyn, mask_before=before, pieces=pieces,
        )  # fmt: skip
        atomic_write_bytes(s.checkpoint_dir / "motion.npz", buf.getvalue())
    dev = s.device
    if pri.depth_fill is not None and pc.depth_import.fit_exclude_dynamic:
        # Imported depth under merge=fill: the refined masks cover more of each moving object than the
        # priors' masks did, so the import is refitted without them and fills them.
        depth, conf = refill_imported(
            s.P["depth"], s.P["depth_conf"], torch.from_numpy(mask).to(dev), pri.depth_fill,
            pc.depth_import.fill_conf,
        )  # fmt: skip
        s.P = {**s.P, "depth": depth, "depth_conf": conf}
        s.depth = depth * s.ba.depth_scale.float().to(dev)[:, None, None]
        s.info["motion_refine"]["depth_refitted"] = True
    elif s.info["priors"].get("depth") == "classical":
        # The classical depth is a static-world estimate and measures nothing on moving pixels (the priors give
        # their own masks confidence 0); the refined masks cover more of each object, where the plane sweep's
        # matches across times gave confidences that readers of the prior (a tree child's depth hold, the
        # auto split) would take for measurements.
        mk = torch.from_numpy(mask).to(dev)
        conf = s.P["depth_conf"]
        s.info["motion_refine"]["depth_conf_cleared"] = float((conf[mk] > 0).float().mean()) if mk.any() else 0.0
        s.P = {**s.P, "depth_conf": torch.where(mk, torch.zeros_like(conf), conf)}
    s.P = {
        **s.P,
        "epi_mask": torch.from_numpy(mask).to(dev),
        "tracks": torch.from_numpy(np.ascontiguousarray(xy)).to(dev),
        "track_vis": torch.from_numpy(vis).to(dev),
        "track_dynamic": torch.from_numpy(dyn).to(dev),
    }


def refill_imported(
    depth: torch.Tensor,
    conf: torch.Tensor,
    mask: torch.Tensor,
    fill: Callable[[np.ndarray], np.ndarray],
    fill_conf: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The depth prior ``[T, H, W]`` (scene units, before BA's per-frame scales) and its confidence with the
    pixels of ``mask`` ``[T, H, W]`` (bool) replaced by ``fill(mask)`` (the imported depth refitted without
    them, :attr:`worldtree.priors.Priors.depth_fill`) at confidence ``fill_conf``; the rest unchanged."""
    refit = torch.from_numpy(np.asarray(fill(mask.cpu().numpy()), np.float32)).to(depth.device)
    return (
        torch.where(mask, refit, depth.float()),
        torch.where(mask, torch.full_like(conf, fill_conf), conf),
    )


def _trajectory_depth(s: BaseState, tracks: torch.Tensor, vis: torch.Tensor, scale: float) -> torch.Tensor:
    """The depth prior ``[T, H, W]`` with the dynamic pixels' depth re-estimated from the dynamic tracks'
    smooth trajectories (each mask pixel scaled like its nearest tracks); ``info["trajectory_depth"]``."""
    depth = s.depth
    z, solved = smooth_trajectory_depths(
        tracks, vis, depth, s.scene.Ks, s.w2cs, scale, s.cfg.scaffold.trajectory_depth_prior
    )
    zhat, ok = sample_depth(depth, tracks)
    has = vis.bool() & ok & solved[None] & (zhat > 0)
    ratio = torch.where(has, z / zhat.clamp_min(1e-12), torch.ones_like(zhat))
    # Tracks may sit a few pixels off the mask (chaining tolerates it): their own pixels are scaled too.
    mask = s.P["epi_mask"].bool().clone()
    T, H, W = mask.shape
    col = tracks[..., 0].round().long().clamp(0, W - 1)
    row = tracks[..., 1].round().long().clamp(0, H - 1)
    frame = torch.arange(T, device=mask.device)[:, None].expand_as(col)
    mask[frame[has], row[has], col[has]] = True
    out = depth * ratio_map(mask, tracks, ratio, has).to(depth.dtype)
    r = ratio[has]
    s.info["trajectory_depth"] = {
        "tracks_solved": int(solved.sum()),
        "tracks": int(solved.numel()),
        "ratio_median": float(r.median()) if r.numel() else 1.0,
        "ratio_p10_p90": [float(r.quantile(0.1)), float(r.quantile(0.9))] if r.numel() else [1.0, 1.0],
    }
    return out


def stage_scaffold(s: BaseState) -> None:
    """Dynamic tracks lifted with the adjusted depth and cameras, gaps filled, scaffold built and fitted;
    dynamic Gaussians lifted from the dynamic-mask pixels, each at its own frame. With a checkpoint folder,
    ``scaffold.pt`` there keeps the fitted scaffold, and a resumed run reads it instead of fitting again."""
    c, sc, P, depth = s.cfg, s.scene, s.P, s.depth
    dyn_ids = torch.nonzero(P["track_dynamic"]).flatten()
    valid_depth = depth[depth > 0]
    scale = float(valid_depth.median()) if valid_depth.numel() else 1.0
    tracks = P["tracks"].float()[:, dyn_ids]
    vis = P["track_vis"][:, dyn_ids]
    if dyn_ids.numel() and _uses_trajectory_depth(c, s.priors.sources):
        depth = s.depth = _trajectory_depth(s, tracks, vis, scale)
    if _uses_object_depth(c, s.priors.sources):
        depth = s.depth = _object_depth(s)
    saved = s.checkpoint_dir / "scaffold.pt" if s.checkpoint_dir is not None else None
    if dyn_ids.numel() == 0:
        scf = Scaffold.empty(sc.num_frames, c.scaffold.unit_ratio * scale, c.scaffold, device=s.device)
    elif saved is not None and saved.is_file():
        # A resumed run: the fit takes minutes at the real size (1,000 steps over 160 frames x 3,459 nodes).
        d = load_torch(
            saved, s.device, missing="no fitted scaffold",
            unreadable="unreadable fitted scaffold ({error}); delete it to fit the scaffold again",
        )  # fmt: skip
        scf = Scaffold.from_state(d["scaffold"], s.device)
        s.info["scaffold_fit"] = d["fit"]
    else:
        pts, valid = lift_tracks(tracks, vis, depth, sc.Ks, s.w2cs)
        radius = c.scaffold.complete_radius_units * c.scaffold.unit_ratio * scale
        traj, observed = complete_trajectories(pts.float(), valid, radius, c.scaffold.complete_k)
        scf = build_scaffold(traj, observed, scale, c.scaffold)
        steps = c.scaffold_fit.steps
        report = Progress("scaffold fit", 0, steps, s.ctx is not None and s.ctx.progress, log_every=1)

        def on_log(rec: dict[str, float]) -> None:  # every 100 steps: minutes at the real size
            report.update(min(int(rec["step"]) + 1, steps), {"loss": rec["data_units"] + rec["motion"]})

        try:
            fitted = fit_scaffold(scf, scf.pos.detach().clone(), scf.observed, c.scaffold_fit, on_log)
        finally:
            report.close()
        s.info["scaffold_fit"] = fitted
        if saved is not None:
            state = scf.to_state()
            state["tensors"] = {k: v.cpu() for k, v in state["tensors"].items()}
            save_torch(saved, {"scaffold": state, "fit": fitted})
    if scf.M == 0:
        dyn = DynamicGaussians.empty(s.device)
    else:
        gen = torch.Generator().manual_seed(c.seed + 7)
        pts, cols, frames = lift_pixels(
            sc.images, depth, P["epi_mask"], sc.Ks, s.w2cs, c.dynamic_init_stride_px, c.dynamic_max_init, gen
        )
        if pts.shape[0] == 0:
            dyn = DynamicGaussians.empty(s.device, skin_k=scf.K)
        else:
            dyn = DynamicGaussians.from_points_at(
                pts, cols, frames, c.dynamic_init_opacity, skin_k=scf.K, time_std=c.dynamic_time_std
            )
    s.info["scaffold_nodes"] = scf.M
    s.info["dynamic_tracks"] = int(dyn_ids.numel())
    s.scaffold, s.dynamic, s.tracks, s.track_vis = scf, dyn, tracks, vis


def stage_photometric(s: BaseState) -> None:
    """Joint photometric fit of static + dynamic Gaussians, scaffold and (from a set step) cameras; under the
    Gaussian budget and with the loss-plateau stop when those are on (``info["adaptive"]``)."""
    c, sc = s.cfg, s.scene
    _drop_floating_depth(s)
    steps = c.photometric_steps(sc.num_frames)
    pcfg = dataclasses.replace(c.photometric_config(), steps=steps)
    fit = PhotometricFit(
        pcfg, sc.images, s.depth, sc.Ks, s.w2cs, s.static, s.dynamic, s.scaffold, s.tracks, s.track_vis,
        s.extent, seed=c.seed,
    )  # fmt: skip
    s.stop = _adaptive_setup(s, fit)
    ckpt = s.checkpoint_dir
    trainer = Trainer(
        TrainerConfig(steps=steps, checkpoint_every=c.checkpoint_every, log_every=c.log_every),
        fit,
        checkpoint_dir=ckpt / "photometric" if ckpt is not None else None,
        generators={"frame_order": fit.order},
        tensorboard_dir=s.ctx.tensorboard_dir,
        progress=s.ctx.progress,
        description="photometric",
        stop=s.stop,
    )
    s.summary = trainer.fit(resume=s.ctx.resume)
    fit.ssim_targets.clear()  # training is over; the tree's workers and the test pose do not use them
    release_freed_memory()
    rec = s.info["adaptive"]
    rec["steps_max"], rec["steps_taken"] = steps, s.summary.end_step
    if s.stop is not None:
        rec["early_stop"] = s.stop.report()
    s.fit = fit
    s.renderer, s.gaussians_at = fit.render, fit.gaussians_at


def _drop_floating_depth(s: BaseState) -> None:
    """An imported depth's pixels outside the dynamic masks that a static world cannot hold
    (:func:`worldtree.priors.free_space.free_space_violations`) get depth 0 and confidence 0, so that neither
    the photometric fit's depth loss nor a tree child's depth hold pulls static Gaussians out to them;
    ``info["depth_free_space"]``. The classical depth is a static-world estimate and is left as it is."""
    fc = s.cfg.depth_free_space
    if not fc.enabled or s.cfg.priors.depth_source == "classical":
        return
    flag = free_space_violations(
        s.depth, s.scene.Ks, s.w2cs, fc.tolerance, fc.views, fc.share, fc.window
    ) & ~s.P["epi_mask"].bool()
    s.depth = torch.where(flag, torch.zeros_like(s.depth), s.depth)
    conf = s.P["depth_conf"]
    s.P = {**s.P, "depth_conf": torch.where(flag, torch.zeros_like(conf), conf)}
    per_frame = flag.flatten(1).float().mean(1)
    s.info["depth_free_space"] = {
        "dropped_fraction": float(per_frame.mean()),
        "dropped_fraction_max_frame": float(per_frame.max()) if per_frame.numel() else 0.0,
    }


def _adaptive_setup(s: BaseState, fit: PhotometricFit) -> PlateauDetector | None:
    """Budget (growth caps from the image size and the starting error) and the early-stop detector of the
    photometric fit, when on; recorded in ``info["adaptive"]``."""
    c = s.cfg
    rec: dict[str, Any] = {"budget_on": c.root_budget_on(), "early_stop_on": c.root_early_stop_on()}
    if c.root_budget_on():
        H, W = fit.images.shape[1:3]
        err = fit.mean_error()
        rec["budget"] = {"error_start": err, **fit.set_budget(node_budget(W, H, err, c.budget))}
    s.info["adaptive"] = rec
    if not c.root_early_stop_on():
        return None
    # Never before density control and camera optimisation have had their turn.
    pc = fit.cfg
    settle = max(pc.static_strategy.refine_stop, pc.dynamic_strategy.refine_stop, pc.camera_start_step)
    return c.early_stop.detector(fit.T, min(settle, pc.steps))


def stage_prune(s: BaseState) -> None:
    """Gaussians whose contribution is negligible removed from the fitted model (runs with ``budget`` on)."""
    b = s.cfg.budget
    s.info["adaptive"]["prune"] = s.fit.prune_negligible(b.prune_contribution, total_frac=b.prune_total_frac)


def stage_test_pose(s: BaseState) -> None:
    """The camera placement (Sim(3) of the given training poses onto the optimised ones, and the frames'
    residuals) applied to the test camera, then photometric refinement per test frame on the test images
    (rendered by ``s.renderer``)."""
    sc = s.scene
    fitted = s.fit.cameras().detach()
    s.sim3 = align_sim3(sc.w2cs, fitted, s.cfg.test_pose.align_rotation)
    s.placement = CameraPlacement.fit(sc.w2cs, fitted, s.sim3, s.cfg.test_pose.residual_time_sigma)
    if sc.test_images.shape[0] == 0:
        return
    times = [min(int(t), sc.num_frames - 1) for t in sc.test_times.tolist()]
    same = coinciding_frame(sc.test_w2c, sc.w2cs) if s.cfg.test_pose.start_at_same_camera else None
    # A test camera that is a training frame's camera (the NVIDIA short protocol's camera 0) starts from that
    # frame's fitted pose: the Sim(3) of all frames leaves each one a residual that shifts its static pixels.
    # Any other starts where the placement puts it; later frames may start there again (their own time's
    # residual) when that renders them better than the previous frame's refined pose.
    placed = torch.stack([s.placement.place(sc.test_w2c, t) for t in times]).to(fitted) if times else None
    start = placed[0] if same is None else fitted[same].clone()
    s.info["test_pose_start"] = "placed" if same is None else f"frame {same}"
    W, H = sc.test_images.shape[2], sc.test_images.shape[1]

    def render_fn(t: int, w2c: torch.Tensor):
        return s.renderer(sc.test_K, w2c, W, H, t)

    if s.gaussians_at is not None:  # the model is fixed here: its Gaussians once per test frame, not per step
        render_fn = FrozenModelRenderer(s.gaussians_at, sc.test_K, W, H, s.cfg.photometric.backend)
    # Without refinement a camera of a training frame stays at that frame's pose; any other at its placement.
    cands = placed if same is None or s.cfg.test_pose.enabled else None
    res = refine_test_poses(render_fn, start, sc.test_images, times, s.cfg.test_pose, w2c_candidates=cands)
    s.test_poses = {int(t): res.w2cs[k] for k, t in enumerate(sc.test_times.tolist())}
    s.info["test_pose_l1_before"] = res.loss_before
    s.info["test_pose_l1_after"] = res.loss_after


def bracket_time(time: float, frames: int) -> tuple[int, float]:
    """``(a, frac)``: ``time`` as ``a + frac`` with ``a`` a training frame and ``0 <= frac < 1``, clamped to the
    ``frames`` training frames (``frac`` 0 at and beyond either end)."""
    if time <= 0 or time >= frames - 1:
        return (0 if time <= 0 else frames - 1), 0.0
    a = math.floor(time)
    return a, float(time - a)


#: The Base method: its stages in order (``ablate`` replaces ``ba`` / ``sw`` by their ablated forms; ``prune``
#: runs only with the Gaussian budget on).
STAGE_LEDGER = "stage_timing.json"
"""The method's per-stage times over every session of a resumed run, under the checkpoint folder."""

BASE_STAGES: tuple[Stage, ...] = (
    Stage("priors", stage_priors),
    Stage("ba", stage_ba),
    Stage("sw", stage_sw),
    Stage("motion", stage_motion),
    Stage("scaffold", stage_scaffold),
    Stage("photometric", stage_photometric),
    Stage("prune", stage_prune),
    Stage("test_pose", stage_test_pose),
)
#: The stages before the test pose, which another run may lend (``wtbench run --root-from``): a WorldTree run's
#: root is this model, so the two methods lend each other.
ROOT_STAGES = SharedRoot(
    checkpoints=("ba.pt", "sw", "motion.npz", "scaffold.pt", "photometric"),
    stages=("ba", "sw", "motion", "scaffold", "photometric"),
    methods=("base", "worldtree"),
    root_ablations=("ba", "sw"),
    ledger=STAGE_LEDGER,
)
#: What each ablation of the Base method does to :data:`BASE_STAGES`.
BASE_ABLATIONS: dict[str, Ablation] = {
    "ba": Ablation("ba", Stage("ba", stage_ba_ablated)),
    "sw": Ablation("sw", Stage("sw", stage_sw_ablated)),
}


@dataclass
class LoadedModel:
    """A saved Base model read back (:meth:`BaseMethod.load_model`), on the method's device."""

    static: GaussianSet
    dynamic: DynamicGaussians
    scaffold: Scaffold
    cache: SkinCache
    """The skinning neighbourhoods of ``dynamic`` the run rendered with."""
    w2cs: torch.Tensor
    """``[T, 4, 4]`` fitted training cameras (model frame)."""


class BaseMethod:
    """The Base method for one scene; implements :class:`methods.registry.Method`.

    What it runs is data: :attr:`STAGES` over a :attr:`STATE` (a subclass, like WorldTree, names its own),
    with :attr:`ABLATIONS` applied for the config's ``ablate``."""

    STAGES: ClassVar[tuple[Stage, ...]] = BASE_STAGES
    ABLATIONS: ClassVar[dict[str, Ablation]] = BASE_ABLATIONS
    STATE: ClassVar[type[BaseState]] = BaseState
    MODEL_NAME: ClassVar[str] = "base"
    """``method`` of the ``model.json`` that :meth:`save_model` writes (and :meth:`load_model` reads)."""

    def __init__(self, cfg: BaseConfig, scene: Scene, device: torch.device):
        if scene.num_frames < 2:
            raise UserError(
                f"scene {scene.name}: {scene.num_frames} training frame(s); the Base method needs 2+"
            )
        self.cfg = cfg
        self.device = device
        self.state = self.STATE(cfg, scene.to(device), device)
        self.clock = StageClock()
        """Times each stage (``stats()["stages_s"]``): this session's, plus the earlier sessions' of a resumed
        run once :meth:`fit` attaches the checkpoint folder's :data:`STAGE_LEDGER`."""
        self._loaded: LoadedModel | None = None
        """The model read by :meth:`load_model` (None while it is trained by :meth:`fit`)."""

    def stages(self) -> list[Stage]:
        """The stages this config runs, in order (ablations applied; ``prune`` only with the budget on)."""
        out = with_ablations(self.STAGES, self.ABLATIONS, self.cfg.ablate)
        return [st for st in out if st.name != "prune" or self.cfg.root_budget_on()]

    def fit(self, ctx: TrainContext) -> TrainSummary:
        """Run every stage in order, each timed by :attr:`clock` (resumable: each stage picks up its own
        checkpoints under ``ctx.checkpoint_dir``)."""
        if ctx.checkpoint_dir is not None:
            ctx.checkpoint_dir.mkdir(parents=True, exist_ok=True)
            if self.clock.ledger is None:
                # A resumed run's stages count every session's time, not only the one that finished them.
                self.clock.attach(ctx.checkpoint_dir / STAGE_LEDGER)
        self.state.ctx = ctx
        run_stages(self.stages(), self.state, self.clock)
        return self.state.summary

    # ------------------------------------------------------------------ Method
    @torch.no_grad()
    def render(
        self, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, time: int, test_view: bool = False
    ) -> torch.Tensor:
        """``[height, width, 3]`` of camera ``K``/``w2c`` (given frame) at frame ``time``. ``test_view``: the
        camera is the scene's test camera, rendered from its refined pose at that time; any other camera
        (or a time without a refined pose) is placed by :meth:`model_w2c`."""
        return self.render_mode(K, w2c, width, height, time, "rgb", test_view)

    def model_w2c(
        self, w2c: torch.Tensor, time: float, test_view: bool = False, frame: int | None = None
    ) -> torch.Tensor:
        """``[4, 4]`` model-frame pose of the given ``w2c``: the refined test pose at ``time`` (``test_view``),
        training frame ``frame``'s fitted pose (also when ``w2c`` is that frame's given pose:
        :func:`~worldtree.stages.testview_pose.coinciding_frame`), or the camera placed at ``time`` (frames,
        may be fractional) by :class:`~worldtree.stages.testview_pose.CameraPlacement`: the Sim(3) from the
        given poses to the fitted ones and the residual of the training frames near that time."""
        s = self.state
        w2c = w2c.to(self.device, torch.float32)
        if test_view and int(time) in s.test_poses:
            return s.test_poses[int(time)]
        if frame is None and self.cfg.test_pose.start_at_same_camera:
            frame = coinciding_frame(w2c, s.scene.w2cs.to(w2c))  # a training frame's own camera: its fitted pose
        if frame is not None:
            return self._train_w2c(int(frame))
        if s.placement is not None:
            return s.placement.place(w2c, float(time))
        return s.sim3.apply_w2c(w2c)

    @torch.no_grad()
    def render_mode(
        self, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, time: int,
        mode: RenderMode = "rgb", test_view: bool = False, frame: int | None = None,
    ) -> torch.Tensor:  # fmt: skip
        """:meth:`render` as ``mode`` (:data:`worldtree.gaussian_frame.RenderMode`), the camera placed by
        :meth:`model_w2c`."""
        s = self.state
        if s.renderer is None:
            raise RuntimeError("render before fit (or load_model)")
        K = K.to(self.device, torch.float32)
        pose = self.model_w2c(w2c, time, test_view, frame)
        t = min(max(int(time), 0), s.scene.num_frames - 1)
        if mode == "rgb":
            return s.renderer(K, pose, width, height, t).rgb.clamp(0.0, 1.0)
        return render_frame(self.gaussians_at(t), K, pose, width, height, mode, self.cfg.photometric.backend)

    @torch.no_grad()
    def gaussians_at(self, time: int) -> GaussianFrame:
        """What :meth:`render` rasterizes at ``time`` (clamped to the training frames): the static Gaussians
        first, then the dynamic ones carried to ``time`` (a tree node's ancestors after them), in the model's
        frame (``scene_to_model``: the run's Sim(3))."""
        s = self.state
        if s.gaussians_at is None:
            raise RuntimeError("gaussians_at before fit (or load_model)")
        t = min(max(int(time), 0), s.scene.num_frames - 1)
        m, q, ls, o, _ = s.gaussians_at(t)
        sh0, n_static, node = self._frame_colours(t)
        if sh0.shape[0] != m.shape[0]:
            raise RuntimeError(f"frame {t}: {m.shape[0]} Gaussians drawn but {sh0.shape[0]} colours")
        dyn = torch.arange(m.shape[0], device=m.device) >= n_static
        sim3 = s.sim3 if s.sim3 is not None else Sim3.identity(device=m.device)
        return GaussianFrame(
            t, m.detach(), q.detach(), ls.detach(), o.detach(), sh0.detach(), dyn, sim3, node=node
        )

    def node_at(self, time: float) -> int | None:
        return None

    @torch.no_grad()
    def render_between(
        self, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, time: float
    ) -> torch.Tensor:
        """``[height, width, 3]`` at a fractional ``time`` between training frames ``a = floor(time)`` and
        ``a + 1`` (:meth:`methods.registry.Method.render_between`): every Gaussian between its positions at the
        two frames (:func:`worldtree.dynamic.between_path`: means on the line between them, or with
        ``between_frames`` 4 on the cubic through the frames around them too; rotations nlerped), the dynamic
        opacities evaluated at ``time`` (they change with it only under temporal opacity; static Gaussians are
        the same at both). The camera is placed at ``time`` by :meth:`model_w2c`, as a non-test camera in :meth:`render`.
        An integer ``time`` (or one outside the training frames) is :meth:`render` of the nearest frame."""
        T = self.state.scene.num_frames
        a, frac = bracket_time(time, T)
        if frac == 0.0:
            return self.render(K, w2c, width, height, a)
        ga, gb, o = self._between_lists(a, time)
        lists = {0: ga, 1: gb}
        if self.cfg.between_frames == 4:
            lists.update({d: self.state.gaussians_at(a + d) for d in (-1, 2) if 0 <= a + d < T})
        m, q, ls, o, c = between_path(lists, o, frac)
        pose = self.model_w2c(w2c, time)  # placed at the fractional time: the residuals drift with it
        out = rasterize(m, q, ls, o, c, K.to(self.device, torch.float32), pose, width, height,
                        backend=self.cfg.photometric.backend)  # fmt: skip
        return out.rgb.clamp(0.0, 1.0)

    def _between_lists(self, a: int, time: float) -> tuple[tuple, tuple, torch.Tensor]:
        """The render lists at frames ``a`` and ``a + 1`` and the ``[N]`` opacities at ``time`` in between."""
        s = self.state
        if s.gaussians_at is None:
            raise RuntimeError("render_between before fit (or load_model)")
        ga = s.gaussians_at(a)
        static, dynamic = self._model_sets()
        o = ga[3]
        if o.shape[0] == len(static) + len(dynamic):
            o = torch.cat([o[: len(static)], dynamic.opacities_at(time)])
        return ga, s.gaussians_at(a + 1), o

    def _model_sets(self) -> tuple[GaussianSet, DynamicGaussians]:
        """The fitted (or loaded) static and dynamic sets."""
        if self.state.fit is not None:
            return self.state.fit.static, self.state.fit.dynamic
        if self._loaded is None:
            raise RuntimeError("no model: fit or load_model first")
        return self._loaded.static, self._loaded.dynamic

    def _frame_colours(self, t: int) -> tuple[torch.Tensor, int, int | None]:
        """``(sh0 [N, 3], number of static Gaussians first, tree node)`` of what frame ``t`` draws, in the
        order of ``state.gaussians_at(t)``."""
        static, dynamic = self._model_sets()
        return torch.cat([static.params["sh0"], dynamic.params["sh0"]]), len(static), None

    def _train_w2c(self, frame: int) -> torch.Tensor:
        """``[4, 4]`` fitted pose of training frame ``frame`` (model frame)."""
        s = self.state
        w2cs = s.fit.cameras() if s.fit is not None else self._loaded.w2cs
        return w2cs[min(max(frame, 0), w2cs.shape[0] - 1)]

    def load_model(self, folder: Path) -> None:
        """Read what :meth:`save_model` wrote: the static and dynamic Gaussians, the scaffold with the skinning
        cache the run rendered with (recomputed from the means for a model saved without one), the fitted
        cameras, the refined test poses and the Sim(3)."""
        folder = Path(folder)
        s, dev = self.state, self.device
        info = read_model_json(folder, self.MODEL_NAME)
        static = GaussianSet.load(folder / "static_gaussians.pt", dev)
        dynamic = DynamicGaussians.load(folder / "dynamic_gaussians.pt", dev)
        extra = load_torch(
            folder / "scaffold_cameras.pt", dev, missing="missing; finish the run with `wtbench run` first",
            unreadable="unreadable ({error}); re-run with `wtbench run --force`",
        )  # fmt: skip
        scaffold = Scaffold.from_state(extra["scaffold"], dev)
        cache = SkinCache.from_state(extra["cache"], dev) if "cache" in extra else dynamic.attach(scaffold)
        self._loaded = LoadedModel(static, dynamic, scaffold, cache, extra["w2cs"].to(dev, torch.float32))
        s.test_poses = {int(k): v for k, v in extra.get("test_poses", {}).items()}
        sim = info.get("sim3_given_to_optimised")
        s.sim3 = (
            Sim3(float(sim["scale"]), torch.tensor(sim["R"], dtype=torch.float32, device=dev),
                 torch.tensor(sim["t"], dtype=torch.float32, device=dev))
            if sim else Sim3.identity(device=dev)
        )  # fmt: skip
        given = s.scene.w2cs.to(dev)
        # A scene whose frames are not the run's (moved, rebuilt) has no residual per frame: the Sim(3) alone.
        s.placement = (
            CameraPlacement.fit(given, self._loaded.w2cs, s.sim3, self.cfg.test_pose.residual_time_sigma)
            if given.shape == self._loaded.w2cs.shape else None
        )  # fmt: skip
        loaded, backend = self._loaded, self.cfg.photometric.backend

        def at(t: int, cache: SkinCache | None = None):
            return gaussians_at(loaded.static, loaded.dynamic, loaded.scaffold, t,
                                loaded.cache if cache is None else cache)  # fmt: skip

        def render(K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, t: int):
            m, q, ls, o, c = at(t)  # as PhotometricFit.render
            return rasterize(m, q, ls, o, c, K, w2c, width, height, backend=backend)

        s.gaussians_at, s.renderer = at, render

    def save_model(self, folder: Path) -> None:
        folder = Path(folder)
        s = self.state
        fit = s.fit
        fit.static.save(folder / "static_gaussians.pt")
        fit.static.write_ply(folder / "static_gaussians.ply")
        fit.dynamic.save(folder / "dynamic_gaussians.pt")
        save_torch(
            folder / "scaffold_cameras.pt",
            {"scaffold": fit.scaffold.to_state(), "w2cs": fit.cameras().cpu(),
             "test_poses": {k: v.cpu() for k, v in s.test_poses.items()},
             # The skinning neighbourhoods the fit renders with (re-attached only every few steps, so not
             # what attaching the final means gives): load_model renders exactly what the run rendered.
             "cache": fit.cache.to_state()},
        )  # fmt: skip
        atomic_write_json(
            folder / "model.json",
            {
                "method": "base",
                "num_static": len(fit.static),
                "num_dynamic": len(fit.dynamic),
                "scaffold_nodes": fit.scaffold.M,
                "frames": s.scene.num_frames,
                "sim3_given_to_optimised": s.sim3.to_dict() if s.sim3 is not None else None,
                "files": {
                    "static_gaussians.pt": "worldtree.gaussians.GaussianSet.load",
                    "static_gaussians.ply": "3DGS viewer PLY (background only)",
                    "dynamic_gaussians.pt": "worldtree.dynamic.DynamicGaussians.load (means at t_ref)",
                    "scaffold_cameras.pt": "torch.load: scaffold (Scaffold.from_state), w2cs [T,4,4], test_poses, "
                    "cache (SkinCache.from_state)",
                },
            },
        )

    def stats(self) -> dict[str, Any]:
        s = self.state
        fit = s.fit
        n_s = len(fit.static) if fit is not None else 0
        n_d = len(fit.dynamic) if fit is not None else 0
        return {
            "num_gaussians": n_s + n_d,
            "num_static": n_s,
            "num_dynamic": n_d,
            "scaffold_nodes_final": fit.scaffold.M if fit is not None else 0,
            "backend": fit.backend if fit is not None else "none",
            "stages": [st.name for st in self.stages()],
            "stages_s": dict(self.clock.stages_s),
            "stages_cpu_s": dict(self.clock.stages_cpu_s),
            "ablate": list(self.cfg.ablate),
            "migration": dict(fit.migration) if fit is not None else {},
            "floaters_removed": fit.floaters if fit is not None else 0,
            **{k: v for k, v in s.info.items() if k not in ("scaffold_fit",)},
        }


register_method(
    MethodSpec(
        name="base",
        description="Base dynamic method: BA, static warm-up, motion scaffold + DQB dynamic Gaussians (MoSca-style)",
        config_cls=BaseConfig,
        presets={
            "paper": paper_config,
            "quick": quick_config,
            "smoke": smoke_config,
        },
        build=BaseMethod,
        shared_root=ROOT_STAGES,
    )
)
