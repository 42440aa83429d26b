"""Depth a static world cannot hold: pixels whose depth puts a point in front of what other frames see there.

A depth prior that measures moving objects (an imported network depth, a generator's exact depth) gives a
moving object's pixels its own depth in every frame. Where the dynamic masks miss part of the object, those
pixels are drawn by static Gaussians, and a depth loss on them pulls static Gaussians out to the object's
place at that time; seen from every other frame they are floaters in front of the scene (a veil over the
whole image on the twin of Balloon1, docs/base_method.md, "Depth that a static world cannot hold").

The test is the free-space constraint of depth fusion: a static point ``X`` lifted from frame ``t`` and seen
by frame ``s`` at pixel ``q`` with camera depth ``z_s`` cannot lie in front of the surface that frame ``s``
sees at ``q``, ``z_s < (1 - tolerance) D_s(q)``, since it would have hidden that surface. A point behind it is
merely occluded there and passes. ``D_s`` is the minimum over a small window (depth edges, a pixel of pose
error), so a violation is counted only where every nearby surface of ``s`` lies behind ``X``. A pixel is
flagged when it violates in at least ``share`` of the frames that see it (a depth error of one frame's
scale fails a few of them, a moving object most: elsewhere at other times). A static-world depth (the
classical plane sweep and its fill) passes by construction.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from worldtree.motion.lift import camera_rays, project_points

__all__ = ["comparison_frames", "free_space_violations", "points_in_free_space", "window_minimum"]


def comparison_frames(t: int | None, num_frames: int, views: int) -> list[int]:
    """Up to ``views`` frames other than ``t`` (None: any frame), spread evenly over the video (ascending,
    distinct)."""
    others = [s for s in range(num_frames) if s != t]
    if views <= 0 or not others:
        return []
    if views >= len(others):
        return others
    idx = torch.linspace(0, len(others) - 1, views).round().long().unique()
    return [others[int(i)] for i in idx]


def window_minimum(depth: torch.Tensor, window: int) -> torch.Tensor:
    """``[T, H, W]`` minimum of ``depth`` over a ``window`` x ``window`` neighbourhood (clipped at the image's
    edge); a pixel without depth (``<= 0`` or non-finite) counts 0 there, which nothing can be in front of."""
    d = torch.where(
        torch.isfinite(depth) & (depth > 0), depth.float(), torch.zeros_like(depth, dtype=torch.float32)
    )
    return -F.max_pool2d(-d[:, None], window, stride=1, padding=window // 2)[:, 0]


def points_in_free_space(
    points: torch.Tensor,
    reference: torch.Tensor,
    Ks: torch.Tensor,
    w2cs: torch.Tensor,
    frames: list[int],
    tolerance: float,
    share: float,
    min_seen: int = 2,
) -> torch.Tensor:
    """Which world ``points`` ``[N, 3]`` lie in front of what ``frames`` see (see the module doc).

    Args:
        reference: ``[T, H, W]`` the frames' depth after :func:`window_minimum` (0 = none).
        Ks: ``[T, 3, 3]``. w2cs: ``[T, 4, 4]``. frames: the frames to look from.
        tolerance, share, min_seen: as in :func:`free_space_violations`.

    Returns:
        ``[N]`` bool: seen (in front of the camera, inside the image, with depth there) by at least ``min_seen``
        of ``frames`` and nearer than ``1 - tolerance`` times their depth in at least ``share`` of those.
    """
    T, H, W = reference.shape
    seen = torch.zeros(points.shape[0], dtype=torch.int32, device=points.device)
    hits = torch.zeros_like(seen)
    pts = points.float()
    for s in frames:
        q, z = project_points(pts, Ks[s].float(), w2cs[s].float())  # behind the camera: excluded by ``z``
        u, v = q[:, 0].round(), q[:, 1].round()
        inside = (z > 1e-6) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        r = reference[s][v.clamp(0, H - 1).long(), u.clamp(0, W - 1).long()]
        looked = inside & (r > 0)
        seen += looked.int()
        hits += (looked & (z < (1.0 - tolerance) * r)).int()
    return (seen >= max(min_seen, 1)) & (hits.float() >= share * seen.float())


def free_space_violations(
    depth: torch.Tensor,
    Ks: torch.Tensor,
    w2cs: torch.Tensor,
    tolerance: float = 0.25,
    views: int = 8,
    share: float = 0.5,
    window: int = 3,
    min_seen: int = 2,
) -> torch.Tensor:
    """Pixels whose depth a static world cannot hold (see the module doc).

    Args:
        depth: ``[T, H, W]`` depth along each camera's z (any consistent unit); ``<= 0`` or non-finite = none.
        Ks: ``[T, 3, 3]`` intrinsics (pixels, at the size of ``depth``). w2cs: ``[T, 4, 4]`` OpenCV poses.
        tolerance: relative margin in ``(0, 1)``: a violation needs ``z_s < (1 - tolerance) D_s``.
        views: frames each frame is compared with (:func:`comparison_frames`).
        share: fraction in ``(0, 1]`` of the frames that see a pixel that must find it in free space.
        window: odd side (pixels) of the minimum filter over ``D_s``.
        min_seen: a pixel seen (inside the image, in front, with depth there) by fewer frames is kept.

    Returns:
        ``[T, H, W]`` bool on ``depth``'s device: True where the pixel's depth floats in front of the scene.
    """
    if depth.dim() != 3 or Ks.shape[0] != depth.shape[0] or w2cs.shape[0] != depth.shape[0]:
        raise ValueError(
            f"free_space_violations: expected depth [T,H,W], Ks [T,3,3], w2cs [T,4,4]; got "
            f"{tuple(depth.shape)}, {tuple(Ks.shape)}, {tuple(w2cs.shape)}"
        )
    if not 0.0 < tolerance < 1.0 or not 0.0 < share <= 1.0 or window < 1 or window % 2 == 0:
        raise ValueError(
            f"free_space_violations: need 0 < tolerance < 1, 0 < share <= 1 and an odd window >= 1; got "
            f"{tolerance}, {share}, {window}"
        )
    T, H, W = depth.shape
    dev = depth.device
    ref = window_minimum(depth, window)
    out = torch.zeros(T, H, W, dtype=torch.bool, device=dev)
    vs, us = torch.meshgrid(torch.arange(H, device=dev), torch.arange(W, device=dev), indexing="ij")
    uv = torch.stack([us, vs], -1).reshape(1, -1, 2).float()
    for t in range(T):
        dt = depth[t].float().flatten()
        valid = torch.isfinite(dt) & (dt > 0)
        if not bool(valid.any()):
            continue
        cam = camera_rays(uv[:, valid], Ks[t : t + 1].float(), torch.float32)[0] * dt[valid, None]
        R, tr = w2cs[t, :3, :3].float(), w2cs[t, :3, 3].float()
        world = (cam - tr) @ R  # R^T (x - t) in row form
        flag = points_in_free_space(
            world, ref, Ks, w2cs, comparison_frames(t, T, views), tolerance, share, min_seen
        )
        frame = torch.zeros(H * W, dtype=torch.bool, device=dev)
        frame[valid] = flag
        out[t] = frame.reshape(H, W)
    return out
