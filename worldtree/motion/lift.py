"""Lift 2D point tracks to 3D world trajectories with depth maps and cameras (and project world points back to
pixels), and fill their gaps in time.

Pixel convention (OpenCV, as the rasterizer): pixel (row i, column j) has its centre at ``(u, v) = (j, i)``;
a frame's pixel area is ``-0.5 <= u < W - 0.5``, ``-0.5 <= v < H - 0.5``. Cameras are OpenCV world-to-camera
``[R | t]`` with intrinsics ``K``; depth is along the camera z axis in scene units.
"""

from __future__ import annotations

import torch

__all__ = ["camera_rays", "fill_gaps", "lift_tracks", "project_points", "sample_depth"]


def sample_depth(
    depths: torch.Tensor, uv: torch.Tensor, mode: str = "bilinear"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth at sub-pixel positions, per frame.

    Args:
        depths: [T, H, W] depth maps (scene units); values <= 0 or non-finite mark missing depth.
        uv: [T, N, 2] pixel positions (u = column, v = row), any values.
        mode: ``"bilinear"`` (the 4 surrounding pixel centres; in the half-pixel border the edge pixels are
            repeated) or ``"nearest"`` (the pixel containing the point; use it where depth edges must not
            be blurred).

    Returns:
        ``(z [T, N], ok [T, N] bool)``: ``ok`` is False outside the image, where ``uv`` is not finite, or where
        any pixel with a non-zero bilinear weight has missing depth; ``z`` is 0 there.
    """
    if depths.dim() != 3 or uv.dim() != 3 or uv.shape[-1] != 2 or uv.shape[0] != depths.shape[0]:
        raise ValueError(
            f"sample_depth: expected depths [T,H,W] and uv [T,N,2], got {tuple(depths.shape)}, {tuple(uv.shape)}"
        )
    if mode not in ("bilinear", "nearest"):
        raise ValueError(f"sample_depth: mode must be 'bilinear' or 'nearest', got {mode!r}")
    T, H, W = depths.shape
    u, v = uv[..., 0], uv[..., 1]
    finite = torch.isfinite(u) & torch.isfinite(v)
    u = torch.where(finite, u, torch.zeros_like(u))
    v = torch.where(finite, v, torch.zeros_like(v))
    inside = finite & (u >= -0.5) & (u < W - 0.5) & (v >= -0.5) & (v < H - 0.5)
    flat = depths.reshape(T, H * W)
    good_map = torch.isfinite(flat) & (flat > 0)
    flat_safe = torch.where(good_map, flat, torch.zeros_like(flat))

    def gather(rows: torch.Tensor, cols: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        lin = (rows * W + cols).long()
        return torch.gather(flat_safe, 1, lin), torch.gather(good_map, 1, lin)

    if mode == "nearest":
        # floor(x + 0.5) puts x = j - 0.5 in pixel j, matching the half-open pixel area above.
        c = torch.floor(u + 0.5).clamp(0, W - 1)
        r = torch.floor(v + 0.5).clamp(0, H - 1)
        z, ok = gather(r, c)
        ok = ok & inside
        return torch.where(ok, z, torch.zeros_like(z)), ok

    uc = u.clamp(0, W - 1)
    vc = v.clamp(0, H - 1)
    c0 = torch.floor(uc).clamp(max=max(W - 2, 0))
    r0 = torch.floor(vc).clamp(max=max(H - 2, 0))
    c1 = (c0 + 1).clamp(max=W - 1)
    r1 = (r0 + 1).clamp(max=H - 1)
    fu, fv = uc - c0, vc - r0  # in [0, 1]; exactly 1 on the last row/column
    z = torch.zeros_like(u)
    ok = inside.clone()
    for rr, cc, wgt in (
        (r0, c0, (1 - fu) * (1 - fv)),
        (r0, c1, fu * (1 - fv)),
        (r1, c0, (1 - fu) * fv),
        (r1, c1, fu * fv),
    ):
        zz, gg = gather(rr, cc)
        z = z + wgt * zz
        ok = ok & (gg | (wgt == 0))
    return torch.where(ok, z, torch.zeros_like(z)), ok


def camera_rays(uv: torch.Tensor, Ks: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Camera-frame rays with unit depth ``K^-1 (u, v, 1)`` [T, N, 3] through pixels ``uv`` [T, N, 2] of the
    cameras ``Ks`` [T, 3, 3], in ``dtype``."""
    pix = torch.cat((uv, torch.ones_like(uv[..., :1])), dim=-1).to(dtype)  # [T, N, 3]
    # solve instead of inv: K is upper triangular and well conditioned, either is fine, solve is cleaner.
    return torch.linalg.solve(Ks.to(dtype), pix.transpose(1, 2)).transpose(1, 2)


def project_points(points: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(uv [N, 2], z [N])``: pixels (centres at integers) and camera depth of world ``points`` [N, 3] seen by
    the pinhole camera ``K`` [3, 3] / ``w2c`` [4, 4]. The division uses the depth clamped at 1e-6, so a point
    at or behind the camera gets finite (meaningless) pixels: test ``z`` before using them. Differentiable."""
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    zc = z.clamp_min(1e-6)
    return torch.stack([K[0, 0] * cam[:, 0] / zc + K[0, 2], K[1, 1] * cam[:, 1] / zc + K[1, 2]], 1), z


def lift_tracks(
    tracks: torch.Tensor,
    visible: torch.Tensor,
    depths: torch.Tensor,
    Ks: torch.Tensor,
    w2cs: torch.Tensor,
    mode: str = "bilinear",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Back-project 2D tracks to world points with their frame's depth and camera.

    Args:
        tracks: [T, N, 2] pixel positions (u, v).
        visible: [T, N] bool track visibility.
        depths: [T, H, W] depth maps along the camera z axis (scene units).
        Ks: [T, 3, 3] intrinsics (pixels). w2cs: [T, 4, 4] OpenCV world-to-camera poses.
        mode: depth sampling, see :func:`sample_depth`.

    Returns:
        ``(points [T, N, 3] world, valid [T, N] bool)``. A point is valid where the track is visible, inside
        the image, and its sampled depth is finite and > 0; invalid points are 0.
        ``x_cam = z K^-1 (u, v, 1)``, ``x_world = R^T (x_cam - t)``.
    """
    T, N = visible.shape
    if tracks.shape != (T, N, 2) or Ks.shape != (T, 3, 3) or w2cs.shape != (T, 4, 4) or depths.shape[0] != T:
        raise ValueError(
            "lift_tracks: expected tracks [T,N,2], visible [T,N], depths [T,H,W], Ks [T,3,3], w2cs [T,4,4]; got "
            f"{tuple(tracks.shape)}, {tuple(visible.shape)}, {tuple(depths.shape)}, {tuple(Ks.shape)}, {tuple(w2cs.shape)}"
        )
    z, ok = sample_depth(depths, tracks, mode)
    valid = ok & visible.bool()
    uv = torch.where(valid[..., None], tracks, torch.zeros_like(tracks))
    dtype = torch.promote_types(tracks.dtype, Ks.dtype)
    rays = camera_rays(uv, Ks, dtype)
    x_cam = rays * z.to(dtype)[..., None]
    R = w2cs[:, :3, :3].to(dtype)
    t = w2cs[:, :3, 3].to(dtype)
    x_world = (x_cam - t[:, None, :]) @ R  # row-vector form of R^T (x - t)
    x_world = torch.where(valid[..., None], x_world, torch.zeros_like(x_world))
    return x_world, valid


def fill_gaps(points: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Complete trajectories over time: linear interpolation inside gaps, held constant at the ends.

    For each track, a frame without a valid point between two valid frames ``a < t < b`` gets
    ``x(a) + (t - a) / (b - a) (x(b) - x(a))``; frames before the first valid frame take the first valid
    point, frames after the last take the last (hold). Tracks with no valid frame stay 0.

    Args:
        points: [T, N, C] values (e.g. world points), anything where ``valid`` is False.
        valid: [T, N] bool.

    Returns:
        ``(filled [T, N, C], observed [T, N] bool)``; ``observed`` is a copy of ``valid`` (the frames that were
        measured, as opposed to filled). Differentiable with respect to the valid points.
    """
    T, N = valid.shape
    if points.shape[:2] != (T, N):
        raise ValueError(f"fill_gaps: points {tuple(points.shape)} and valid {tuple(valid.shape)} disagree")
    valid = valid.bool()
    if T == 0 or N == 0:
        return points.clone(), valid.clone()
    frames = torch.arange(T, device=valid.device)[:, None].expand(T, N)
    # Index of the last valid frame at or before t (-1 if none) and the first at or after t (T if none).
    prev = torch.where(valid, frames, torch.full_like(frames, -1)).cummax(dim=0).values
    nxt = torch.where(valid, frames, torch.full_like(frames, T)).flip(0).cummin(dim=0).values.flip(0)
    has_prev, has_next = prev >= 0, nxt < T
    a = torch.where(has_prev, prev, nxt).clamp(0, T - 1)  # hold: fall back on the other side
    b = torch.where(has_next, nxt, prev).clamp(0, T - 1)
    span = (b - a).to(points.dtype)
    frac = torch.where(span > 0, (frames - a).to(points.dtype) / span.clamp(min=1), torch.zeros_like(span))
    col = torch.arange(N, device=valid.device)[None, :].expand(T, N)
    xa, xb = points[a, col], points[b, col]
    filled = xa + frac[..., None] * (xb - xa)
    any_valid = valid.any(dim=0)[None, :, None]
    filled = torch.where(any_valid, filled, torch.zeros_like(filled))
    filled = torch.where(valid[..., None], points, filled)  # measured frames exactly as given
    return filled, valid.clone()
