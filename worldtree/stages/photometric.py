"""Joint photometric fit of static + dynamic Gaussians, the motion scaffold and (from a set step) the cameras.

Each step renders one training frame ``i`` with the static Gaussians and the dynamic ones carried to frame
``i`` by the scaffold (:meth:`worldtree.dynamic.DynamicGaussians.at`), and minimises (appendix of the paper,
weights of MoSca, REFERENCE section 2)

    L = lambda_rgb (L1 + lambda_dssim (1 - SSIM))            RGB, 1.0 and 0.1
      + lambda_depth * SSI-L1(depth)                          0.05
      + lambda_track * track  (every ``track_every`` steps)   0.005, every 8 steps, clamp 100 px
      + lambda_depth_spread * spread  (every ``depth_spread_every`` steps)   not in the paper; 0 = off
      + motion regularisers (ARAP coordinate/length, velocity, acceleration; MotionLossConfig)

- SSI-L1: the rendered depth ``depth / alpha`` and the prior are each normalised by their median and mean
  absolute deviation over pixels with alpha > 0.5, then compared by L1 (scale-shift invariant).
- track: for a random other frame ``j``, every Gaussian's pixel position in frame ``j`` (its position at time
  ``j`` projected by camera ``j``) is rendered as a colour from camera ``i``; at each dynamic track's pixel in
  frame ``i`` this predicts its pixel in frame ``j``; the error is clamped at ``track_clamp_px``.
- spread: the blending-weighted variance of the Gaussians' camera depths along each pixel's ray over the
  squared mean depth (:func:`relative_depth_variance`), averaged over pixels with alpha > 0.5. One camera per
  time lets a moving object's Gaussians spread along that camera's rays at no photometric cost; seen from
  another camera the spread is a smear of about ``baseline x spread / depth`` pixels.
- cameras: a pose delta per frame (frame 0 fixed) whose learning rate is 0 before ``camera_start_step``.

Density control runs on the static and the dynamic set separately (their own :class:`DensifyStrategy`).
Scaffold nodes are densified too (``node_densify_*``): every ``node_densify_every`` steps inside
``[node_densify_start, node_densify_stop]``, dynamic Gaussians farther than ``scaffold.cfg.densify_dist_units``
from every node at their reference frame get new nodes (:func:`worldtree.motion.scaffold.densify`, at most
``densify_max_new`` = 32 per call as in the paper's appendix). Dynamic Gaussians that grew or moved away from
the tracks' nodes are then skinned to a node that can move them, instead of being held by the identity mix.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import torch

from worldtree.budget import growth_cap, negligible, render_contributions
from worldtree.dynamic import TIME_STD, DynamicGaussians, gaussians_at
from worldtree.gaussians import GaussianSet
from worldtree.infra.config_ranges import in_range
from worldtree.losses import SsimTargets, ssim
from worldtree.motion.lift import project_points
from worldtree.motion.regularizers import MotionLossConfig, frame_window, motion_losses
from worldtree.motion.scaffold import Scaffold, SkinCache, densify
from worldtree.optim import ConstantLR, GroupedAdam, gaussian_schedules
from worldtree.pixels import unit_float
from worldtree.priors.config import FreeSpaceConfig
from worldtree.priors.free_space import comparison_frames, points_in_free_space, window_minimum
from worldtree.render import rasterize
from worldtree.stages import set_migration as mig
from worldtree.stages.cameras import apply_delta
from worldtree.stages.frame_coupling import carried_frame, neighbour
from worldtree.strategy import DensifyStrategy, remove
from worldtree.trainer import StepOutput


@dataclass
class PhotometricConfig:
    """Joint photometric fit (defaults: the paper's NVIDIA-LS root schedule)."""

    steps: int = 4000
    """Optimisation steps (NVIDIA-LS root: 4000)."""
    lambda_rgb: float = 1.0
    """Weight of the RGB term."""
    lambda_dssim: float = 0.1
    """Weight of (1 - SSIM) inside the RGB term (added to L1)."""
    lambda_depth: float = 0.05
    """Weight of the scale-shift-invariant depth L1."""
    lambda_track: float = 0.005
    """Weight of the 2D track loss (pixels)."""
    track_every: int = 8
    """The track loss is evaluated every this many steps."""
    track_clamp_px: float = 100.0
    """Track errors are clamped at this many pixels."""
    lambda_depth_spread: float = 0.0
    """Weight of the depth spread along each pixel's ray (module docstring; not in the paper). 0 = off."""
    depth_spread_every: int = 4
    """The depth-spread term is evaluated every this many steps (one extra render of the frame)."""
    lambda_couple: float = 0.0
    """Weight of the neighbour coupling (``worldtree.stages.frame_coupling``): frame i's dynamic picture carried
    by the scaffold to the next or previous training frame must match that image (RGB term: L1 + lambda_dssim
    (1 - SSIM)); only the scaffold and the skinning correction learn from it. 0 = off."""
    couple_every: int = 2
    """The coupling term is evaluated every this many steps (alternately towards i + 1 and i - 1)."""
    motion: MotionLossConfig = field(default_factory=MotionLossConfig)
    """ARAP / velocity / acceleration weights."""
    motion_window: int = 0
    """Frames of the scaffold the motion regularisers see per step: a window of this many consecutive frames
    at a start drawn from (seed, step), so resumes repeat it (0 = every frame). Their cost grows with frames
    x nodes x neighbours and dominates a CPU step once the scaffold has hundreds of nodes; every term is a mean,
    so a window's value estimates the full-length one (frames near the ends are drawn a little less often).
    Keep it above the largest ARAP shift (4)."""
    camera_start_step: int = 1500
    """Cameras are optimised from this step on (NVIDIA-LS: 1500)."""
    lr_cam_rot: float = 1e-4
    """Camera rotation-delta learning rate (radians)."""
    lr_cam_trans: float = 1e-4
    """Camera translation-delta learning rate, times the scene extent."""
    lr_means: float = 1.6e-4
    """Gaussian position learning rate, times the extent, decaying to 1% over ``steps``."""
    lr_sh0: float = 2.5e-3
    """Colour learning rate."""
    lr_opacity: float = 0.05
    """Opacity-logit learning rate."""
    lr_scales: float = 5e-3
    """Log-scale learning rate."""
    lr_quats: float = 1e-3
    """Gaussian rotation learning rate."""
    lr_skin_corr: float = 1e-3
    """Skinning-correction learning rate."""
    lr_time_std: float = 1e-2
    """Learning rate of the dynamic Gaussians' log temporal std (when they have one, ``worldtree.dynamic``)."""
    lr_node_pos: float = 1.6e-4
    """Scaffold node position learning rate, times the extent."""
    lr_node_quat: float = 1e-3
    """Scaffold node rotation learning rate."""
    lr_node_sigma: float = 1e-3
    """Scaffold node radius (logit) learning rate."""
    static_strategy: DensifyStrategy = field(
        default_factory=lambda: DensifyStrategy(refine_start=500, refine_stop=3000, reset_every=0)
    )
    """Density control of the static Gaussians."""
    dynamic_strategy: DensifyStrategy = field(
        default_factory=lambda: DensifyStrategy(refine_start=500, refine_stop=3000, reset_every=0)
    )
    """Density control of the dynamic Gaussians."""
    node_densify_start: int = 500
    """First step at which scaffold nodes may be added (with the Gaussians' density control)."""
    node_densify_stop: int = 3000
    """No node is added after this step."""
    node_densify_every: int = 500
    """Period of node densification (0 = never; tree children never densify, as in the paper)."""
    reattach_every: int = 100
    """Skinning neighbourhoods are recomputed this often (and after every density change)."""
    migrate_every: int = 500
    """Period of the static <-> dynamic migration (``worldtree.stages.set_migration``; 0 = never; the quick
    schedule: 100)."""
    migrate_start: int = 500
    """First step of the migration."""
    migrate_stop: int = 3000
    """No migration after this step."""
    migrate_frames: int = 16
    """Training frames (evenly spaced) rendered to measure each Gaussian's residual at a migration."""
    migrate_residual: float = 0.08
    """A static Gaussian whose mean residual (image units) over the frames that see it exceeds this becomes
    dynamic; a dynamic one that does not move and stays under half of it becomes static."""
    migrate_min_views: int = 3
    """A Gaussian must be seen in at least this many of the measured frames to move."""
    floater_every: int = 100
    """Every this many steps from the static density control's start (0 = off; not in the paper), static
    Gaussians whose centre floats in front of the depth prior seen from the training frames
    (:func:`worldtree.priors.free_space.points_in_free_space`: nearer than ``1 - floater_tolerance`` of the
    depth in at least ``share`` of the frames that see it, out of ``views`` spread over the video, the depth's
    minimum over a ``window``: :class:`worldtree.priors.config.FreeSpaceConfig`'s defaults) are removed. A depth
    that measures moving objects pulls static Gaussians out to them where the masks miss them; a static world
    cannot hold a point there (docs/base_method.md, "Depth that a static world cannot hold")."""
    floater_tolerance: float = field(
        default=FreeSpaceConfig.tolerance,
        metadata=in_range(0, 1, "a relative margin", open_lo=True, open_hi=True),
    )
    """Relative margin of the floater test (the imported depth's check's, ``priors.free_space.tolerance``)."""
    static_move_frac: float = 0.002
    """A dynamic Gaussian moving less than this fraction of the scene extent over the video is 'still'."""
    backend: str = "auto"
    """Rasterizer backend."""


PRESET_MOTION_WINDOW = 12
"""Frames per step of the motion regularisers in the quick and paper presets (``motion_window``)."""


def quick_photometric_config() -> PhotometricConfig:
    """CPU-friendly: 600 steps, cameras from step 300, density control (Gaussians and scaffold nodes) every 100
    steps between 100 and 450, motion regularisers on a 12-frame window per step."""
    strat = DensifyStrategy(
        refine_start=100, refine_stop=450, refine_every=100, reset_every=0, max_gaussians=20_000
    )
    return PhotometricConfig(
        steps=600,
        camera_start_step=300,
        motion_window=PRESET_MOTION_WINDOW,
        node_densify_start=100,
        node_densify_stop=450,
        node_densify_every=100,
        migrate_every=100,
        migrate_start=150,
        migrate_stop=450,
        static_strategy=strat,
        dynamic_strategy=DensifyStrategy(**vars(strat)),
    )


class _StartAt:
    """Learning rate ``value`` from step ``start`` on, 0 before."""

    def __init__(self, start: int, value: float):
        self.start, self.value = start, value

    def __call__(self, step: int) -> float:
        return self.value if step >= self.start else 0.0


class _View:
    """The slice of a joint render that belongs to one Gaussian set, as density control expects it."""

    def __init__(self, out, sl: slice):
        self.rgb = out.rgb
        self.radii = out.radii[sl]
        self.means2d = out.means2d.detach()[sl].clone()
        grad = out.means2d.grad
        if grad is not None:
            self.means2d.grad = grad[sl].clone()


def ssi_normalise(d: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``(d - median) / mean|d - median|`` over ``mask`` (values elsewhere are returned but meaningless)."""
    v = d[mask]
    if v.numel() == 0:
        return torch.zeros_like(d)
    med = v.detach().median()
    scale = (v - med).abs().mean().clamp_min(1e-6)
    return (d - med) / scale


def ssi_depth_l1(depth: torch.Tensor, alpha: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
    """Scale-shift-invariant L1 between ``depth / alpha`` and ``prior`` [H, W] over alpha > 0.5."""
    mask = (alpha.detach() > 0.5) & torch.isfinite(prior) & (prior > 0)
    if int(mask.sum()) < 16:
        return depth.sum() * 0.0
    d = depth / alpha.clamp_min(1e-6)
    a, b = ssi_normalise(d, mask), ssi_normalise(prior, mask)
    return (a - b)[mask].abs().mean()


def anchored_depth_l1(
    depth: torch.Tensor, alpha: torch.Tensor, anchor: torch.Tensor, weight: torch.Tensor
) -> torch.Tensor:
    """Weighted relative L1 of the rendered depth against a fixed depth map, averaged over all pixels.

    Args:
        depth: ``[H, W]`` alpha-weighted rendered depth (world units along the camera's z).
        alpha: ``[H, W]`` accumulated opacity; ``depth / alpha`` is the pixel's mean depth.
        anchor: ``[H, W]`` depth to stay near (world units); pixels with ``anchor <= 0`` or not finite count 0.
        weight: ``[H, W]`` per-pixel weight in [0, 1].

    Returns:
        ``sum(w |depth / alpha - anchor| / anchor) / (H W)`` over pixels with ``alpha > 0.5`` (a scalar; 0
        with a gradient path when no pixel qualifies). Dividing by every pixel, not by the weighted ones, keeps
        the term's size proportional to the area it covers, as the RGB L1's is.
    """
    ok = (alpha.detach() > 0.5) & torch.isfinite(anchor) & (anchor > 0)
    a = torch.where(ok, anchor, torch.ones_like(anchor)).clamp_min(1e-6)  # no 0 or NaN reaches the division
    err = ((depth / alpha.clamp_min(1e-6) - a).abs() / a) * weight
    return torch.where(ok, err, torch.zeros_like(err)).mean()


def relative_depth_variance(
    moments: torch.Tensor, alpha: torch.Tensor, min_alpha: float = 0.5
) -> torch.Tensor | None:
    """Mean over pixels with ``alpha > min_alpha`` of ``Var[z] / E[z]^2`` along each ray.

    Args:
        moments: ``[H, W, 2]`` the rendered ``sum_i w_i c_i`` and ``sum_i w_i c_i^2`` of the Gaussians'
            centred depths ``c_i = z_i / z_ref - 1`` (``w_i`` the blending weights, ``z_ref > 0`` any fixed
            depth near the scene's: centring keeps float32's cancellation in ``E[c^2] - E[c]^2`` small).
        alpha: ``[H, W]`` accumulated opacity ``sum_i w_i``.

    Returns:
        A scalar (dimensionless; 0 for a single surface), or None when no pixel is opaque enough. With
        ``E[.] = sum w . / alpha``: ``Var[z] / E[z]^2 = (E[c^2] - E[c]^2) / (1 + E[c])^2``, guarded against
        ``E[z] <= 0`` (points behind the camera are not drawn) and negative rounding.
    """
    mask = alpha.detach() > min_alpha
    if not bool(mask.any()):
        return None
    a = alpha[mask].clamp_min(1e-6)
    mean = moments[..., 0][mask] / a
    var = (moments[..., 1][mask] / a - mean * mean).clamp_min(0.0)
    return (var / (1.0 + mean).square().clamp_min(1e-6)).mean()


def project(points: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor) -> torch.Tensor:
    """Pixels ``[N, 2]`` of world points ``[N, 3]`` (depth clamped at 1e-6 to stay finite;
    :func:`worldtree.motion.lift.project_points`)."""
    return project_points(points, K, w2c)[0]


class PhotometricFit:
    """Trainable joint fit (see the module docstring); :class:`worldtree.trainer.Trainer` runs it.

    Args:
        cfg: settings.
        images: [T, H, W, 3], uint8 or float in [0, 1] (:mod:`worldtree.pixels`).
        depth: [T, H, W] depth prior. Ks: [T, 3, 3]. w2cs: [T, 4, 4] start.
        static: background Gaussians (e.g. from the static warm-up). dynamic: dynamic Gaussians.
        scaffold: motion scaffold over the T frames.
        tracks: [T, N, 2] dynamic tracks (pixels) and ``track_vis`` [T, N] bool, or None (no track loss).
        extent: scene extent (world units). seed: frame order and track-pair sampling.
    """

    def __init__(
        self,
        cfg: PhotometricConfig,
        images: torch.Tensor,
        depth: torch.Tensor,
        Ks: torch.Tensor,
        w2cs: torch.Tensor,
        static: GaussianSet,
        dynamic: DynamicGaussians,
        scaffold: Scaffold,
        tracks: torch.Tensor | None,
        track_vis: torch.Tensor | None,
        extent: float,
        seed: int = 0,
    ):
        self.cfg = cfg
        self.images, self.depth, self.Ks, self.w2c0 = images, depth, Ks, w2cs
        self.static, self.dynamic, self.scaffold = static, dynamic, scaffold
        self.tracks, self.track_vis = tracks, track_vis
        self.extent = float(extent)
        self.T = images.shape[0]
        self.ssim_targets = SsimTargets(images)  # the frames' SSIM statistics, once per frame
        self.cam_xi = torch.zeros(max(self.T - 1, 0), 6, device=images.device, requires_grad=True)
        self.seed = int(seed)
        self.order = torch.Generator().manual_seed(seed)
        self.pairs = torch.Generator().manual_seed(seed + 1)
        self.queue: list[int] = []
        self._build_optimizers()
        cfg.static_strategy.check_sanity(self.static, self.static_opt)
        self.static_state = cfg.static_strategy.initialize_state(self.extent)
        self.dyn_state = cfg.dynamic_strategy.initialize_state(self.extent)
        self.cache = self.dynamic.attach(self.scaffold)
        self.backend = "none"
        self.migration = {"static_to_dynamic": 0, "dynamic_to_static": 0, "events": []}
        self.floaters = 0  # static Gaussians removed by the floater test (``floater_every``)

    # ------------------------------------------------------------------ set-up
    def _gauss_schedules(self, gs: GaussianSet) -> dict:
        c = self.cfg
        e = self.extent
        s = gaussian_schedules(
            c.lr_means * e, 0.01 * c.lr_means * e, c.steps, c.lr_quats, c.lr_scales, c.lr_opacity, c.lr_sh0
        )
        if "skin_corr" in gs.params:
            s["skin_corr"] = ConstantLR(c.lr_skin_corr)
        if TIME_STD in gs.params:
            s[TIME_STD] = ConstantLR(c.lr_time_std)
        return s

    def _build_optimizers(self) -> None:
        c = self.cfg
        st = self._gauss_schedules(self.static)
        self.static_opt = GroupedAdam({k: self.static.params[k] for k in st}, st)
        ds = self._gauss_schedules(self.dynamic)
        self.dyn_opt = GroupedAdam({k: self.dynamic.params[k] for k in ds}, ds)
        other = {
            "node_pos": self.scaffold.pos,
            "node_quat": self.scaffold.quat,
            "node_sigma": self.scaffold.sigma_logit,
            "cam": self.cam_xi,
        }
        sched = {
            "node_pos": ConstantLR(c.lr_node_pos * self.extent),
            "node_quat": ConstantLR(c.lr_node_quat),
            "node_sigma": ConstantLR(c.lr_node_sigma),
            # One group for the camera twist: rotation and translation share the lr; translation is scaled.
            "cam": _StartAt(c.camera_start_step, c.lr_cam_rot),
        }
        self.other_opt = GroupedAdam(other, sched)

    # ------------------------------------------------------------------ rendering
    def camera(self, i: int) -> torch.Tensor:
        """[4, 4] current world-to-camera pose of frame ``i``."""
        if i == 0 or self.T < 2:
            return self.w2c0[i]
        xi = self.cam_xi[i - 1]
        ratio = self.cfg.lr_cam_trans * self.extent / max(self.cfg.lr_cam_rot, 1e-12)
        return apply_delta(torch.cat([xi[:3] * ratio, xi[3:]]), self.w2c0[i])

    def cameras(self) -> torch.Tensor:
        """[T, 4, 4] current poses (detached)."""
        with torch.no_grad():
            return torch.stack([self.camera(i) for i in range(self.T)])

    def gaussians_at(self, t: int, cache=None):
        """Joint tensors ``(means, quats, log_scales, opacities, colours)`` of static + dynamic at frame t
        (:func:`worldtree.dynamic.gaussians_at`)."""
        return gaussians_at(
            self.static, self.dynamic, self.scaffold, t, cache if cache is not None else self.cache
        )

    def render(self, K, w2c, width, height, t: int, colors=None, cache=None, gaussians=None):
        """Render frame ``t``'s Gaussians (``gaussians``: this frame's :meth:`gaussians_at` result when the
        caller already has it) from camera ``K``/``w2c``, with their own colours or ``colors`` [N, 3]."""
        m, q, ls, o, c = self.gaussians_at(t, cache) if gaussians is None else gaussians
        out = rasterize(
            m, q, ls, o, c if colors is None else colors, K, w2c, width, height, backend=self.cfg.backend
        )
        self.backend = out.backend
        return out

    # ------------------------------------------------------------------ losses
    def track_means_at(self, j: int) -> torch.Tensor:
        """``[N, 3]`` means of every rendered Gaussian at frame ``j``, in render order (static, dynamic)."""
        mj, _ = self.dynamic.at(self.scaffold, j, self.cache)
        return torch.cat([self.static.means, mj])

    def track_loss(self, i: int, gaussians=None) -> torch.Tensor | None:
        """Clamped pixel error of the rendered correspondence map from frame ``i`` to a random frame.

        ``gaussians``: frame ``i``'s :meth:`gaussians_at` result, when the step already computed it for its
        RGB render (the correspondence map is the same Gaussians at frame ``i`` with other colours); None
        evaluates the motion model again (same values)."""
        if self.tracks is None or self.T < 2 or self.tracks.shape[1] == 0:
            return None
        j = int(torch.randint(0, self.T - 1, (1,), generator=self.pairs))
        j = j + 1 if j >= i else j
        both = self.track_vis[i] & self.track_vis[j]
        if int(both.sum()) == 0:
            return None
        H, W = self.images.shape[1:3]
        uv_j = project(self.track_means_at(j), self.Ks[j], self.camera(j))
        col = torch.cat([uv_j, torch.ones_like(uv_j[:, :1])], 1)
        out = self.render(self.Ks[i], self.camera(i), W, H, i, colors=col, gaussians=gaussians)
        flow = out.rgb[..., :2] / out.alpha.clamp_min(1e-6)[..., None]  # [H, W, 2] predicted pixel in j
        p_i = self.tracks[i, both]
        col_i = p_i[:, 0].round().long().clamp(0, W - 1)
        row_i = p_i[:, 1].round().long().clamp(0, H - 1)
        ok = out.alpha[row_i, col_i].detach() > 0.5
        if int(ok.sum()) == 0:
            return None
        err = (flow[row_i, col_i] - self.tracks[j, both]).norm(dim=-1).clamp(max=self.cfg.track_clamp_px)
        return err[ok].mean()

    def depth_spread_loss(self, i: int, gaussians) -> torch.Tensor | None:
        """:func:`relative_depth_variance` of frame ``i``'s Gaussians (``gaussians``: its
        :meth:`gaussians_at` result) seen from camera ``i``; None when nothing is opaque enough."""
        H, W = self.images.shape[1:3]
        w2c = self.camera(i)
        z = gaussians[0] @ w2c[2, :3] + w2c[2, 3]  # camera depth of every centre
        front = z.detach() > 0
        if not bool(front.any()):
            return None
        z_ref = z.detach()[front].median().clamp_min(1e-6)
        c = z / z_ref - 1.0
        moments = torch.stack([c, c * c, torch.zeros_like(c)], 1)
        out = self.render(self.Ks[i], w2c, W, H, i, colors=moments, gaussians=gaussians)
        return relative_depth_variance(out.rgb[..., :2], out.alpha)

    def coupling_extra(self, j: int):
        """Further Gaussians drawn (fixed) behind the carried picture at frame ``j``; None here (a tree node
        adds its ancestors)."""
        return None

    def coupling_loss(self, i: int, j: int) -> torch.Tensor | None:
        """RGB error (L1 + lambda_dssim (1 - SSIM)) of frame ``i``'s dynamic picture carried to frame ``j`` and
        rendered from camera ``j`` (:func:`worldtree.stages.frame_coupling.carried_frame`), or None when no
        dynamic Gaussian is seen at ``i``."""
        carried = carried_frame(
            self.static, self.dynamic, self.scaffold, i, j, self.cache, extra=self.coupling_extra(j)
        )
        if carried is None:
            return None
        H, W = self.images.shape[1:3]
        out = rasterize(*carried, self.Ks[j], self.camera(j).detach(), W, H, backend=self.cfg.backend)
        loss = (out.rgb - unit_float(self.images[j])).abs().mean()
        if self.cfg.lambda_dssim > 0:
            loss = loss + self.cfg.lambda_dssim * (1.0 - ssim(out.rgb, self.ssim_targets[j]))
        return loss

    def frame_losses(self, i: int, step: int) -> tuple[torch.Tensor, dict[str, float], Any]:
        c = self.cfg
        H, W = self.images.shape[1:3]
        frame = self.gaussians_at(i)  # shared by the RGB render and the track loss's render of frame i
        out = self.render(self.Ks[i], self.camera(i), W, H, i, gaussians=frame)
        l1 = (out.rgb - unit_float(self.images[i])).abs().mean()
        loss = l1
        parts = {"l1": float(l1.detach())}
        if c.lambda_dssim > 0:
            s = ssim(out.rgb, self.ssim_targets[i])
            loss = loss + c.lambda_dssim * (1.0 - s)
            parts["ssim"] = float(s.detach())
        loss = c.lambda_rgb * loss
        if c.lambda_depth > 0:
            ld = ssi_depth_l1(out.depth, out.alpha, self.depth[i])
            loss = loss + c.lambda_depth * ld
            parts["depth"] = float(ld.detach())
        if c.lambda_track > 0 and c.track_every > 0 and step % c.track_every == 0:
            lt = self.track_loss(i, frame)
            if lt is not None:
                loss = loss + c.lambda_track * lt
                parts["track_px"] = float(lt.detach())
        if c.lambda_depth_spread > 0 and c.depth_spread_every > 0 and step % c.depth_spread_every == 0:
            lds = self.depth_spread_loss(i, frame)
            if lds is not None:
                loss = loss + c.lambda_depth_spread * lds
                parts["spread"] = float(lds.detach())
        if c.lambda_couple > 0 and c.couple_every > 0 and step % c.couple_every == 0 and self.T >= 2:
            lc = self.coupling_loss(i, neighbour(i, self.T, step // c.couple_every))
            if lc is not None:
                loss = loss + c.lambda_couple * lc
                parts["couple"] = float(lc.detach())
        if self.scaffold.M > 0:
            w = self._motion_window(step)
            ml = motion_losses(
                self.scaffold.pos[w], self.scaffold.quat[w], self.scaffold.arap_graphs(), c.motion
            )
            loss = loss + ml.total
            parts["motion"] = float(ml.total.detach())
        return loss, parts, out

    def _motion_window(self, step: int) -> slice:
        """Frames the motion regularisers see at ``step`` (``motion_window``; a function of seed and step)."""
        return frame_window(self.T, self.cfg.motion_window, self.seed, step)

    # ------------------------------------------------------------------ Trainable
    def _next_frame(self) -> int:
        if not self.queue:
            self.queue = torch.randperm(self.T, generator=self.order).tolist()
        return self.queue.pop()

    def training_step(self, step: int) -> StepOutput:
        for opt in (self.static_opt, self.dyn_opt, self.other_opt):
            opt.set_step(step)
        i = self._next_frame()
        loss, parts, out = self.frame_losses(i, step)
        return StepOutput(loss=loss, scalars=parts, info=out)

    def optimizer_step(self, step: int, out: StepOutput) -> dict[str, float]:
        for opt in (self.static_opt, self.dyn_opt, self.other_opt):
            opt.step()
            opt.zero_grad()
        n_s = len(self.static)
        render = out.info
        before = len(self.dynamic)
        self.cfg.static_strategy.step_post_backward(
            self.static, self.static_opt, self.static_state, step, _View(render, slice(0, n_s))
        )
        if before > 0:
            self.cfg.dynamic_strategy.step_post_backward(
                self.dynamic, self.dyn_opt, self.dyn_state, step, _View(render, slice(n_s, n_s + before))
            )
        self._remove_floaters(step)
        changed = len(self.dynamic) != before or (step % self.cfg.dynamic_strategy.refine_every == 0)
        changed = self._densify_nodes(step) > 0 or changed
        changed = self._migrate(step) > 0 or changed
        if changed or (self.cfg.reattach_every > 0 and step % self.cfg.reattach_every == 0):
            self.cache = self.dynamic.attach(self.scaffold)
        return {
            "static": float(len(self.static)),
            "dynamic": float(len(self.dynamic)),
            "nodes": float(self.scaffold.M),
        }

    # ------------------------------------------------------------------ budget and residuals
    @torch.no_grad()
    def residuals(self) -> torch.Tensor:
        """``[T, H, W]`` per-pixel L1 photometric residual (mean over colour channels) of every frame."""
        H, W = self.images.shape[1:3]
        out = [
            (self.render(self.Ks[i], self.camera(i), W, H, i).rgb - unit_float(self.images[i])).abs().mean(-1)
            for i in range(self.T)
        ]
        return torch.stack(out)

    def mean_error(self) -> float:
        """Mean L1 photometric error over every pixel of every frame (colour units; non-finite -> inf)."""
        r = self.residuals()
        v = float(r.mean())
        return v if v == v else float("inf")

    def contributions(self) -> torch.Tensor:
        """``[N]`` contribution (:func:`worldtree.budget.render_contributions`) of every rendered Gaussian over
        this fit's frames, in render order (static, dynamic, then whatever a subclass appends)."""
        H, W = self.images.shape[1:3]
        views = [(i, self.Ks[i], self.cameras_detached(i)) for i in range(self.T)]
        return render_contributions(self.gaussians_at, views, W, H, self.cfg.backend)

    def cameras_detached(self, i: int) -> torch.Tensor:
        """``[4, 4]`` current pose of frame ``i`` without gradient."""
        with torch.no_grad():
            return self.camera(i).detach()

    def prune_negligible(
        self, threshold: float, dynamic: bool = True, total_frac: float | None = None, static: bool = True
    ) -> dict[str, int]:
        """Remove the (with ``static``) static and (with ``dynamic``) dynamic Gaussians whose contribution over
        this fit's frames is below ``threshold`` (pixels; :mod:`worldtree.budget`), with ``total_frac`` only the
        smallest whose contributions add up to at most that fraction of a frame's pixels; their Adam moments and
        density statistics go with them. Returns the counts before and after."""
        H, W = self.images.shape[1:3]
        total = None if total_frac is None else float(total_frac) * H * W
        return self._prune_with(self.contributions(), threshold, dynamic, total, static)

    def _prune_with(
        self, contrib: torch.Tensor, thr: float, dynamic: bool = True, total: float | None = None,
        static: bool = True,
    ) -> dict[str, int]:
        n_s, n_d = len(self.static), len(self.dynamic)
        report = {"static_before": n_s, "dynamic_before": n_d}
        own = contrib[: n_s + n_d].clone()
        if not dynamic:
            own[n_s:] = float("inf")  # deferred: never selected
        if not static:
            own[:n_s] = float("inf")
        drop = negligible(own, thr, total)  # one shared total for both sets
        drop_s, drop_d = drop[:n_s], drop[n_s:]
        if bool(drop_s.any()):
            remove(self.static, self.static_opt, self.static_state, drop_s)
        if bool(drop_d.any()):
            remove(self.dynamic, self.dyn_opt, self.dyn_state, drop_d)
            self.cache = self.dynamic.attach(self.scaffold)
        report.update(static_after=len(self.static), dynamic_after=len(self.dynamic))
        return report

    def set_budget(self, budget: int) -> dict[str, int]:
        """Cap density control at ``budget`` Gaussians in all, shared by the static and dynamic sets in
        proportion to their current sizes (never below what a set holds: the cap stops growth only)."""
        n_s, n_d = len(self.static), len(self.dynamic)
        total = max(n_s + n_d, 1)
        cap_s = growth_cap(round(budget * n_s / total), n_s)
        cap_d = growth_cap(round(budget * n_d / total), n_d)
        c = self.cfg
        self.cfg = dataclasses.replace(
            c,
            static_strategy=dataclasses.replace(c.static_strategy, max_gaussians=cap_s),
            dynamic_strategy=dataclasses.replace(c.dynamic_strategy, max_gaussians=cap_d),
        )
        return {"budget": int(budget), "static_cap": cap_s, "dynamic_cap": cap_d}

    def _densify_nodes(self, step: int) -> int:
        """Add scaffold nodes for far dynamic Gaussians when scheduled; returns the number added."""
        c = self.cfg
        if (
            c.node_densify_every <= 0
            or not c.node_densify_start <= step <= c.node_densify_stop
            or step % c.node_densify_every != 0
            or len(self.dynamic) == 0
        ):
            return 0
        new, added = densify(self.scaffold, self.dynamic.means.detach(), self.dynamic.t_ref)
        if added == 0:
            return 0
        self._swap_scaffold(new)
        return added

    @torch.no_grad()
    def _remove_floaters(self, step: int) -> int:
        """Static Gaussians in front of the depth prior seen from the training frames, removed when scheduled
        (``floater_every``); returns how many. ``self.floaters`` counts them over the fit."""
        c = self.cfg
        if c.floater_every <= 0 or step < c.static_strategy.refine_start or step % c.floater_every != 0:
            return 0
        if len(self.static) == 0:
            return 0
        test = FreeSpaceConfig(tolerance=c.floater_tolerance)  # the imported depth's check's other defaults
        ref = window_minimum(self.depth, test.window)
        w2cs = torch.stack([self.cameras_detached(t) for t in range(self.T)])
        frames = comparison_frames(None, self.T, test.views)
        mask = points_in_free_space(
            self.static.means.detach(), ref, self.Ks, w2cs, frames, test.tolerance, test.share
        )
        n = int(mask.sum())
        if n:
            remove(self.static, self.static_opt, self.static_state, mask)
        self.floaters += n
        return n

    @torch.no_grad()
    def _migrate(self, step: int) -> int:
        """Static <-> dynamic migration when scheduled (module ``set_migration``); returns Gaussians moved."""
        c = self.cfg
        if (
            c.migrate_every <= 0
            or not c.migrate_start <= step <= c.migrate_stop
            or (step - c.migrate_start) % c.migrate_every != 0
            or self.scaffold.M == 0
            or not mig.compatible(self.static, self.dynamic)
        ):
            return 0
        H, W = self.images.shape[1:3]
        n_s, n_d = len(self.static), len(self.dynamic)
        dev = self.images.device
        acc_s, acc_d = mig.ResidualAccumulator(n_s, dev), mig.ResidualAccumulator(n_d, dev)
        cache = self.dynamic.attach(self.scaffold)
        frames = torch.linspace(0, self.T - 1, min(self.T, max(1, c.migrate_frames))).round().long().tolist()
        for t in sorted(set(frames)):
            m, q, ls, o, col = self.gaussians_at(t, cache)
            w2c = self.camera(t)
            out = rasterize(m, q, ls, o, col, self.Ks[t], w2c, W, H, backend=c.backend)
            r = mig.residual_map(out.rgb, unit_float(self.images[t]))
            front = mig.in_front(m, self.Ks[t], w2c, out.depth, out.alpha)
            acc_s.add(r, out.means2d[:n_s], out.radii[:n_s], t, front[:n_s])
            acc_d.add(r, out.means2d[n_s:], out.radii[n_s:], t, front[n_s:])
        seen_s = acc_s.count >= c.migrate_min_views
        to_dyn = seen_s & (acc_s.mean() > c.migrate_residual)
        still = mig.max_displacement(self.dynamic, self.scaffold, cache, sorted(set(frames)))
        seen_d = acc_d.count >= c.migrate_min_views
        to_static = (
            seen_d & (acc_d.mean() < 0.5 * c.migrate_residual) & (still < c.static_move_frac * self.extent)
        )
        a = mig.dynamic_to_static(
            self.static,
            self.static_opt,
            self.static_state,
            self.dynamic,
            self.dyn_opt,
            self.dyn_state,
            to_static,
        )
        # Static indices are unchanged by appending to the static set: move the high-residual ones after.
        mask = torch.cat([to_dyn, torch.zeros(len(self.static) - n_s, dtype=torch.bool, device=dev)])
        t_ref = torch.cat([acc_s.frame, torch.zeros(len(self.static) - n_s, dtype=torch.long, device=dev)])
        b = mig.static_to_dynamic(
            self.static,
            self.static_opt,
            self.static_state,
            self.dynamic,
            self.dyn_opt,
            self.dyn_state,
            mask,
            t_ref,
        )
        self.migration["static_to_dynamic"] += b
        self.migration["dynamic_to_static"] += a
        self.migration["events"].append([int(step), b, a])
        return a + b

    def _swap_scaffold(self, new: Scaffold) -> None:
        """Put a scaffold with more nodes (appended along dim 1) in place; Adam moments of the kept nodes
        follow them and the new nodes start from zero moments."""
        old_m = self.scaffold.M
        pairs = (("node_pos", new.pos), ("node_quat", new.quat), ("node_sigma", new.sigma_logit))

        def grow(value: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
            out = torch.zeros_like(like)
            if like.dim() == 1:  # radii [M]
                out[:old_m] = value
            else:  # trajectories [T, M, C]
                out[:, :old_m] = value
            return out

        for name, param in pairs:
            self.other_opt.replace_param(name, param, lambda _k, v, like=param: grow(v, like))
        self.scaffold = new

    def state_dict(self) -> dict[str, Any]:
        def cpu(d):
            return {k: (v.detach().cpu() if isinstance(v, torch.Tensor) else v) for k, v in d.items()}

        return {
            "static": cpu(dict(self.static.params.items())),
            "dynamic": cpu(dict(self.dynamic.params.items())),
            "scaffold": self.scaffold.to_state(),
            "cam_xi": self.cam_xi.detach().cpu(),
            "static_opt": self.static_opt.state_dict(),
            "dyn_opt": self.dyn_opt.state_dict(),
            "other_opt": self.other_opt.state_dict(),
            "static_state": cpu(self.static_state),
            "dyn_state": cpu(self.dyn_state),
            "queue": list(self.queue),
            "pairs_rng": self.pairs.get_state(),
            "migration": dict(self.migration),
            "floaters": self.floaters,
            "cache": self.cache.to_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        dev = self.images.device
        self.static.load_params(state["static"])
        self.dynamic.load_params(state["dynamic"])
        self.scaffold = Scaffold.from_state(state["scaffold"], dev)
        self.cam_xi = state["cam_xi"].to(dev).clone().requires_grad_(True)
        self._build_optimizers()
        self.static_opt.load_state_dict(state["static_opt"])
        self.dyn_opt.load_state_dict(state["dyn_opt"])
        self.other_opt.load_state_dict(state["other_opt"])
        self.static_state = {
            k: (v.to(dev) if isinstance(v, torch.Tensor) else v) for k, v in state["static_state"].items()
        }
        self.dyn_state = {
            k: (v.to(dev) if isinstance(v, torch.Tensor) else v) for k, v in state["dyn_state"].items()
        }
        self.queue = [int(i) for i in state["queue"]]
        self.pairs.set_state(state["pairs_rng"])
        self.migration = state.get("migration", self.migration)
        self.floaters = int(state.get("floaters", 0))
        # The skinning neighbourhoods in use at the checkpoint, not new ones from its (moved) node positions:
        # they are recomputed only every ``reattach_every`` steps, so a resumed fit must keep the old ones.
        cache = state.get("cache")
        self.cache = (
            SkinCache.from_state(cache, dev) if cache is not None else self.dynamic.attach(self.scaffold)
        )
