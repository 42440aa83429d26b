"""Tracklet bundle adjustment ("BA"): cameras, per-frame depth scales and static track depths.

Unknowns (MoSca's BA, REFERENCE section 2):

- a pose delta per frame, ``w2c_t = exp(xi_t) w2c_t^0`` (:func:`worldtree.stages.cameras.apply_delta`); frame 0
  is held fixed (gauge of the rigid motion);
- a per-frame depth scale ``s_t = exp(l_t - mean(l))`` of the depth prior (the mean-zero log keeps the
  world's scale: only relative scales are free);
- a per-track log depth correction ``delta_i`` of each selected static track.

Each track ``i`` is anchored at its reference frame ``r_i`` (its first visible frame with a valid depth):
``X_i = c2w_r (K_r^-1 (u, v, 1) * s_r D_r(u, v) * exp(delta_i))``. The loss over visible observations is

    L = lambda_reproj * mean_{(t,i), t != r_i} huber(min(|pi(K_t w2c_t X_i) - p_ti|, clamp_px); huber_px)
      + lambda_depth  * mean_{(t,i) with valid depth} min(|log(z_t(X_i) / (s_t D_t(p_ti)))|, depth_clamp)

where ``z_t`` is the camera depth of ``X_i`` in frame ``t``. The clamps make outliers (wrong tracks, moving
points labelled static) contribute a constant, i.e. no gradient. Up to ``max_tracks`` static tracks are used.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from worldtree.infra import stop_request, thread_governor
from worldtree.motion.lift import sample_depth
from worldtree.optim import ExponentialLR
from worldtree.stages.cameras import apply_delta


@dataclass
class BundleAdjustConfig:
    """Tracklet bundle adjustment settings (steps: the paper's 2000)."""

    enabled: bool = True
    """Run BA; False keeps the given poses and unit depth scales (the ``--ablate ba`` switch)."""
    steps: int = 2000
    """Adam steps."""
    max_tracks: int = 10_000
    """At most this many static tracks (a seeded random subset of the usable ones)."""
    min_track_frames: int = 2
    """A track needs at least this many visible frames."""
    lr_rot: float = 1e-3
    """Learning rate of the rotation part of the pose deltas (radians)."""
    lr_trans: float = 1e-3
    """Learning rate of the translation part, times the scene scale (median reference depth)."""
    lr_depth_scale: float = 1e-2
    """Learning rate of the per-frame log depth scales."""
    lr_track_depth: float = 1e-2
    """Learning rate of the per-track log depth corrections."""
    lr_final_ratio: float = 0.1
    """Every learning rate decays log-linearly to this fraction of its initial value at the last step."""
    lambda_reproj: float = 1.0
    """Weight of the reprojection term (pixels)."""
    lambda_depth: float = 10.0
    """Weight of the depth-ratio consistency term (log ratio). Not given by the paper: with the reprojection
    term in pixels, 10 makes a 10% depth disagreement cost about as much as a 1 px reprojection error, which
    keeps the poses from drifting along the rotation/translation ambiguity of noisy tracks (tested)."""
    huber_px: float = 1.0
    """Huber threshold of the reprojection error, pixels."""
    clamp_px: float = 50.0
    """Reprojection errors are clamped at this many pixels (no gradient beyond)."""
    depth_clamp: float = 0.5
    """Absolute log depth ratios are clamped at this (no gradient beyond)."""
    min_depth_conf: float = 0.0
    """Observations whose depth confidence is not above this value are left out of the depth term (and
    cannot anchor a track) when a confidence map is given."""
    seed: int = 0
    """Seed of the track subset."""


@dataclass
class BAResult:
    """Bundle-adjusted cameras and depth scales, and what the optimisation did."""

    w2cs: torch.Tensor
    """[T, 4, 4] adjusted world-to-camera poses."""
    depth_scale: torch.Tensor
    """[T] factor to multiply each frame's depth prior by."""
    track_ids: torch.Tensor
    """[P] long, indices of the tracks used."""
    points: torch.Tensor
    """[P, 3] their adjusted world points."""
    reproj_px_before: float
    """Median reprojection error (pixels) of the observations at the start."""
    reproj_px_after: float
    """Median reprojection error at the end."""
    history: list[dict[str, float]] = field(default_factory=list)
    """Loss terms every ``log_every`` steps."""

    def stats(self) -> dict[str, float]:
        return {
            "tracks": int(self.track_ids.numel()),
            "reproj_px_before": self.reproj_px_before,
            "reproj_px_after": self.reproj_px_after,
            "depth_scale_min": float(self.depth_scale.min()) if self.depth_scale.numel() else 1.0,
            "depth_scale_max": float(self.depth_scale.max()) if self.depth_scale.numel() else 1.0,
        }


def select_tracks(
    visible: torch.Tensor,
    static: torch.Tensor,
    depth_ok: torch.Tensor,
    cfg: BundleAdjustConfig,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Usable static tracks and their reference frames: ``(ids [P] long, ref [P] long)``.

    A track is usable when it is static, visible in ``>= min_track_frames`` frames and has a valid depth in
    at least one visible frame (the first such frame is its reference). At most ``max_tracks`` are kept,
    a random subset drawn with ``seed``.
    """
    anchor = visible & depth_ok  # [T, N]
    usable = static & (visible.sum(0) >= cfg.min_track_frames) & anchor.any(0)
    ids = torch.nonzero(usable).flatten()
    if ids.numel() > cfg.max_tracks:
        g = torch.Generator().manual_seed(cfg.seed)
        ids = ids[torch.randperm(ids.numel(), generator=g)[: cfg.max_tracks].to(ids.device)].sort().values
    T = visible.shape[0]
    frames = torch.arange(T, device=visible.device)[:, None]
    ref = torch.where(anchor[:, ids], frames, torch.full_like(frames, T)).min(0).values
    return ids, ref


def _huber(e: torch.Tensor, delta: float) -> torch.Tensor:
    return torch.where(e < delta, 0.5 * e * e / delta, e - 0.5 * delta)


class _Problem:
    """The BA objective for fixed observations; parameters live in :attr:`params`."""

    def __init__(self, tracks, visible, depth, conf, Ks, w2cs, ids, ref, cfg: BundleAdjustConfig):
        dev, dt = w2cs.device, w2cs.dtype
        T = w2cs.shape[0]
        self.cfg, self.T = cfg, T
        self.Ks, self.w2c0 = Ks.to(dt), w2cs
        self.ids, self.ref = ids, ref
        P = ids.numel()
        uv = tracks[:, ids].to(dt)  # [T, P, 2]
        vis = visible[:, ids]
        z_all, ok = sample_depth(depth.to(dt), uv)
        if conf is not None:
            c_all, _ = sample_depth(conf.to(dt), uv)
            ok = ok & (c_all > cfg.min_depth_conf)
        col = torch.arange(P, device=dev)
        self.ref_uv = uv[ref, col]  # [P, 2]
        pix = torch.cat([self.ref_uv, torch.ones_like(self.ref_uv[:, :1])], 1)
        self.ref_ray = torch.linalg.solve(self.Ks[ref], pix[..., None])[..., 0]  # [P, 3], z = 1 (K is fixed)
        self.ref_z = z_all[ref, col]  # [P]
        t_idx, p_idx = torch.nonzero(vis, as_tuple=True)
        self.obs_t, self.obs_p, self.obs_uv = t_idx, p_idx, uv[t_idx, p_idx]
        self.obs_reproj = t_idx != ref[p_idx]
        self.obs_z = z_all[t_idx, p_idx]
        self.obs_zok = ok[t_idx, p_idx]
        self.params = {
            "trans": torch.zeros(T - 1, 3, dtype=dt, device=dev, requires_grad=True),
            "rot": torch.zeros(T - 1, 3, dtype=dt, device=dev, requires_grad=True),
            "log_scale": torch.zeros(T, dtype=dt, device=dev, requires_grad=True),
            "track_depth": torch.zeros(P, dtype=dt, device=dev, requires_grad=True),
        }

    def poses(self) -> torch.Tensor:
        p = self.params
        xi = torch.cat([p["trans"], p["rot"]], 1)
        xi = torch.cat([torch.zeros_like(xi[:1]), xi], 0)  # frame 0 fixed
        return apply_delta(xi, self.w2c0)

    def scales(self) -> torch.Tensor:
        ls = self.params["log_scale"]
        return torch.exp(ls - ls.mean())

    def points(self, w2cs: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
        ref = self.ref
        z = self.ref_z * scales[ref] * torch.exp(self.params["track_depth"])
        x_cam = self.ref_ray * z[:, None]
        R, t = w2cs[ref, :3, :3], w2cs[ref, :3, 3]
        return ((x_cam - t)[:, None, :] @ R)[:, 0]  # R^T (x - t)

    def residuals(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(reproj px [O], reproj mask [O], |log depth ratio| [O], depth mask [O])``."""
        w2cs, scales = self.poses(), self.scales()
        X = self.points(w2cs, scales)[self.obs_p]  # [O, 3]
        Rt = w2cs[self.obs_t]
        cam = (Rt[:, :3, :3] @ X[..., None])[..., 0] + Rt[:, :3, 3]
        z = cam[:, 2]
        front = z > 1e-6
        zs = torch.where(front, z, torch.ones_like(z))
        K = self.Ks[self.obs_t]
        u = K[:, 0, 0] * cam[:, 0] / zs + K[:, 0, 2]
        v = K[:, 1, 1] * cam[:, 1] / zs + K[:, 1, 2]
        d = torch.stack([u, v], 1) - self.obs_uv
        err = torch.sqrt((d * d).sum(1) + 1e-12)
        m_reproj = self.obs_reproj & front
        prior = self.obs_z * scales[self.obs_t]
        good = self.obs_zok & front & (prior > 0)
        ratio = torch.log(zs.clamp_min(1e-12)) - torch.log(torch.where(good, prior, torch.ones_like(prior)))
        return err, m_reproj, ratio.abs(), good

    def loss(self) -> tuple[torch.Tensor, dict[str, float]]:
        cfg = self.cfg
        err, m_r, ratio, m_d = self.residuals()
        e = err.clamp(max=cfg.clamp_px)
        l_r = (_huber(e, cfg.huber_px) * m_r).sum() / m_r.sum().clamp_min(1)
        l_d = (ratio.clamp(max=cfg.depth_clamp) * m_d).sum() / m_d.sum().clamp_min(1)
        loss = cfg.lambda_reproj * l_r + cfg.lambda_depth * l_d
        return loss, {"reproj": float(l_r.detach()), "depth": float(l_d.detach())}

    @torch.no_grad()
    def median_reproj(self) -> float:
        err, m_r, _, _ = self.residuals()
        return float(err[m_r].median()) if bool(m_r.any()) else 0.0


def bundle_adjust(
    tracks: torch.Tensor,
    visible: torch.Tensor,
    static: torch.Tensor,
    depth: torch.Tensor,
    Ks: torch.Tensor,
    w2cs: torch.Tensor,
    cfg: BundleAdjustConfig | None = None,
    depth_conf: torch.Tensor | None = None,
    log_every: int = 100,
    progress: Callable[[int, int, dict[str, float]], None] | None = None,
) -> BAResult:
    """Adjust cameras, depth scales and static track depths.

    Args:
        tracks: [T, N, 2] track pixels (u = x, v = y). visible: [T, N] bool. static: [N] bool (not dynamic).
        depth: [T, H, W] depth prior along camera z (scene units). Ks: [T, 3, 3]. w2cs: [T, 4, 4] starting
            OpenCV world-to-camera poses (frame 0 stays fixed).
        cfg: settings. depth_conf: optional [T, H, W] confidence (see ``min_depth_conf``).
        log_every: record the loss terms this often. progress: optional ``progress(step, steps, terms)``.

    Returns:
        :class:`BAResult`. With BA disabled, fewer than 2 frames or no usable track, the input poses and unit
        scales are returned unchanged.
    """
    cfg = cfg or BundleAdjustConfig()
    T = w2cs.shape[0]
    dev, dt = w2cs.device, w2cs.dtype
    tracks, visible, static = tracks.to(dev), visible.to(dev).bool(), static.to(dev).bool()
    depth = depth.to(dev, dt)
    conf = depth_conf.to(dev, dt) if depth_conf is not None else None
    _, depth_ok = sample_depth(depth, tracks.to(dt))
    if conf is not None:
        c_s, _ = sample_depth(conf, tracks.to(dt))
        depth_ok = depth_ok & (c_s > cfg.min_depth_conf)
    ids, ref = select_tracks(visible, static, depth_ok, cfg)
    ones = torch.ones(T, dtype=dt, device=dev)
    if not cfg.enabled or T < 2 or ids.numel() == 0:
        return BAResult(w2cs.clone(), ones, ids, torch.zeros(0, 3, dtype=dt, device=dev), 0.0, 0.0)

    prob = _Problem(tracks, visible, depth, conf, Ks.to(dev), w2cs, ids, ref, cfg)
    scene_scale = float(prob.ref_z.median().clamp_min(1e-6))
    lrs = {
        "trans": cfg.lr_trans * scene_scale,
        "rot": cfg.lr_rot,
        "log_scale": cfg.lr_depth_scale,
        "track_depth": cfg.lr_track_depth,
    }
    opt = torch.optim.Adam([{"params": [p], "name": k, "lr": lrs[k]} for k, p in prob.params.items()])
    scheds = {k: ExponentialLR(v, v * cfg.lr_final_ratio, max(cfg.steps, 1)) for k, v in lrs.items()}
    before = prob.median_reproj()
    history: list[dict[str, float]] = []
    best = {k: v.detach().clone() for k, v in prob.params.items()}
    for step in range(cfg.steps):
        stop_request.check()  # a stop whose exception was lost elsewhere (worldtree.infra.stop_request)
        thread_governor.tick()  # the torch team follows the free cores
        for g in opt.param_groups:
            g["lr"] = scheds[g["name"]](step)
        loss, terms = prob.loss()
        if not torch.isfinite(loss):
            # Keep the last finite parameters; BA is an initialisation, a partial result is still useful.
            with torch.no_grad():
                for k, v in prob.params.items():
                    v.copy_(best[k])
            break
        best = {k: v.detach().clone() for k, v in prob.params.items()}
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % log_every == 0 or step == cfg.steps - 1:
            history.append({"step": step, "loss": float(loss.detach()), **terms})
        if progress is not None:
            progress(step + 1, cfg.steps, terms)
    with torch.no_grad():
        w_out, s_out = prob.poses(), prob.scales()
        pts = prob.points(w_out, s_out)
    return BAResult(w_out.detach(), s_out.detach(), ids, pts.detach(), before, prob.median_reproj(), history)
