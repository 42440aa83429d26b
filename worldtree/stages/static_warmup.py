"""Static warm-up ("SW"): fit the background Gaussians to the static pixels of the training video first.

The dynamic (EPI) mask of each frame is dilated by ``dilate_px``; only the remaining static pixels enter the
loss, so moving content neither drags the background nor gets baked into it. The image loss is

    (1 - lambda_dssim) * L1_static + lambda_dssim * (1 - SSIM_static) + lambda_depth * depth_static

where ``L1_static`` averages over static pixels, ``SSIM_static`` averages the SSIM map (11x11 window) over
pixels whose whole window is static (the static mask eroded by the window radius, so no dynamic pixel reaches
the loss through a window), and ``depth_static`` is the mean ``|d - D| / D`` between the rendered depth
``d = depth / alpha`` and the (bundle-adjusted) depth prior ``D`` over static pixels with alpha > 0.5.

Cameras are fixed (they come from BA). The Gaussians start from the depth prior lifted at static pixels.
Training runs in :class:`worldtree.trainer.Trainer` (checkpoints, resume, progress) through
:class:`StaticWarmup`, which implements :class:`worldtree.trainer.Trainable`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from worldtree.gaussians import GaussianSet
from worldtree.infra.config_ranges import in_range
from worldtree.infra.errors import UserError
from worldtree.losses import SsimTargets, ssim_map
from worldtree.motion.lift import project_points
from worldtree.optim import GroupedAdam, gaussian_schedules
from worldtree.pixels import unit_float
from worldtree.render import rasterize
from worldtree.strategy import DensifyStrategy
from worldtree.trainer import DensifiedGaussianTrainable, StepOutput

SSIM_WINDOW = 11


@dataclass
class StaticWarmupConfig:
    """Static warm-up settings (steps: the paper's 6000)."""

    enabled: bool = True
    """Run the warm-up; False starts the joint fit from the lifted static points (``--ablate sw``)."""
    steps: int = 6000
    """Optimisation steps (one training frame per step, each frame once per epoch)."""
    dilate_px: int = 3
    """The dynamic mask is dilated by this many pixels (square) before its complement is used."""
    init_stride_px: int = 4
    """Initial points: the depth prior is lifted at static pixels on a grid of this stride in every frame."""
    init_max_points: int = 20_000
    """At most this many initial points (a seeded random subset)."""
    init_points_per_pixel: float = field(default=0.0, metadata=in_range(0, None, "points per pixel; 0 turns it off"))
    """Raise that bound to this many points per pixel of one training image (0: ``init_max_points`` alone), so
    a larger training image starts with proportionally more of its background."""
    init_balance_views: bool = True
    """Draw the initial subset with each candidate weighted by 1 / (training cameras whose image it falls in), so
    the background starts equally dense wherever it is, instead of dense where every camera sees it and sparse
    at a rig's edges, which one or two cameras see (and a test camera at that end renders). False: uniform."""
    init_opacity: float = 0.1
    """Opacity of the initial Gaussians."""
    lambda_dssim: float = 0.2
    """Weight of (1 - SSIM) in the image loss."""
    lambda_depth: float = 0.05
    """Weight of the relative depth error against the depth prior (0 disables it)."""
    lr_means: float = 1.6e-4
    """Initial position learning rate, times the scene extent (decays to 1% over ``steps``)."""
    lr_sh0: float = 2.5e-3
    """Colour learning rate."""
    lr_opacity: float = 0.05
    """Opacity-logit learning rate."""
    lr_scales: float = 5e-3
    """Log-scale learning rate."""
    lr_quats: float = 1e-3
    """Quaternion learning rate."""
    strategy: DensifyStrategy = field(
        default_factory=lambda: DensifyStrategy(refine_start=500, refine_stop=4000, reset_every=3000)
    )
    """Density control of the static set."""
    backend: str = "auto"
    """Rasterizer backend."""


def quick_static_warmup_config() -> StaticWarmupConfig:
    """CPU-friendly: 300 steps, densification every 100 steps between 100 and 250, no opacity reset; 4,000
    initial points, or 0.12 per pixel of a training image where that is more (15,552 at 480x270)."""
    return StaticWarmupConfig(
        steps=300,
        init_max_points=4000,
        init_points_per_pixel=0.12,
        strategy=DensifyStrategy(
            refine_start=100, refine_stop=250, refine_every=100, reset_every=0, max_gaussians=20_000
        ),
    )


def initial_points(cfg: StaticWarmupConfig, height: int, width: int) -> int:
    """Most initial points for training images of ``height x width``: ``init_max_points``, raised to
    ``ceil(init_points_per_pixel * height * width)`` where that is larger."""
    return max(int(cfg.init_max_points), math.ceil(cfg.init_points_per_pixel * int(height) * int(width)))


def static_weights(dynamic: torch.Tensor, dilate_px: int) -> torch.Tensor:
    """``[T, H, W]`` float 1 on static pixels, 0 on the dynamic mask ``dynamic [T, H, W]`` dilated by
    ``dilate_px`` (square structuring element)."""
    d = dynamic.float()[:, None]
    if dilate_px > 0:
        d = F.max_pool2d(d, 2 * dilate_px + 1, stride=1, padding=dilate_px)
    return 1.0 - d[:, 0]


def ssim_weights(static: torch.Tensor) -> torch.Tensor:
    """Weights of the 'valid' SSIM map ``[T, H - 10, W - 10]``: 1 where the whole 11x11 window is static."""
    inner = -F.max_pool2d(-static[:, None], SSIM_WINDOW, stride=1)  # min over each window
    return inner[:, 0]


@torch.no_grad()
def lift_pixels(
    images: torch.Tensor,
    depth: torch.Tensor,
    mask: torch.Tensor,
    Ks: torch.Tensor,
    w2cs: torch.Tensor,
    stride: int,
    max_points: int,
    generator: torch.Generator,
    balance_views: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(points [P, 3], colours [P, 3], frames [P] long)``: the depth prior ``depth [T, H, W]`` at the pixels
    of a ``stride`` grid where ``mask [T, H, W]`` is > 0.5 and the depth is valid, lifted with each frame's
    ``Ks``/``w2cs``; at most ``max_points`` (a random subset drawn from ``generator``; with ``balance_views``
    each candidate drawn with weight 1 / :func:`view_counts`). May be empty."""
    T, H, W = depth.shape
    pts, cols, frames = [], [], []
    v, u = torch.meshgrid(
        torch.arange(0, H, stride, device=depth.device), torch.arange(0, W, stride, device=depth.device),
        indexing="ij",
    )  # fmt: skip
    for t in range(T):
        z = depth[t, v, u]
        ok = (mask[t, v, u].float() > 0.5) & torch.isfinite(z) & (z > 0)
        if not ok.any():
            continue
        uu, vv, zz = u[ok].to(depth.dtype), v[ok].to(depth.dtype), z[ok]
        K = Ks[t].to(depth.dtype)
        x = (uu - K[0, 2]) / K[0, 0] * zz
        y = (vv - K[1, 2]) / K[1, 1] * zz
        cam = torch.stack([x, y, zz], -1)
        R, tr = w2cs[t, :3, :3].to(depth.dtype), w2cs[t, :3, 3].to(depth.dtype)
        pts.append((cam - tr) @ R)
        cols.append(unit_float(images[t, v[ok], u[ok]]))
        frames.append(torch.full((int(ok.sum()),), t, dtype=torch.long, device=depth.device))
    if not pts:
        z3 = depth.new_zeros((0, 3))
        return z3, z3.clone(), torch.zeros(0, dtype=torch.long, device=depth.device)
    P, C, F_ = torch.cat(pts), torch.cat(cols), torch.cat(frames)
    if P.shape[0] > max_points:
        if balance_views:
            weights = 1.0 / view_counts(P, Ks, w2cs, W, H).clamp_min(1).double().cpu()
            keep = torch.multinomial(weights, max_points, replacement=False, generator=generator).to(P.device)
        else:
            keep = torch.randperm(P.shape[0], generator=generator)[:max_points].to(P.device)
        P, C, F_ = P[keep], C[keep], F_[keep]
    return P, C, F_


#: Most cameras :func:`view_counts` projects into (evenly spaced over the frames): bounds its cost on long videos.
VIEW_COUNT_CAMERAS = 32


@torch.no_grad()
def view_counts(points: torch.Tensor, Ks: torch.Tensor, w2cs: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """``[P]`` long: of the training cameras ``Ks [T, 3, 3]`` / ``w2cs [T, 4, 4]`` (at most
    :data:`VIEW_COUNT_CAMERAS` of them, evenly spaced, the count then scaled back to T), how many have
    ``points [P, 3]`` in front of them and inside their ``width x height`` image. Occlusion is not tested: this
    says how much of the rig looks towards a point, which is what decides how densely frames sample it."""
    T = Ks.shape[0]
    pick = torch.linspace(0, T - 1, min(T, VIEW_COUNT_CAMERAS)).round().long().unique()
    count = torch.zeros(points.shape[0], dtype=torch.long, device=points.device)
    for t in pick.tolist():
        uv, z = project_points(points, Ks[t].to(points.dtype), w2cs[t].to(points.dtype))
        u, v = uv[:, 0], uv[:, 1]
        # Pixel centres at integers: the image spans [-0.5, size - 0.5).
        inside = (z > 1e-6) & (u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5)
        count += inside.long()
    if pick.numel() < T:  # a subset of the cameras: scaled to all of them, rounded, at least 1 where seen
        count = torch.where(count > 0, (count * T + pick.numel() - 1) // pick.numel(), count)
    return count


def lift_static_points(images, depth, static, Ks, w2cs, stride, max_points, generator, balance_views=False):
    """:func:`lift_pixels` on the static pixels; a :class:`UserError` when there is none."""
    P, C, _ = lift_pixels(images, depth, static, Ks, w2cs, stride, max_points, generator, balance_views)
    if P.shape[0] == 0:
        raise UserError(
            "static warm-up: no static pixel with a valid depth; the dynamic mask covers every frame "
            "(check the priors' EPI threshold or the imported masks)"
        )
    return P, C


class StaticWarmup(DensifiedGaussianTrainable):
    """Trainable static warm-up; after :class:`worldtree.trainer.Trainer` runs it, :attr:`gaussians` holds
    the background.

    Args:
        cfg: settings.
        images: [T, H, W, 3] training frames, uint8 or float in [0, 1] (:mod:`worldtree.pixels`).
        dynamic: [T, H, W] bool dynamic masks.
        depth: [T, H, W] depth prior (scene units, after BA scaling). Ks: [T, 3, 3]. w2cs: [T, 4, 4] (fixed).
        extent: scene extent (world units) for the learning rate and density thresholds.
        seed: seed of the frame order and of the initial subset.
        gaussians: start from these instead of the lifted depth (e.g. to continue a warm-up).
    """

    def __init__(
        self,
        cfg: StaticWarmupConfig,
        images: torch.Tensor,
        dynamic: torch.Tensor,
        depth: torch.Tensor,
        Ks: torch.Tensor,
        w2cs: torch.Tensor,
        extent: float,
        seed: int = 0,
        gaussians: GaussianSet | None = None,
    ):
        self.cfg = cfg
        self.images, self.depth, self.Ks, self.w2cs = images, depth, Ks, w2cs
        self.static = static_weights(dynamic.to(images.device), cfg.dilate_px)
        self.ssim_w = ssim_weights(self.static)
        self.ssim_targets = SsimTargets(images)  # the frames' SSIM statistics, once per frame
        self.extent = float(extent)
        self.order = torch.Generator().manual_seed(seed)
        self.queue: list[int] = []
        if gaussians is None:
            pts, cols = lift_static_points(
                images, depth, self.static, Ks, w2cs, cfg.init_stride_px, initial_points(cfg, *images.shape[1:3]),
                torch.Generator().manual_seed(seed), cfg.init_balance_views,
            )  # fmt: skip
            gaussians = GaussianSet.from_points(pts, cols, init_opacity=cfg.init_opacity)
        self.gaussians = gaussians
        self.optimizer = self._make_optimizer()
        cfg.strategy.check_sanity(self.gaussians, self.optimizer)
        self.strategy_state = cfg.strategy.initialize_state(self.extent)
        self.backend = "none"

    def _make_optimizer(self) -> GroupedAdam:
        c = self.cfg
        e = self.extent
        schedules = gaussian_schedules(
            c.lr_means * e, 0.01 * c.lr_means * e, c.steps, c.lr_quats, c.lr_scales, c.lr_opacity, c.lr_sh0
        )
        return GroupedAdam(dict(self.gaussians.params.items()), schedules)

    @property
    def frame_count(self) -> int:
        return int(self.images.shape[0])

    def frame_loss(self, i: int, out) -> tuple[torch.Tensor, dict[str, float]]:
        """Masked loss of render ``out`` against frame ``i`` (see the module docstring)."""
        c = self.cfg
        w = self.static[i]
        err = (out.rgb - unit_float(self.images[i])).abs().mean(-1)
        l1 = (err * w).sum() / w.sum().clamp_min(1.0)
        loss = (1.0 - c.lambda_dssim) * l1
        parts = {"l1": float(l1.detach())}
        if c.lambda_dssim > 0:
            sw = self.ssim_w[i]
            smap = ssim_map(out.rgb, self.ssim_targets[i]).mean(1)[0]  # [H-10, W-10], channels averaged
            s = (smap * sw).sum() / sw.sum().clamp_min(1.0)
            loss = loss + c.lambda_dssim * (1.0 - s) * (sw.sum() > 0)
            parts["ssim"] = float(s.detach())
        if c.lambda_depth > 0:
            alpha = out.alpha
            ok = (alpha.detach() > 0.5) & (w > 0) & (self.depth[i] > 0)
            d = out.depth / alpha.clamp_min(1e-6)
            prior = torch.where(ok, self.depth[i], torch.ones_like(self.depth[i]))
            rel = ((d - prior).abs() / prior) * ok
            l_d = rel.sum() / ok.sum().clamp_min(1)
            loss = loss + c.lambda_depth * l_d
            parts["depth"] = float(l_d.detach())
        return loss, parts

    def render(self, i: int):
        gs = self.gaussians
        W, H = self.images.shape[2], self.images.shape[1]
        out = rasterize(
            gs.means, gs.quats, gs.log_scales, gs.opacities, gs.colors, self.Ks[i], self.w2cs[i], W, H,
            backend=self.cfg.backend,
        )  # fmt: skip
        self.backend = out.backend
        return out

    # ------------------------------------------------------------------ Trainable
    def training_step(self, step: int) -> StepOutput:
        self.optimizer.set_step(step)
        i = self._next_frame()
        out = self.render(i)
        loss, parts = self.frame_loss(i, out)
        self.cfg.strategy.step_pre_backward(self.gaussians, self.optimizer, self.strategy_state, step, out)
        return StepOutput(loss=loss, scalars=parts, info=out)
