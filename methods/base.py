"""The Base dynamic method (MoSca-style global optimisation; the first row group of the paper's ablation).

Stages, each timed in ``stats()["stages_s"]`` (docs/base_method.md):

1. priors -- :func:`worldtree.priors.compute_priors` (cached under ``SCENE/priors/x<downscale>``, as
   ``wtbench prep``);
2. BA -- :func:`worldtree.stages.bundle_adjust.bundle_adjust` on the static tracks (``ablate_ba`` skips it);
3. SW -- static warm-up of the background Gaussians on static pixels (``ablate_sw``: no warm-up steps, the
   background starts from the lifted static depth);
4. scaffold -- dynamic tracks lifted with the adjusted depth and cameras, gaps filled, scaffold built
   (:func:`worldtree.motion.scaffold.build_scaffold`) and fitted (:mod:`worldtree.stages.scaffold_fit`);
   dynamic Gaussians lifted from the dynamic-mask pixels, each at its own frame;
5. photometric -- joint fit of static + dynamic Gaussians, scaffold and (from a set step) cameras;
6. test pose -- Sim(3) of the given training poses onto the optimised ones applied to the test camera, then
   photometric refinement per test frame on the test images.

A scene without dynamic content (no dynamic track) gets an empty scaffold and no dynamic Gaussian: the model
is then a static one, and every stage still runs.
"""

from __future__ import annotations

import dataclasses
import io
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from methods.registry import CommonConfig, MethodSpec, register_method
from methods.static3dgs import scene_extent
from worldtree.atomic import atomic_write_bytes, atomic_write_json
from worldtree.budget import node_budget
from worldtree.dynamic import DynamicGaussians
from worldtree.errors import UserError
from worldtree.motion.lift import fill_gaps, lift_tracks
from worldtree.motion.scaffold import Scaffold, ScaffoldConfig, build_scaffold
from worldtree.plateau import PlateauDetector
from worldtree.priors import PriorsConfig, compute_priors
from worldtree.priors.api import add_chained_tracks
from worldtree.priors.dynamic_masks import refine_with_residual
from worldtree.priors.epipolar import label_dynamic_tracks
from worldtree.render import rasterize
from worldtree.scene import Scene
from worldtree.stages.bundle_adjust import BAResult, BundleAdjustConfig, bundle_adjust
from worldtree.stages.photometric import PhotometricConfig, PhotometricFit, quick_photometric_config
from worldtree.stages.scaffold_fit import ScaffoldFitConfig, fit_scaffold
from worldtree.stages.static_warmup import (
    StaticWarmup,
    StaticWarmupConfig,
    lift_pixels,
    quick_static_warmup_config,
)
from worldtree.stages.testview_pose import (
    PoseRefineConfig,
    align_sim3,
    quick_pose_refine_config,
    refine_test_poses,
)
from worldtree.strategy import DensifyStrategy
from worldtree.torchfile import load_torch, save_torch
from worldtree.trainer import TrainContext, Trainer, TrainerConfig, TrainSummary


@dataclass
class BaseConfig(CommonConfig):
    """Base method settings (defaults: the ``paper`` preset). ``steps`` is the photometric fit's."""

    steps: int = 4000
    """Photometric-fit steps (NVIDIA-LS root: 4000)."""
    ablate: tuple[str, ...] = ()
    """Ablated stages (``--ablate``): ``ba`` and/or ``sw``; kept in sync with ``ablate_ba``/``ablate_sw``
    (either spelling works). Subclasses widen the choice through :meth:`ablation_names`."""
    ablate_ba: bool = False
    """Skip the tracklet bundle adjustment (ablation row "w/o BA")."""
    ablate_sw: bool = False
    """Skip the static warm-up (ablation row "w/o SW")."""
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

    def __post_init__(self) -> None:
        allowed = self.ablation_names()
        bad = [a for a in self.ablate if a not in allowed]
        if bad:
            raise UserError(f"--ablate {bad[0]}: choose among {', '.join(allowed)}")
        names = set(self.ablate) | {n for n, on in (("ba", self.ablate_ba), ("sw", self.ablate_sw)) if on}
        self.ablate = tuple(a for a in allowed if a in names)
        self.ablate_ba, self.ablate_sw = "ba" in names, "sw" in names


def paper_config() -> BaseConfig:
    """The paper's schedule: BA 2000, SW 6000, photometric 4000 (cameras from 1500), test pose 300/30."""
    return BaseConfig()


def quick_config() -> BaseConfig:
    """CPU-friendly schedule for a small scene: BA 300, SW 300, scaffold fit 100, photometric 600, test pose
    60/10, half resolution, fewer initial Gaussians."""
    return BaseConfig(
        steps=600,
        downscale=2,
        ba=BundleAdjustConfig(steps=300, max_tracks=4000),
        sw=quick_static_warmup_config(),
        scaffold_fit=ScaffoldFitConfig(steps=100),
        photometric=quick_photometric_config(),
        test_pose=quick_pose_refine_config(),
        dynamic_max_init=4000,
        checkpoint_every=200,
        log_every=50,
    )


def smoke_config() -> BaseConfig:
    """A few steps of every stage (tests and smoke runs; not a meaningful reconstruction)."""
    no_densify = DensifyStrategy(refine_start=10_000, refine_stop=10_000, reset_every=0)
    return BaseConfig(
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
    )


def _ablated(factory, ba: bool, sw: bool):
    def make() -> BaseConfig:
        return dataclasses.replace(factory(), ablate_ba=ba, ablate_sw=sw)

    return make


class BaseMethod:
    """The Base method for one scene; implements :class:`methods.registry.Method`."""

    def __init__(self, cfg: BaseConfig, scene: Scene, device: torch.device):
        if scene.num_frames < 2:
            raise UserError(
                f"scene {scene.name}: {scene.num_frames} training frame(s); the Base method needs 2+"
            )
        self.cfg = cfg
        self.device = device
        self.scene = scene.to(device)
        self.fit_state: PhotometricFit | None = None
        self.sim3 = None
        self.test_poses: dict[int, torch.Tensor] = {}
        self.stage_s: dict[str, float] = {}
        self.info: dict[str, Any] = {}
        self.backend = "none"
        self.refined_mask = None

    # ------------------------------------------------------------------ stages
    def _timed(self, name: str, fn, *args, **kwargs):
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            self.stage_s[name] = self.stage_s.get(name, 0.0) + time.perf_counter() - t0

    def _priors(self):
        s = self.scene
        cache = s.root / "priors" / f"x{self.cfg.downscale}" if self.cfg.priors_cache else None
        pri = compute_priors(s, self.cfg.priors, cache)
        self.info["priors"] = dict(pri.sources)
        return pri, pri.torch(self.device)

    def _ba(self, P: dict, ckpt: Path | None) -> BAResult:
        s = self.scene
        path = ckpt / "ba.pt" if ckpt is not None else None
        if path is not None and path.is_file():
            d = load_torch(
                path, self.device, missing="no BA result",
                unreadable="unreadable BA result ({error}); delete it to run BA again",
            )  # fmt: skip
            return BAResult(d["w2cs"], d["depth_scale"], d["track_ids"], d["points"], d["before"], d["after"])
        ba_cfg = dataclasses.replace(self.cfg.ba, enabled=self.cfg.ba.enabled and not self.cfg.ablate_ba)
        res = bundle_adjust(
            P["tracks"].float(), P["track_vis"], ~P["track_dynamic"], P["depth"].float(), s.Ks, s.w2cs, ba_cfg,
            depth_conf=P["depth_conf"].float(),
        )  # fmt: skip
        if path is not None:
            save_torch(
                path,
                {"w2cs": res.w2cs.cpu(), "depth_scale": res.depth_scale.cpu(), "track_ids": res.track_ids.cpu(),
                 "points": res.points.cpu(), "before": res.reproj_px_before, "after": res.reproj_px_after},
            )  # fmt: skip
        return res

    def _warmup(self, depth, dynamic, w2cs, extent, ctx: TrainContext) -> tuple[Any, TrainSummary]:
        c = self.cfg
        sw_cfg = dataclasses.replace(c.sw, steps=0 if (c.ablate_sw or not c.sw.enabled) else c.sw.steps)
        sw = StaticWarmup(sw_cfg, self.scene.images, dynamic, depth, self.scene.Ks, w2cs, extent, seed=c.seed)
        trainer = Trainer(
            TrainerConfig(steps=sw_cfg.steps, checkpoint_every=c.checkpoint_every, log_every=c.log_every),
            sw,
            checkpoint_dir=ctx.checkpoint_dir / "sw" if ctx.checkpoint_dir is not None else None,
            progress=ctx.progress,
            description="static warm-up",
        )
        return sw.gaussians, trainer.fit(resume=ctx.resume)

    @torch.no_grad()
    def _refine_motion(self, pri, P: dict, static, w2cs, ckpt: Path | None = None) -> dict:
        """Masks refined with the static model's residual, tracks relabelled and re-chained (``refine_masks``).

        With a checkpoint folder, ``motion.npz`` there keeps the result (masks ``[T, H, W]``, confidence,
        tracks ``[T, N, 2]``, visibility, dynamic labels): previews and the motion proof read it."""
        c, s = self.cfg, self.scene
        pc = c.priors
        if not (c.refine_masks and pc.motion.enabled and pc.masks_source is None and pri.motion_evidence):
            return P
        T, H, W = s.images.shape[:3]
        renders = torch.stack(
            [rasterize(static.means, static.quats, static.log_scales, static.opacities, static.colors,
                       s.Ks[t], w2cs[t], W, H, backend=c.sw.backend).rgb.clamp(0, 1) for t in range(T)]
        ).cpu().numpy()  # fmt: skip
        images = s.images.cpu().numpy()
        before = pri.epi_mask
        fused = refine_with_residual(
            pri.motion_evidence, images, renders, pri.flow, before, pc.motion, pc.epi
        )
        mask = fused.mask
        n_lk = pri.tracks.shape[1] - pri.num_chained_tracks
        xy, vis = pri.tracks[:, :n_lk], pri.track_vis[:, :n_lk]
        dyn = label_dynamic_tracks(xy, vis, mask, pc.epi.track_min_frames)
        xy, vis, dyn, n_ch = add_chained_tracks(xy, vis, dyn, pri.flow, mask, pc)
        self.info["motion_refine"] = {
            "mask_fraction_before": float(before.mean()),
            "mask_fraction_after": float(mask.mean()),
            "dynamic_tracks_before": int(pri.track_dynamic.sum()),
            "dynamic_tracks_after": int(dyn.sum()),
            "chained_tracks": int(n_ch),
        }
        self.refined_mask = mask
        if ckpt is not None:
            buf = io.BytesIO()
            np.savez_compressed(
                buf, mask=mask, confidence=fused.confidence.astype(np.float16), tracks=xy, visible=vis,
                dynamic=dyn, mask_before=before,
            )  # fmt: skip
            atomic_write_bytes(ckpt / "motion.npz", buf.getvalue())
        out = dict(P)
        dev = self.device
        out["epi_mask"] = torch.from_numpy(mask).to(dev)
        out["tracks"] = torch.from_numpy(np.ascontiguousarray(xy)).to(dev)
        out["track_vis"] = torch.from_numpy(vis).to(dev)
        out["track_dynamic"] = torch.from_numpy(dyn).to(dev)
        return out

    def _dynamic(self, P: dict, depth, w2cs) -> tuple[Scaffold, DynamicGaussians, torch.Tensor, torch.Tensor]:
        c, s = self.cfg, self.scene
        dyn_ids = torch.nonzero(P["track_dynamic"]).flatten()
        valid_depth = depth[depth > 0]
        scale = float(valid_depth.median()) if valid_depth.numel() else 1.0
        T = s.num_frames
        tracks = P["tracks"].float()[:, dyn_ids]
        vis = P["track_vis"][:, dyn_ids]
        if dyn_ids.numel() == 0:
            scf = Scaffold.empty(T, c.scaffold.unit_ratio * scale, c.scaffold, device=self.device)
        else:
            pts, valid = lift_tracks(tracks, vis, depth, s.Ks, w2cs)
            traj, observed = fill_gaps(pts.float(), valid)
            scf = build_scaffold(traj, observed, scale, c.scaffold)
            self.info["scaffold_fit"] = fit_scaffold(
                scf, scf.pos.detach().clone(), scf.observed, c.scaffold_fit
            )
        if scf.M == 0:
            dyn = DynamicGaussians.empty(self.device)
        else:
            gen = torch.Generator().manual_seed(c.seed + 7)
            pts, cols, frames = lift_pixels(
                s.images, depth, P["epi_mask"], s.Ks, w2cs, c.dynamic_init_stride_px, c.dynamic_max_init, gen
            )
            if pts.shape[0] == 0:
                dyn = DynamicGaussians.empty(self.device, skin_k=scf.K)
            else:
                dyn = DynamicGaussians.from_points_at(pts, cols, frames, c.dynamic_init_opacity, skin_k=scf.K)
        self.info["scaffold_nodes"] = scf.M
        self.info["dynamic_tracks"] = int(dyn_ids.numel())
        return scf, dyn, tracks, vis

    def fit(self, ctx: TrainContext) -> TrainSummary:
        c, s = self.cfg, self.scene
        ckpt = ctx.checkpoint_dir
        if ckpt is not None:
            ckpt.mkdir(parents=True, exist_ok=True)
        pri, P = self._timed("priors", self._priors)
        ba = self._timed("ba", self._ba, P, ckpt)
        self.info["ba"] = ba.stats()
        w2cs = ba.w2cs.float()
        depth = P["depth"].float() * ba.depth_scale.float()[:, None, None]
        extent = scene_extent(w2cs, s.near, s.far)
        static, sw_summary = self._timed("sw", self._warmup, depth, P["epi_mask"], w2cs, extent, ctx)
        self.info["sw_steps"] = sw_summary.end_step
        P = self._timed("motion", self._refine_motion, pri, P, static, w2cs, ckpt)
        scf, dyn, tracks, vis = self._timed("scaffold", self._dynamic, P, depth, w2cs)
        pcfg = dataclasses.replace(c.photometric, steps=c.steps)
        fit = PhotometricFit(
            pcfg, s.images, depth, s.Ks, w2cs, static, dyn, scf, tracks, vis, extent, seed=c.seed
        )
        stop = self._adapt_before(fit)
        trainer = Trainer(
            TrainerConfig(steps=c.steps, checkpoint_every=c.checkpoint_every, log_every=c.log_every),
            fit,
            checkpoint_dir=ckpt / "photometric" if ckpt is not None else None,
            generators={"frame_order": fit.order},
            tensorboard_dir=ctx.tensorboard_dir,
            progress=ctx.progress,
            description="photometric",
            stop=stop,
        )
        summary = self._timed("photometric", trainer.fit, resume=ctx.resume)
        self._timed("prune", self._adapt_after, fit, summary, stop)
        self.fit_state = fit
        self._timed("test_pose", self._test_pose)
        self.backend = fit.backend
        return summary

    def _adapt_before(self, fit: PhotometricFit) -> PlateauDetector | None:
        """Budget (growth caps from the image size and the starting error) and the early-stop detector of the
        photometric fit, when on; recorded in ``info["adaptive"]``."""
        c = self.cfg
        rec: dict[str, Any] = {"budget_on": c.budget_on(), "early_stop_on": c.early_stop_on()}
        if c.budget_on():
            H, W = fit.images.shape[1:3]
            err = fit.mean_error()
            rec["budget"] = {"error_start": err, **fit.set_budget(node_budget(W, H, err, c.budget))}
        self.info["adaptive"] = rec
        if not c.early_stop_on():
            return None
        # Never before density control and camera optimisation have had their turn.
        pc = fit.cfg
        settle = max(pc.static_strategy.refine_stop, pc.dynamic_strategy.refine_stop, pc.camera_start_step)
        return c.early_stop.detector(fit.T, min(settle, c.steps))

    def _adapt_after(self, fit: PhotometricFit, summary: TrainSummary, stop: PlateauDetector | None) -> None:
        """Prune negligible Gaussians (budget on) and record the steps taken."""
        rec = self.info["adaptive"]
        rec["steps_max"], rec["steps_taken"] = self.cfg.steps, summary.end_step
        if stop is not None:
            rec["early_stop"] = stop.report()
        if self.cfg.budget_on():
            rec["prune"] = fit.prune_negligible(self.cfg.budget.prune_contribution)

    def _test_render(self, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, t: int):
        """Differentiable render used by test-pose refinement (WorldTree renders through its tree)."""
        return self.fit_state.render(K, w2c, width, height, t)

    def _test_pose(self) -> None:
        s = self.scene
        self.sim3 = align_sim3(s.w2cs, self.fit_state.cameras(), self.cfg.test_pose.align_rotation)
        if s.test_images.shape[0] == 0:
            return
        start = self.sim3.apply_w2c(s.test_w2c)
        W, H = s.test_images.shape[2], s.test_images.shape[1]
        times = [min(int(t), s.num_frames - 1) for t in s.test_times.tolist()]

        def render_fn(t: int, w2c: torch.Tensor):
            return self._test_render(s.test_K, w2c, W, H, t)

        res = refine_test_poses(render_fn, start, s.test_images, times, self.cfg.test_pose)
        self.test_poses = {int(t): res.w2cs[k] for k, t in enumerate(s.test_times.tolist())}
        self.info["test_pose_l1_before"] = res.loss_before
        self.info["test_pose_l1_after"] = res.loss_after

    # ------------------------------------------------------------------ Method
    @torch.no_grad()
    def render(self, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, time: int) -> torch.Tensor:
        """``[height, width, 3]`` of camera ``K``/``w2c`` (given frame) at frame ``time``; the scene's test
        camera uses its refined pose at that time, any other camera the Sim(3) alignment."""
        if self.fit_state is None:
            raise RuntimeError("render before fit")
        K = K.to(self.device, torch.float32)
        w2c = w2c.to(self.device, torch.float32)
        is_test = torch.allclose(w2c, self.scene.test_w2c.to(w2c), atol=1e-5)
        if is_test and int(time) in self.test_poses:
            pose = self.test_poses[int(time)]
        else:
            pose = self.sim3.apply_w2c(w2c)
        t = min(max(int(time), 0), self.scene.num_frames - 1)
        out = self.fit_state.render(K, pose, width, height, t)
        return out.rgb.clamp(0.0, 1.0)

    def save_model(self, folder: Path) -> None:
        folder = Path(folder)
        fit = self.fit_state
        fit.static.save(folder / "static_gaussians.pt")
        fit.static.write_ply(folder / "static_gaussians.ply")
        fit.dynamic.save(folder / "dynamic_gaussians.pt")
        save_torch(
            folder / "scaffold_cameras.pt",
            {"scaffold": fit.scaffold.to_state(), "w2cs": fit.cameras().cpu(),
             "test_poses": {k: v.cpu() for k, v in self.test_poses.items()}},
        )  # fmt: skip
        atomic_write_json(
            folder / "model.json",
            {
                "method": "base",
                "num_static": len(fit.static),
                "num_dynamic": len(fit.dynamic),
                "scaffold_nodes": fit.scaffold.M,
                "frames": self.scene.num_frames,
                "sim3_given_to_optimised": self.sim3.to_dict() if self.sim3 is not None else None,
                "files": {
                    "static_gaussians.pt": "worldtree.gaussians.GaussianSet.load",
                    "static_gaussians.ply": "3DGS viewer PLY (background only)",
                    "dynamic_gaussians.pt": "worldtree.dynamic.DynamicGaussians.load (means at t_ref)",
                    "scaffold_cameras.pt": "torch.load: scaffold (Scaffold.from_state), w2cs [T,4,4], test_poses",
                },
            },
        )

    def stats(self) -> dict[str, Any]:
        fit = self.fit_state
        n_s = len(fit.static) if fit is not None else 0
        n_d = len(fit.dynamic) if fit is not None else 0
        return {
            "num_gaussians": n_s + n_d,
            "num_static": n_s,
            "num_dynamic": n_d,
            "scaffold_nodes_final": fit.scaffold.M if fit is not None else 0,
            "backend": self.backend,
            "stages_s": dict(self.stage_s),
            "ablate_ba": self.cfg.ablate_ba,
            "ablate_sw": self.cfg.ablate_sw,
            "migration": dict(fit.migration) if fit is not None else {},
            **{k: v for k, v in self.info.items() if k not in ("scaffold_fit",)},
        }


register_method(
    MethodSpec(
        name="base",
        description="Base dynamic method: BA, static warm-up, motion scaffold + DQB dynamic Gaussians (MoSca-style)",
        config_cls=BaseConfig,
        presets={
            "paper": paper_config,
            "quick": quick_config,
            "paper-ablate-ba": _ablated(paper_config, True, False),
            "paper-ablate-sw": _ablated(paper_config, False, True),
            "paper-ablate-ba-sw": _ablated(paper_config, True, True),
            "quick-ablate-ba": _ablated(quick_config, True, False),
            "quick-ablate-sw": _ablated(quick_config, False, True),
            "quick-ablate-ba-sw": _ablated(quick_config, True, True),
            "smoke": smoke_config,
            "smoke-ablate-ba": _ablated(smoke_config, True, False),
            "smoke-ablate-sw": _ablated(smoke_config, False, True),
        },
        build=BaseMethod,
    )
)
