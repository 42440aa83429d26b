"""Static 3D Gaussian Splatting: one Gaussian set for the whole video, blind to time.

Trained on the monocular training video (one random training frame per step, each frame once per epoch) with
the 3DGS loss ``0.8 L1 + 0.2 (1 - SSIM)``, Adam groups with 3DGS learning rates (position decaying
exponentially, scaled by the scene extent), view-dependent SH colour whose degree grows during training, and
3DGS density control. It initialises from SfM points when the
scene folder holds ``points3d.npy`` (``[N, 3]`` world xyz, or ``[N, 6]`` with RGB in [0, 1]) and otherwise from
random points in the training cameras' near/far frustums. The test camera renders the same image at every
time, which is the point of the baseline: moving content is averaged away.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from methods.model_folder import read_model_json
from methods.registry import QUICK_FULL_SIZE_PIXELS, CommonConfig, MethodSpec, register_method
from worldtree.budget import growth_cap, negligible, node_budget, render_contributions
from worldtree.gaussian_frame import GaussianFrame, RenderMode, render_frame
from worldtree.gaussians import GaussianSet
from worldtree.infra.atomic import atomic_write_json
from worldtree.infra.errors import UserError
from worldtree.losses import photometric_loss
from worldtree.optim import ConstantLR, GroupedAdam, gaussian_schedules
from worldtree.pixels import unit_float
from worldtree.render import rasterize
from worldtree.scene import Scene
from worldtree.stages.cameras import Sim3
from worldtree.strategy import DensifyStrategy, remove
from worldtree.trainer import (
    DensifiedGaussianTrainable,
    StepOutput,
    TrainContext,
    Trainer,
    TrainerConfig,
    TrainSummary,
)

POINTS_FILE = "points3d.npy"


@dataclass
class StaticConfig(CommonConfig):
    """Static 3DGS settings (defaults: the ``paper`` preset, the 3DGS paper's schedule)."""

    init: str = "auto"
    """Initial points: ``sfm`` (scene's points3d.npy), ``random`` (in the camera frustums) or ``auto``."""
    init_num_points: int = 100_000
    """Number of random initial points (``random`` init only)."""
    init_opacity: float = 0.1
    """Opacity of the initial Gaussians."""
    lambda_dssim: float = 0.2
    """Weight of the (1 - SSIM) term in the image loss."""
    lr_means: float = 1.6e-4
    """Initial position learning rate, times the scene extent."""
    lr_means_final: float = 1.6e-6
    """Final position learning rate (exponential decay over ``steps``), times the scene extent."""
    lr_sh0: float = 2.5e-3
    """Colour (SH DC) learning rate."""
    lr_opacity: float = 0.05
    """Opacity-logit learning rate."""
    lr_scales: float = 5e-3
    """Log-scale learning rate."""
    lr_quats: float = 1e-3
    """Quaternion learning rate."""
    sh_degree: int = 3
    """Highest spherical-harmonic degree of the colours (0 = view-independent; at most 3)."""
    sh_increase_every: int = 1000
    """The SH degree used in training rises by one every this many steps, up to ``sh_degree`` (as 3DGS)."""
    lr_shN: float = 2.5e-3 / 20
    """Learning rate of the higher SH coefficients."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Background colour (RGB in [0, 1])."""
    backend: str = "auto"
    """Rasterizer backend: auto, cpu, gsplat or reference."""
    strategy: DensifyStrategy = field(default_factory=DensifyStrategy)
    """Density control (3DGS defaults)."""
    checkpoint_every: int = 1000
    """Checkpoint period in steps."""
    log_every: int = 100
    """Progress/TensorBoard period in steps (when not on a terminal)."""

    def ignored_settings(self) -> dict[str, str]:
        """:meth:`CommonConfig.ignored_settings` plus ``strategy.max_gaussians``, which the budget sets."""
        out = super().ignored_settings()
        if self.budget_on():
            out["strategy.max_gaussians"] = "the Gaussian budget sets it; --set budget.enabled=false to cap by hand"
        return out


def paper_config() -> StaticConfig:
    """3DGS schedule: 30k steps, densify every 100 steps from 500 to 15k, opacity reset every 3k, SH degree 3."""
    return StaticConfig()


def quick_config() -> StaticConfig:
    """CPU-friendly: 1500 steps at half resolution (full resolution for a video of at most 2,000,000 pixels),
    densify every 100 steps from 200 to 1000, no opacity reset, view-independent colour."""
    return StaticConfig(
        steps=1500,
        downscale=2,
        full_size_pixels=QUICK_FULL_SIZE_PIXELS,
        init_num_points=5_000,
        sh_degree=0,
        strategy=DensifyStrategy(
            refine_start=200, refine_stop=1000, refine_every=100, reset_every=0, max_gaussians=30_000
        ),
        checkpoint_every=500,
        log_every=50,
    )


def camera_centres(w2cs: torch.Tensor) -> torch.Tensor:
    """``[T, 3]`` camera centres ``-R^T t`` of world-to-camera poses ``[T, 4, 4]``."""
    return -torch.einsum("tji,tj->ti", w2cs[:, :3, :3], w2cs[:, :3, 3])


def scene_extent(w2cs: torch.Tensor, near: float, far: float) -> float:
    """3DGS's scene extent, ``1.1 * max distance of a camera centre from their mean``, in world units.

    A monocular rig can have nearly coincident cameras, so the radius is floored at a tenth of the mean
    scene depth ``(near + far) / 2``; the extent scales the position learning rate and the size thresholds.
    """
    w = w2cs.detach().double().cpu()
    centres = camera_centres(w)
    radius = float((centres - centres.mean(0)).norm(dim=-1).max()) if len(centres) else 0.0
    return 1.1 * max(radius, 0.1 * 0.5 * (near + far))


def load_points(root: Path) -> tuple[torch.Tensor, torch.Tensor | None] | None:
    """``(xyz [N, 3], rgb [N, 3] or None)`` from ``root/points3d.npy``, or None when there is no such file."""
    path = root / POINTS_FILE
    if not path.is_file():
        return None
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise UserError(f"{path}: unreadable ({e}); rewrite it as a float [N, 3] or [N, 6] .npy") from e
    if arr.ndim != 2 or arr.shape[1] not in (3, 6) or arr.shape[0] == 0:
        raise UserError(f"{path}: shape {arr.shape}; expected [N, 3] xyz or [N, 6] xyz + RGB in [0, 1]")
    t = torch.from_numpy(arr.astype(np.float32))
    return t[:, :3], (t[:, 3:].clamp(0, 1) if arr.shape[1] == 6 else None)


class StaticGaussians(DensifiedGaussianTrainable):
    """The static baseline for one scene; implements :class:`methods.registry.Method` and
    :class:`worldtree.trainer.Trainable`."""

    def __init__(self, cfg: StaticConfig, scene: Scene, device: torch.device):
        if cfg.init not in ("auto", "sfm", "random"):
            raise UserError(f"init={cfg.init!r}: choose auto, sfm or random")
        if not 0 <= cfg.sh_degree <= 3:
            raise UserError(f"sh_degree={cfg.sh_degree}: choose 0, 1, 2 or 3")
        self.cfg = cfg
        self.device = device
        self.scene = scene.to(device)
        self.extent = scene_extent(scene.w2cs, scene.near, scene.far)
        self.background = torch.tensor(cfg.background, dtype=torch.float32, device=device)
        self.order = torch.Generator().manual_seed(cfg.seed)
        self.queue: list[int] = []
        self.init_source = ""
        self.gaussians = self._initial_gaussians(scene)
        self.gaussians.add_sh(cfg.sh_degree)
        self.centres = camera_centres(self.scene.w2cs)
        self.optimizer = self._make_optimizer()
        cfg.strategy.check_sanity(self.gaussians, self.optimizer)
        self.strategy_state = cfg.strategy.initialize_state(self.extent)
        self.backend = "none"
        self._render_cache: tuple[bytes, torch.Tensor] | None = None

    # ------------------------------------------------------------------ set-up
    def _initial_gaussians(self, scene: Scene) -> GaussianSet:
        pts = load_points(scene.root) if self.cfg.init in ("auto", "sfm") else None
        if self.cfg.init == "sfm" and pts is None:
            raise UserError(f"init=sfm but {scene.root / POINTS_FILE} does not exist; use init=random")
        if pts is not None:
            self.init_source = f"sfm ({len(pts[0])} points)"
            xyz, rgb = pts
            return GaussianSet.from_points(
                xyz.to(self.device), None if rgb is None else rgb.to(self.device), self.cfg.init_opacity
            )
        self.init_source = f"random ({self.cfg.init_num_points} points in the camera frustums)"
        gen = torch.Generator().manual_seed(self.cfg.seed)
        return GaussianSet.random_in_frustums(
            self.cfg.init_num_points,
            self.scene.Ks,
            self.scene.w2cs,
            scene.width,
            scene.height,
            scene.near,
            scene.far,
            images=scene.images,
            init_opacity=self.cfg.init_opacity,
            generator=gen,
        )

    def _make_optimizer(self) -> GroupedAdam:
        c = self.cfg
        e = self.extent
        schedules = gaussian_schedules(
            c.lr_means * e, c.lr_means_final * e, c.steps, c.lr_quats, c.lr_scales, c.lr_opacity, c.lr_sh0
        )
        if "shN" in self.gaussians.params:
            schedules["shN"] = ConstantLR(c.lr_shN)
        return GroupedAdam(dict(self.gaussians.params.items()), schedules)

    # ------------------------------------------------------------------ Trainable
    @property
    def frame_count(self) -> int:
        return self.scene.num_frames

    def _sh_degree_at(self, step: int | None) -> int:
        if step is None or self.cfg.sh_increase_every <= 0:
            return self.cfg.sh_degree
        return min(self.cfg.sh_degree, step // self.cfg.sh_increase_every)

    def _render(self, K, w2c, width, height, centre, step=None):
        gs = self.gaussians
        colors = gs.view_colors(centre, self._sh_degree_at(step))
        out = rasterize(
            gs.means, gs.quats, gs.log_scales, gs.opacities, colors, K, w2c, width, height,
            background=self.background, backend=self.cfg.backend,
        )  # fmt: skip
        self.backend = out.backend
        return out

    def training_step(self, step: int) -> StepOutput:
        self.optimizer.set_step(step)
        i = self._next_frame()
        s = self.scene
        out = self._render(s.Ks[i], s.w2cs[i], s.width, s.height, self.centres[i], step)
        loss, parts = photometric_loss(out.rgb, unit_float(s.images[i]), self.cfg.lambda_dssim)
        self.cfg.strategy.step_pre_backward(self.gaussians, self.optimizer, self.strategy_state, step, out)
        return StepOutput(loss=loss, scalars=parts, info=out)

    def optimizer_step(self, step: int, out: StepOutput) -> dict[str, float]:
        scalars = super().optimizer_step(step, out)
        self._render_cache = None  # parameters changed
        return scalars

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self._render_cache = None

    # ------------------------------------------------------------------ Method
    def fit(self, ctx: TrainContext) -> TrainSummary:
        c = self.cfg
        tcfg = TrainerConfig(steps=c.steps, checkpoint_every=c.checkpoint_every, log_every=c.log_every)
        self.adaptive: dict[str, Any] = {"budget_on": c.budget_on(), "early_stop_on": c.early_stop_on()}
        if c.budget_on():
            err = self._mean_error()
            budget = node_budget(self.scene.width, self.scene.height, err, c.budget)
            cap = growth_cap(budget, len(self.gaussians))
            self.cfg = dataclasses.replace(c, strategy=dataclasses.replace(c.strategy, max_gaussians=cap))
            self.adaptive["budget"] = {"error_start": err, "budget": budget, "cap": cap}
        stop = c.early_stop.detector(self.frame_count, min(c.strategy.refine_stop, c.steps)) if (
            c.early_stop_on()) else None  # fmt: skip
        trainer = Trainer(
            tcfg,
            self,
            checkpoint_dir=ctx.checkpoint_dir,
            generators={"frame_order": self.order},
            tensorboard_dir=ctx.tensorboard_dir,
            progress=ctx.progress,
            description="static",
            stop=stop,
        )
        summary = trainer.fit(resume=ctx.resume)
        self.adaptive.update(steps_max=c.steps, steps_taken=summary.end_step)
        if stop is not None:
            self.adaptive["early_stop"] = stop.report()
        if c.budget_on():
            self.adaptive["prune"] = self._prune(c.budget.prune_contribution, c.budget.prune_total_frac)
        return summary

    @torch.no_grad()
    def _mean_error(self) -> float:
        """Mean L1 of the current model over every training frame (colour units)."""
        s = self.scene
        errs = [float((self._render(s.Ks[i], s.w2cs[i], s.width, s.height, self.centres[i]).rgb - unit_float(s.images[i]))
                      .abs().mean()) for i in range(s.num_frames)]  # fmt: skip
        e = float(np.mean(errs))
        return e if np.isfinite(e) else float("inf")

    def _prune(self, threshold: float, total_frac: float | None = None) -> dict[str, int]:
        """Remove the Gaussians whose contribution over the training views is below ``threshold`` (pixels),
        smallest first and only while they sum to at most ``total_frac`` of a view's pixels."""
        s, gs = self.scene, self.gaussians
        views = [(i, s.Ks[i], s.w2cs[i]) for i in range(s.num_frames)]
        contrib = render_contributions(
            lambda _t: (gs.means, gs.quats, gs.log_scales, gs.opacities, gs.colors), views, s.width, s.height,
            self.cfg.backend,
        )  # fmt: skip
        before = len(gs)
        total = None if total_frac is None else float(total_frac) * s.width * s.height
        drop = negligible(contrib, threshold, total)
        if bool(drop.any()):
            remove(gs, self.optimizer, self.strategy_state, drop)
        self._render_cache = None
        return {"before": before, "after": len(self.gaussians)}

    @torch.no_grad()
    def render(
        self, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, time: int, test_view: bool = False
    ) -> torch.Tensor:
        """``[height, width, 3]`` in [0, 1]; ``time`` and ``test_view`` are ignored (the model is static and
        knows nothing of the test camera), so one camera is rendered once and reused."""
        key = (
            K.detach().cpu().double().numpy().tobytes()
            + w2c.detach().cpu().double().numpy().tobytes()
            + np.array([width, height]).tobytes()
        )
        if self._render_cache is not None and self._render_cache[0] == key:
            return self._render_cache[1]
        K = K.to(self.device, torch.float32)
        w2c = w2c.to(self.device, torch.float32)
        img = self._render(K, w2c, width, height, camera_centres(w2c[None])[0]).rgb.clamp(0.0, 1.0)
        self._render_cache = (key, img)
        return img

    def save_model(self, folder: Path) -> None:
        folder = Path(folder)
        self.gaussians.save(folder / "gaussians.pt")
        self.gaussians.write_ply(folder / "gaussians.ply")
        atomic_write_json(
            folder / "model.json",
            {
                "method": "static",
                "num_gaussians": len(self.gaussians),
                "scene_extent": self.extent,
                "background": list(self.cfg.background),
                "sh_degree": self.gaussians.sh_degree,
                "files": {"gaussians.pt": "GaussianSet.load", "gaussians.ply": "3DGS viewer PLY"},
            },
        )

    def load_model(self, folder: Path) -> None:
        """Read ``folder/gaussians.pt`` written by :meth:`save_model` (the config's background and backend are
        the run's, from its recorded config)."""
        folder = Path(folder)
        read_model_json(folder, "static")
        self.gaussians = GaussianSet.load(folder / "gaussians.pt", self.device)
        self._render_cache = None

    @torch.no_grad()
    def gaussians_at(self, time: int) -> GaussianFrame:
        """The whole set at any time (the scene's own frame: the Sim(3) is the identity; nothing is dynamic)."""
        gs = self.gaussians
        n = len(gs)
        return GaussianFrame(
            time=int(time), means=gs.means.detach(), quats=gs.quats.detach(), log_scales=gs.log_scales.detach(),
            opacities=gs.opacities.detach(), sh0=gs.params["sh0"].detach(),
            dynamic=torch.zeros(n, dtype=torch.bool, device=gs.device),
            scene_to_model=Sim3.identity(device=gs.device),
            shN=gs.params["shN"].detach() if "shN" in gs.params else None,
        )  # fmt: skip

    def model_w2c(
        self, w2c: torch.Tensor, time: int, test_view: bool = False, frame: int | None = None
    ) -> torch.Tensor:
        """``w2c`` itself: the model lives in the scene's frame and never moves a camera."""
        return w2c.to(self.device, torch.float32)

    @torch.no_grad()
    def render_mode(
        self, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, time: int,
        mode: RenderMode = "rgb", test_view: bool = False, frame: int | None = None,
    ) -> torch.Tensor:  # fmt: skip
        """:meth:`render` for ``rgb``; the other modes rasterize :meth:`gaussians_at` (``dynamic``: black)."""
        if mode == "rgb":
            return self.render(K, w2c, width, height, time, test_view)
        return render_frame(self.gaussians_at(time), K, self.model_w2c(w2c, time), width, height, mode,
                            self.cfg.backend, self.background)  # fmt: skip

    def node_at(self, time: float) -> int | None:
        return None

    @torch.no_grad()
    def render_between(
        self, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, time: float
    ) -> torch.Tensor:
        """:meth:`render`: the one model draws every time the same, a time it never trained on included."""
        return self.render(K, w2c, width, height, 0)

    def stats(self) -> dict[str, Any]:
        return {
            "num_gaussians": len(self.gaussians),
            "backend": self.backend,
            "scene_extent": self.extent,
            "init": self.init_source,
            "adaptive": getattr(self, "adaptive", {}),
        }


register_method(
    MethodSpec(
        name="static",
        description="Static 3D Gaussian Splatting: one Gaussian set for the whole video (no motion)",
        config_cls=StaticConfig,
        presets={"paper": paper_config, "quick": quick_config},
        build=StaticGaussians,
    )
)
