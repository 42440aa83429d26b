"""Depth of moving points from the smoothness of their 3D trajectories (trajectory triangulation).

The classical depth prior is a static-world estimate: on a moving object plane-sweep stereo matches frames
taken at other times, and the prior's dynamic pixels are filled from the static surroundings. A dynamic track
seen at pixel ``p_t`` of frame ``t`` lies on that frame's ray, ``X_t = c_t + z_t r_t`` (``r_t`` the ray with unit
camera depth), so its depths ``z_t`` are the only unknowns of its trajectory. When consecutive frames come
from different cameras (a rig visited in ping-pong order, or a moving camera), wrong depths make the
trajectory zig-zag between the rays; the depths that make it smooth are a measurement of the moving point's
depth. Per track, over its visible frames ``t_1 < ... < t_k``, the linear least squares

    sum_m || X''(t_m) ||^2 / L^2  +  w sum_m ((z_m - zhat_m) / zhat_m)^2

where ``X''`` is the second divided difference of three consecutive visible frames (gaps allowed), ``L`` the
scene's length scale and ``zhat`` the depth prior, weakly weighted by ``w``: it settles what the cameras'
motion leaves undetermined (a camera moving in step with the point gives a family of equally smooth
trajectories). A point moving at constant velocity (or at rest) is recovered exactly as ``w`` goes to 0.
"""

from __future__ import annotations

import torch

from worldtree.motion.lift import sample_depth

__all__ = ["ratio_map", "smooth_trajectory_depths"]


def _rays(tracks: torch.Tensor, Ks: torch.Tensor, w2cs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays with unit camera depth ``[T, N, 3]`` through ``tracks`` [T, N, 2] and centres ``[T, 3]``."""
    dt = torch.float64
    ones = torch.ones_like(tracks[..., :1])
    pix = torch.cat([tracks, ones], -1).to(dt)
    cam = torch.linalg.solve(Ks.to(dt), pix.transpose(1, 2)).transpose(1, 2)  # [T, N, 3], z = 1
    R = w2cs[:, :3, :3].to(dt)
    t = w2cs[:, :3, 3].to(dt)
    centres = -(R.transpose(1, 2) @ t[..., None])[..., 0]
    return cam @ R, centres  # row-vector form of R^T cam


def smooth_trajectory_depths(
    tracks: torch.Tensor,
    visible: torch.Tensor,
    depths: torch.Tensor,
    Ks: torch.Tensor,
    w2cs: torch.Tensor,
    length: float,
    prior_weight: float,
    min_frames: int = 4,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Depths of each track's visible frames that make its world trajectory smooth (see the module doc).

    Args:
        tracks: ``[T, N, 2]`` pixels (u, v). visible: ``[T, N]`` bool.
        depths: ``[T, H, W]`` depth prior along camera z (scene units), sampled bilinearly at the tracks.
        Ks: ``[T, 3, 3]``. w2cs: ``[T, 4, 4]`` OpenCV world-to-camera poses.
        length: the scene's length scale (e.g. the median depth), in scene units.
        prior_weight: ``w`` above (dimensionless; > 0).
        min_frames: tracks visible in fewer frames (with a prior depth in at least one) keep the prior.

    Returns:
        ``(z [T, N], solved [N] bool)``: the depths along camera z at the visible frames with a valid prior
        sample (the prior's value where a track was not solved, 0 where there is none), and which tracks
        were solved.
    """
    if prior_weight <= 0:
        raise ValueError(f"smooth_trajectory_depths: prior_weight must be > 0, got {prior_weight}")
    T, N = visible.shape
    zhat, ok = sample_depth(depths.to(torch.float64), tracks.to(torch.float64))
    vis = visible.bool() & ok
    z = torch.where(vis, zhat, torch.zeros_like(zhat))
    solved = torch.zeros(N, dtype=torch.bool, device=visible.device)
    if N == 0 or T < 3:
        return z.to(depths.dtype), solved
    rays, centres = _rays(tracks, Ks, w2cs)
    sw = float(prior_weight) ** 0.5
    inv_len = 1.0 / max(float(length), 1e-12)
    for n in torch.nonzero(vis.sum(0) >= max(min_frames, 3)).flatten().tolist():
        ts = torch.nonzero(vis[:, n]).flatten()
        k = int(ts.numel())
        tf = ts.to(torch.float64)
        a, b, c = tf[:-2], tf[1:-1], tf[2:]
        # Second divided difference of X at (a, b, c): 2 [X_a / ((b-a)(c-a)) - X_b / ((b-a)(c-b)) + X_c / ((c-b)(c-a))]
        coef = torch.stack([2 / ((b - a) * (c - a)), -2 / ((b - a) * (c - b)), 2 / ((c - b) * (c - a))], 1)
        r, cen = rays[ts, n], centres[ts]  # [k, 3]
        rows = k - 2
        A = torch.zeros(rows, 3, k, dtype=torch.float64, device=tracks.device)
        rhs = torch.zeros(rows, 3, dtype=torch.float64, device=tracks.device)
        m = torch.arange(rows, device=tracks.device)
        for j in range(3):
            A[m, :, m + j] = coef[:, j : j + 1] * r[m + j]
            rhs -= coef[:, j : j + 1] * cen[m + j]
        A = A.reshape(3 * rows, k) * inv_len
        rhs = rhs.reshape(3 * rows) * inv_len
        zh = zhat[ts, n]
        P = torch.diag(sw / zh)
        full_A = torch.cat([A, P], 0)
        full_b = torch.cat([rhs, torch.full((k,), sw, dtype=torch.float64, device=tracks.device)])
        sol = torch.linalg.lstsq(full_A, full_b[:, None]).solution[:, 0]
        if bool(torch.isfinite(sol).all()) and bool((sol > 0).all()):
            z[ts, n] = sol
            solved[n] = True
    return z.to(depths.dtype), solved


def ratio_map(
    mask: torch.Tensor, tracks: torch.Tensor, ratio: torch.Tensor, has: torch.Tensor, k: int = 4
) -> torch.Tensor:
    """``[T, H, W]`` factor for the depth of the mask's pixels: the inverse-distance weighted mean of the
    ``k`` nearest tracks' ``ratio`` ([T, N], where ``has`` [T, N]); 1 off the mask and in frames without any.
    """
    T, H, W = mask.shape
    out = torch.ones(T, H, W, dtype=ratio.dtype, device=ratio.device)
    for t in range(T):
        sel = has[t]
        if not bool(sel.any()) or not bool(mask[t].any()):
            continue
        ys, xs = torch.nonzero(mask[t], as_tuple=True)
        px = torch.stack([xs, ys], -1).to(tracks.dtype)
        d = torch.cdist(px, tracks[t, sel].to(px.dtype))  # [P, n_t]
        kk = min(k, d.shape[1])
        dist, idx = d.topk(kk, dim=1, largest=False)
        w = 1.0 / (dist + 1.0)
        val = (w * ratio[t, sel][idx].to(w.dtype)).sum(1) / w.sum(1)
        out[t, ys, xs] = val.to(out.dtype)
    return out
