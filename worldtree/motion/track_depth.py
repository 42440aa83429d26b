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

:func:`trajectory_scale` is the same least squares with one unknown: depths known up to a common factor (an
object's apparent size, by size constancy) and the factor that makes the path smoothest.
"""

from __future__ import annotations

import torch

from worldtree.motion.lift import camera_rays, sample_depth

__all__ = ["ratio_map", "smooth_trajectory_depths", "trajectory_scale"]


def _rays(tracks: torch.Tensor, Ks: torch.Tensor, w2cs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays with unit camera depth ``[T, N, 3]`` through ``tracks`` [T, N, 2] and centres ``[T, 3]``."""
    dt = torch.float64
    cam = camera_rays(tracks, Ks, dt)  # [T, N, 3], z = 1
    R = w2cs[:, :3, :3].to(dt)
    t = w2cs[:, :3, 3].to(dt)
    centres = -(R.transpose(1, 2) @ t[..., None])[..., 0]
    return cam @ R, centres  # row-vector form of R^T cam


def _second_difference_weights(ba: torch.Tensor, cb: torch.Tensor, ca: torch.Tensor) -> torch.Tensor:
    """Weights ``[..., 3]`` of ``X_a, X_b, X_c`` in the second divided difference at times ``a < b < c``, from
    the gaps ``b - a``, ``c - b``, ``c - a``: ``2 [X_a / ((b-a)(c-a)) - X_b / ((b-a)(c-b)) + X_c / ((c-b)(c-a))]``."""
    return torch.stack([2 / (ba * ca), -2 / (ba * cb), 2 / (cb * ca)], -1)


_CHUNK = 256
"""Tracks solved together (one batched least squares; bounds the memory at ~10 MB)."""


def _solve_chunk(cols, vis, zhat, rays, centres, sw: float, inv_len: float):
    """The least squares of tracks ``cols`` [B] in one batch. Each track's visible frames come first, in
    time order, padded to the longest (padded unknowns get a unit row and no other). Returns ``(good [B],
    frames [K, B], inside [K, B], depths [B, K])``."""
    T = vis.shape[0]
    dev, dt = vis.device, torch.float64
    v = vis[:, cols]  # [T, B]
    k = v.sum(0)
    K = int(k.max())
    frames = torch.arange(T, device=dev)[:, None]
    ts = torch.where(v, frames, frames + T).sort(0).values[:K]  # visible frames first, ascending
    inside = torch.arange(K, device=dev)[:, None] < k[None]
    ts = torch.where(inside, ts, torch.zeros_like(ts))
    B = cols.numel()
    tf = ts.to(dt)
    a, b, c = tf[:-2], tf[1:-1], tf[2:]  # [K-2, B]
    tri = (torch.arange(K - 2, device=dev)[:, None] + 2) < k[None]
    one = torch.ones_like(a)
    ba, cb, ca = (torch.where(tri, x, one) for x in (b - a, c - b, c - a))
    coef = _second_difference_weights(ba, cb, ca) * tri[..., None]  # [K-2, B, 3]
    r = rays[ts, cols[None].expand(K, B)]  # [K, B, 3]
    cen = centres[ts]  # [K, B, 3]
    A = torch.zeros(B, K - 2, 3, K, dtype=dt, device=dev)
    rhs = torch.zeros(K - 2, B, 3, dtype=dt, device=dev)
    m = torch.arange(K - 2, device=dev)
    for j in range(3):
        A[:, m, :, m + j] = coef[..., j : j + 1] * r[m + j]
        rhs -= coef[..., j : j + 1] * cen[m + j]
    zh = zhat[ts, cols[None].expand(K, B)]  # [K, B]
    P = torch.diag_embed(torch.where(inside, sw / zh.clamp_min(1e-12), torch.ones_like(zh)).T)  # [B, K, K]
    full_A = torch.cat([A.reshape(B, 3 * (K - 2), K) * inv_len, P], 1)
    full_b = torch.cat(
        [rhs.permute(1, 0, 2).reshape(B, 3 * (K - 2)) * inv_len, torch.where(inside, sw, 0.0).T.to(dt)], 1
    )
    sol = torch.linalg.lstsq(full_A, full_b[..., None]).solution[..., 0]  # [B, K]
    ok = torch.isfinite(sol) & (sol > 0)
    good = (ok | ~inside.T).all(1)
    return good, ts, inside, sol


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
    todo = torch.nonzero(vis.sum(0) >= max(min_frames, 3)).flatten()
    for chunk in todo.split(_CHUNK) if todo.numel() else ():
        good, ts, inside, sol = _solve_chunk(chunk, vis, zhat, rays, centres, sw, inv_len)
        sel = inside & good[None]
        col = chunk[None].expand_as(ts)
        z[ts[sel], col[sel]] = sol.T[sel]
        solved[chunk[good]] = True
    return z.to(depths.dtype), solved


def trajectory_scale(
    frames: torch.Tensor,
    pixels: torch.Tensor,
    rel_depth: torch.Tensor,
    Ks: torch.Tensor,
    w2cs: torch.Tensor,
) -> tuple[float, float]:
    """The one factor ``s`` that makes ``X_m = c_m + s q_m r_m`` smoothest, for a point whose depths are known
    up to scale (``q_m``: e.g. an object's inverse apparent size, which size constancy makes proportional to
    its depth).

    With one unknown the least squares ``min_s sum ||A_m + s B_m||^2`` (``A`` the cameras' second divided
    differences, ``B`` those of ``q r``) is closed form. It measures the scale only where the cameras
    accelerate: a camera moving at constant velocity leaves every ``s`` equally smooth up to the point's own
    acceleration, which ``s -> 0`` removes (the point glued to the camera). ``fit`` says how much of the
    cameras' acceleration the scaled rays cancel, ``(A.B)^2 / (|A|^2 |B|^2)``: 1 when an exactly smooth
    trajectory exists, near 0 when the answer is noise.

    Args:
        frames: ``[K]`` frame indices, strictly increasing (gaps allowed).
        pixels: ``[K, 2]`` the point's pixel (u, v) in each of those frames.
        rel_depth: ``[K]`` its depth along camera z up to one unknown factor (> 0).
        Ks: ``[T, 3, 3]`` intrinsics (pixels). w2cs: ``[T, 4, 4]`` OpenCV world-to-camera poses.

    Returns:
        ``(s, fit)``: the depths are ``s * rel_depth``; ``s`` is NaN (and ``fit`` 0) with fewer than 3 frames,
        no acceleration at all, or a non-positive optimum.
    """
    dt = torch.float64
    K = int(frames.numel())
    if K < 3 or bool((rel_depth <= 0).any()) or not bool(torch.isfinite(rel_depth).all()):
        return float("nan"), 0.0
    f = frames.long()
    r, centres = _rays(pixels.to(dt)[:, None], Ks[f], w2cs[f])  # [K, 1, 3], [K, 3]
    q = rel_depth.to(dt)[:, None] * r[:, 0]  # [K, 3]
    t = f.to(dt)
    a, b, c = t[:-2], t[1:-1], t[2:]
    coef = _second_difference_weights(b - a, c - b, c - a)  # [K-2, 3]

    def second(x: torch.Tensor) -> torch.Tensor:
        return coef[:, :1] * x[:-2] + coef[:, 1:2] * x[1:-1] + coef[:, 2:] * x[2:]

    A, B = second(centres), second(q)
    ab, aa, bb = float((A * B).sum()), float((A * A).sum()), float((B * B).sum())
    if aa <= 0.0 or bb <= 0.0:
        return float("nan"), 0.0
    s = -ab / bb
    if not s > 0.0:
        return float("nan"), 0.0
    return s, ab * ab / (aa * bb)


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
