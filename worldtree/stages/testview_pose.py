"""Test-view pose: bring the held-out test camera into the reconstruction's frame.

Two steps, as in the authors' evaluation (REFERENCE section 3):

1. :func:`align_sim3` -- a similarity ``x -> s R x + t`` from the *given* training poses onto the *optimised*
   ones (after bundle adjustment and photometric camera refinement), applied to the test camera's given pose
   (:meth:`worldtree.stages.cameras.Sim3.apply_w2c`). Umeyama on the camera centres; when the centres do not
   determine a rotation (fewer than 3 non-collinear centres) the rotation comes from the camera orientations.
   Not in the authors' code: :class:`CameraPlacement` then applies the pose residual that the Sim(3) left the
   training frames nearest in time and space (``PoseRefineConfig.residual_time_sigma``), which is how the
   model places any camera it did not train with, and each test frame may start from it.
2. :func:`refine_test_poses` -- per test frame, an se(3) delta on the world-to-camera pose optimised with Adam
   on the photometric L1 error over pixels whose rendered alpha exceeds 0.1; 300 steps for the first frame, 30
   for each next one starting from the previous frame's result; the learning rate decays log-linearly from
   3e-3 to 1e-4 within each frame.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from worldtree.infra import stop_request, thread_governor
from worldtree.motion import se3
from worldtree.optim import ExponentialLR
from worldtree.pixels import unit_float
from worldtree.render import rasterize
from worldtree.stages.cameras import Sim3, apply_delta, centres

RenderFn = Callable[[int, torch.Tensor], object]
"""``render_fn(time, w2c [4, 4]) -> RenderOutput`` (needs ``.rgb [H, W, 3]`` and ``.alpha [H, W]``),
differentiable with respect to ``w2c``."""

GaussiansAt = Callable[[int], tuple[torch.Tensor, ...]]
"""``gaussians_at(time) -> (means [N, 3], quats [N, 4], log_scales [N, 3], opacities [N], colours [N, 3])``."""


class FrozenModelRenderer:
    """A :data:`RenderFn` over a model that does not change while the test pose is refined.

    The Gaussians at a frame (scaffold motion and skinning of every dynamic Gaussian, the ancestors' too) depend
    on the frame only, not on the pose being optimised, so they are computed once per frame, without autograd,
    and reused by every pose step of that frame; gradients reach ``w2c`` only. The last frame's tensors are
    kept (:func:`refine_test_poses` visits each frame once, in order). Renders equal the uncached
    ``rasterize(*gaussians_at(t), ...)`` and the pose gradient equals the one with the model in the graph.

    Args:
        gaussians_at: the model's Gaussians at a frame (:data:`GaussiansAt`).
        K: [3, 3] intrinsics of the test camera. width, height: render size in pixels.
        backend: rasterizer backend.
    """

    def __init__(self, gaussians_at: GaussiansAt, K: torch.Tensor, width: int, height: int, backend: str):
        self.gaussians_at, self.K, self.width, self.height = gaussians_at, K, int(width), int(height)
        self.backend = backend
        self._time: int | None = None
        self._gaussians: tuple[torch.Tensor, ...] = ()
        self.computed = 0
        """How many times the Gaussians were computed (once per distinct consecutive frame)."""

    def __call__(self, time: int, w2c: torch.Tensor):
        if self._time != int(time):
            with torch.no_grad():
                self._gaussians = tuple(x.detach() for x in self.gaussians_at(int(time)))
            self._time = int(time)
            self.computed += 1
        return rasterize(*self._gaussians, self.K, w2c, self.width, self.height, backend=self.backend)


@dataclass
class PoseRefineConfig:
    """Test-time pose optimisation (defaults: the authors' schedule)."""

    align_rotation: str = "orientations"
    """Rotation of the Sim(3) alignment from the camera ``orientations`` (robust for small rigs) or from the
    ``centres`` (Umeyama); see :func:`align_sim3`."""
    enabled: bool = True
    """Refine the aligned test pose photometrically; False keeps the Sim(3)-aligned pose."""
    start_at_same_camera: bool = True
    """A test camera whose given pose is a training frame's (:func:`coinciding_frame`) starts from, and without
    test images is drawn at, that frame's fitted pose instead of the Sim(3)-aligned one."""
    residual_time_sigma: float = 1.0
    """Placing a camera the model did not train with (:class:`CameraPlacement`): after the Sim(3), the pose
    residual of the training frames within about this many frames of its time (a Gaussian weight, in frames),
    nearer cameras weighing more. 0: the Sim(3) alone (the placement before 2026-11-27)."""
    first_steps: int = 300
    """Adam steps for the first test frame (from the placed pose)."""
    next_steps: int = 30
    """Adam steps for every next frame, starting from the previous frame's refined pose."""
    lr_init: float = 3e-3
    """Learning rate at the first step of each frame (twist units: radians and world units)."""
    lr_final: float = 1e-4
    """Learning rate at the last step of each frame (log-linear decay)."""
    translation_lr_scale: float = 1.0
    """Multiplier of the learning rate of the translational part (set to the scene scale when world units
    are far from ~1)."""
    alpha_threshold: float = 0.1
    """Only pixels whose rendered alpha exceeds this enter the loss."""
    min_pixels: int = 16
    """A frame with fewer such pixels is not optimised (its pose is carried over)."""


def quick_pose_refine_config() -> PoseRefineConfig:
    """CPU-friendly: 60 steps for the first frame, 10 for each next one."""
    return PoseRefineConfig(first_steps=60, next_steps=10)


@torch.no_grad()
def align_sim3(
    src_w2cs: torch.Tensor, dst_w2cs: torch.Tensor, rotation_from: str = "centres", rtol: float = 1e-6
) -> Sim3:
    """Similarity taking the frame of poses ``src_w2cs`` [T, 4, 4] onto that of ``dst_w2cs`` [T, 4, 4].

    ``rotation_from="centres"``: Umeyama (least squares ``sum_i |s R c_i + t - d_i|^2`` over camera centres
    ``c`` -> ``d``) when the centres span a plane. ``rotation_from="orientations"``, and the fallback when the
    centres are collinear or coincide: ``R`` is the chordal mean of the per-camera rotations ``Rd_i^T Rs_i``,
    and ``s``, ``t`` the least-squares fit of the centres with that ``R`` (``s = 1`` when the centres
    coincide). For a small rig far from the scene the orientations fix ``R`` far better than the centres (a
    centre error of 10% of the rig's size tilts the Umeyama rotation by degrees). Computed in float64;
    returned in ``dst_w2cs``'s dtype.
    """
    if rotation_from not in ("centres", "orientations"):
        raise ValueError(
            f"align_sim3: rotation_from must be 'centres' or 'orientations', got {rotation_from!r}"
        )
    if src_w2cs.shape != dst_w2cs.shape or src_w2cs.dim() != 3 or src_w2cs.shape[1:] != (4, 4):
        raise ValueError(
            f"align_sim3: expected two [T, 4, 4] pose stacks, got {tuple(src_w2cs.shape)}, {tuple(dst_w2cs.shape)}"
        )
    src, dst = src_w2cs.double(), dst_w2cs.double()
    cs, cd = centres(src), centres(dst)
    fit = se3.procrustes(cs, cd, with_scale=True, rtol=rtol)
    if rotation_from == "centres" and int(fit.kind) == 0:
        R, s, t = fit.rotation, float(fit.scale), fit.translation
    else:
        M = (dst[:, :3, :3].transpose(-1, -2) @ src[:, :3, :3]).sum(0)
        U, _, Vh = torch.linalg.svd(M)
        D = torch.eye(3, dtype=M.dtype, device=M.device)
        D[2, 2] = torch.sign(torch.linalg.det(U @ Vh))
        R = U @ D @ Vh
        a, b = cs - cs.mean(0), cd - cd.mean(0)
        var = float((a * a).sum())
        s = float(((a @ R.T) * b).sum()) / var if var > 1e-24 else 1.0
        t = cd.mean(0) - s * R @ cs.mean(0)
    dt, dev = dst_w2cs.dtype, dst_w2cs.device
    return Sim3(s, R.to(dev, dt), t.to(dev, dt))


@torch.no_grad()
def coinciding_frame(w2c: torch.Tensor, given_w2cs: torch.Tensor, tol: float = 1e-4) -> int | None:
    """The first training frame whose given pose is the pose ``w2c`` [4, 4] itself, or None.

    ``given_w2cs`` [T, 4, 4] are the training frames' given poses. A frame coincides when its rotation differs
    by at most ``tol`` (Frobenius norm of the difference, about radians) and its centre by at most ``tol``
    times the spread of the training centres (the rig's size; ``tol`` world units when there is one centre).
    Intrinsics are not compared: only the pose is mapped. In the NVIDIA short protocol the test camera is frame
    0's rig camera: placing it at that frame's fitted pose, instead of through the Sim(3) of all the frames,
    draws what was fitted from that very camera (on Balloon1 the Sim(3) leaves frame 0's camera about 0.1
    degrees off its fitted pose, which costs its static pixels 5 dB, docs/base_method.md)."""
    if given_w2cs.shape[0] == 0:
        return None
    W, Ws = w2c.double(), given_w2cs.double()
    dR = torch.linalg.matrix_norm(Ws[:, :3, :3] - W[:3, :3], ord="fro")
    cs = centres(Ws)
    spread = float((cs - cs.mean(0)).norm(dim=-1).max())
    dc = (cs - centres(W[None])[0]).norm(dim=-1)
    ok = (dR <= tol) & (dc <= tol * (spread if spread > 0 else 1.0))
    hits = torch.nonzero(ok).flatten()
    return int(hits[0]) if hits.numel() else None


@dataclass
class CameraPlacement:
    """Where the model puts a camera given in the scene's frame that it did not train with.

    The Sim(3) of the given training poses onto the fitted ones (:func:`align_sim3`) is one transform for the
    whole video; bundle adjustment and the photometric fit leave every frame a residual ``D_i = fitted_i
    placed_i^-1`` (``placed_i`` the Sim(3) of frame i's given pose), which drifts smoothly along the video: on
    generated scenes a training frame drawn through the Sim(3) alone loses 2-10 dB against its fitted pose,
    and the residuals of the frames nearest in time predict its own far better than those of the same camera
    at other times (docs/base_method.md). A camera at time ``t`` and centre ``c`` is placed at ``D(t, c)
    Sim3(w2c)``, where ``D`` blends the frames' residual twists (se(3) logarithms) with weights
    ``exp(-(t - t_i)^2 / (2 sigma^2)) / (|c - c_i|^2 + e^2)``: ``sigma`` in frames, ``c_i`` the frames' given
    centres, ``e`` a tenth of the rig's camera spacing (median distance from a camera to its nearest other
    one), so a camera at a training frame's centre and time takes mostly that frame's residual, and one
    between two cameras takes both. The residuals are small (a fraction of a degree), where blending twists
    is accurate.

    Attributes:
        sim3: given (scene) frame -> model frame.
        given_centres: [T, 3] training frames' given camera centres (scene units).
        twists: [T, 6] each frame's residual twist ``(rho, omega)`` (model units, radians); 0 where not finite.
        time_sigma: Gaussian width in frames; 0 places by the Sim(3) alone.
        spacing: ``e`` above (scene units, > 0).
    """

    sim3: Sim3
    given_centres: torch.Tensor
    twists: torch.Tensor
    time_sigma: float
    spacing: float
    times: torch.Tensor | None = None
    """[T] the frames' times (None: frame i at time i)."""

    @staticmethod
    @torch.no_grad()
    def fit(given_w2cs: torch.Tensor, fitted_w2cs: torch.Tensor, sim3: Sim3, time_sigma: float) -> CameraPlacement:
        """The placement of ``sim3`` and the residuals of the training frames' ``fitted_w2cs`` [T, 4, 4] (model
        frame) against their ``given_w2cs`` [T, 4, 4] (scene frame); frame ``i`` is at time ``i``."""
        if given_w2cs.shape != fitted_w2cs.shape or given_w2cs.dim() != 3 or given_w2cs.shape[1:] != (4, 4):
            raise ValueError(
                f"CameraPlacement.fit: expected two [T, 4, 4] pose stacks, got {tuple(given_w2cs.shape)}, "
                f"{tuple(fitted_w2cs.shape)}"
            )
        given, fitted = given_w2cs.double(), fitted_w2cs.double().to(given_w2cs.device)
        placed = sim3.apply_w2c(given)
        D = fitted @ torch.linalg.inv(placed)
        twists = se3.log(*se3.from_matrix(D))
        twists = torch.where(torch.isfinite(twists).all(-1, keepdim=True), twists, torch.zeros_like(twists))
        c = centres(given)
        return CameraPlacement(sim3, c, twists, float(time_sigma), 0.1 * _spacing(c))

    @torch.no_grad()
    def weights(self, centre: torch.Tensor, time: float) -> torch.Tensor:
        """[T] weights (summing to 1) of the training frames' residuals for a camera at ``centre`` [3] (scene
        frame) and ``time`` (frames, may be fractional)."""
        T = self.twists.shape[0]
        times = torch.arange(T, dtype=torch.float64, device=self.twists.device) if self.times is None else (
            self.times.to(self.twists))  # fmt: skip
        d2 = ((self.given_centres - centre.to(self.given_centres)) ** 2).sum(-1)
        logw = -((float(time) - times) ** 2) / (2.0 * self.time_sigma**2) - torch.log(d2 + self.spacing**2)
        return torch.softmax(logw, dim=0)  # the largest term is 1 before normalising: never 0 / 0

    @torch.no_grad()
    def place(self, w2c: torch.Tensor, time: float) -> torch.Tensor:
        """[4, 4] model-frame pose of the scene-frame camera ``w2c`` [4, 4] at ``time``, in ``w2c``'s dtype."""
        out = self.sim3.apply_w2c(w2c)
        if not self.time_sigma > 0 or self.twists.shape[0] == 0 or not math.isfinite(float(time)):
            return out
        w = self.weights(centres(w2c.double()[None])[0], time)
        q, t = se3.exp((w[:, None] * self.twists).sum(0))
        return (se3.to_matrix(q, t).to(out) @ out).to(w2c.dtype)


def _spacing(c: torch.Tensor) -> float:
    """Median distance from a camera centre ``c`` [T, 3] to its nearest distinct one; 1.0 when all coincide."""
    if c.shape[0] < 2:
        return 1.0
    d = torch.cdist(c, c)
    scale = float(d.max())
    d = torch.where(d > 1e-9 * max(scale, 1e-12), d, torch.full_like(d, math.inf))
    nearest = d.min(dim=1).values
    nearest = nearest[torch.isfinite(nearest)]
    return float(nearest.median()) if nearest.numel() else 1.0


@dataclass
class PoseRefineResult:
    """Refined test poses and the photometric error before/after, per test frame (in the order given)."""

    w2cs: torch.Tensor
    """[F, 4, 4] refined world-to-camera pose of each test frame."""
    loss_before: list[float]
    """Masked L1 at the frame's starting pose (nan when the frame had too few pixels)."""
    loss_after: list[float]
    """Masked L1 at the returned pose."""
    steps: list[int]
    """Adam steps spent on each frame."""


def masked_l1(rgb: torch.Tensor, alpha: torch.Tensor, target: torch.Tensor, threshold: float):
    """``(mean |rgb - target| over pixels with alpha > threshold and channels, pixel count)``; rgb/target
    [H, W, 3], alpha [H, W]. The selection is not differentiated (it is a mask, not a weight)."""
    valid = (alpha.detach() > threshold).to(rgb.dtype)
    n = int(valid.sum())
    err = ((rgb - target).abs().sum(-1) * valid).sum() / (3.0 * max(n, 1))
    return err, n


def refine_test_poses(
    render_fn: RenderFn,
    w2c_init: torch.Tensor,
    images: torch.Tensor,
    times: Sequence[int],
    cfg: PoseRefineConfig | None = None,
    w2c_candidates: torch.Tensor | None = None,
) -> PoseRefineResult:
    """Photometric refinement of the test camera, frame after frame.

    Args:
        render_fn: ``render_fn(time, w2c)`` -> render with ``.rgb`` [H, W, 3] and ``.alpha`` [H, W].
        w2c_init: [4, 4] starting pose of the first frame (typically the placed test pose).
        images: [F, H, W, 3] test images, uint8 or float in [0, 1] (:mod:`worldtree.pixels`), at the render size.
        times: F time indices (frame k is rendered at ``times[k]``).
        cfg: schedule (default :class:`PoseRefineConfig`).
        w2c_candidates: [F, 4, 4] another starting pose per frame (the camera placed at that frame's time,
            :class:`CameraPlacement`): each frame after the first starts from whichever of it and the previous
            frame's result renders the frame's image with the smaller error (with ``cfg.enabled`` False: is
            at its candidate). None: the previous result.

    Each frame optimises ``xi`` [6] in ``w2c = exp(xi) w2c_start`` with a fresh Adam; a frame whose final
    error is not finite or above its starting error keeps its starting pose.
    """
    cfg = cfg or PoseRefineConfig()
    if images.dim() != 4 or images.shape[0] != len(times):
        raise ValueError(f"refine_test_poses: {len(times)} times but images of shape {tuple(images.shape)}")
    if w2c_candidates is not None and tuple(w2c_candidates.shape) != (len(times), 4, 4):
        raise ValueError(
            f"refine_test_poses: {len(times)} times but candidates of shape {tuple(w2c_candidates.shape)}"
        )
    current = w2c_init.detach().clone()
    out_w2cs, before, after, steps_used = [], [], [], []
    for k, time in enumerate(times):
        target = unit_float(images[k]).to(current)
        n_steps = cfg.first_steps if k == 0 else cfg.next_steps
        with torch.no_grad():
            out = render_fn(int(time), current)
            l0, n0 = masked_l1(out.rgb, out.alpha, target, cfg.alpha_threshold)
            if k > 0 and w2c_candidates is not None:
                cand = w2c_candidates[k].to(current)
                oc = render_fn(int(time), cand)
                lc, nc = masked_l1(oc.rgb, oc.alpha, target, cfg.alpha_threshold)
                better = nc >= cfg.min_pixels and torch.isfinite(lc) and (
                    n0 < cfg.min_pixels or not torch.isfinite(l0) or float(lc) < float(l0)
                )
                if better or not cfg.enabled:  # without refinement the test image chooses nothing
                    current, l0, n0 = cand.clone(), lc, nc
        if not cfg.enabled or n_steps <= 0 or n0 < cfg.min_pixels:
            out_w2cs.append(current.clone())
            before.append(float(l0) if n0 >= cfg.min_pixels else float("nan"))
            after.append(before[-1])
            steps_used.append(0)
            continue
        xi = torch.zeros(6, dtype=current.dtype, device=current.device, requires_grad=True)
        opt = torch.optim.Adam([xi], lr=cfg.lr_init)
        sched = ExponentialLR(cfg.lr_init, cfg.lr_final, max(n_steps - 1, 1))
        scale = torch.ones(6, dtype=current.dtype, device=current.device)
        scale[:3] = cfg.translation_lr_scale
        for s in range(n_steps):
            stop_request.check()  # a stop whose exception was lost elsewhere
            thread_governor.tick()  # the torch team follows the free cores
            for g in opt.param_groups:
                g["lr"] = sched(s)
            out = render_fn(int(time), apply_delta(xi * scale, current))
            loss, n = masked_l1(out.rgb, out.alpha, target, cfg.alpha_threshold)
            if n < cfg.min_pixels or not torch.isfinite(loss):
                break
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if xi.grad is None or not torch.isfinite(xi.grad).all():
                break
            opt.step()
        with torch.no_grad():
            cand = apply_delta(xi.detach() * scale, current)
            out = render_fn(int(time), cand)
            l1, n1 = masked_l1(out.rgb, out.alpha, target, cfg.alpha_threshold)
        if n1 >= cfg.min_pixels and torch.isfinite(l1) and float(l1) <= float(l0):
            current = cand
            after.append(float(l1))
        else:
            after.append(float(l0))
        before.append(float(l0))
        steps_used.append(n_steps)
        out_w2cs.append(current.clone())
    return PoseRefineResult(
        torch.stack(out_w2cs) if out_w2cs else w2c_init[None, :0], before, after, steps_used
    )
