"""Link track pieces that are one point: motion continued across a short gap, with the camera motion removed.

Chained dynamic tracks (:mod:`worldtree.priors.dynamic_tracks`) end wherever the flow fails, and the point is
picked up again a few frames later by a re-detected piece. Piece A (last visible at frame e) and piece B
(first visible at s, e < s <= e + ``MotionConfig.track_link_gap``) are joined when all of these hold:

1. **position**: B's start lies where A's motion predicts,
   ``|x_B(s) - q| <= track_link_px + track_link_rel |v_A| (s - e)``, with
   ``q = x_A(e) + v_A (s - e) + c_{e->s}``: ``v_A`` is A's own motion per frame over its last step with the
   camera's share removed, and ``c_{e->s}`` the camera's share of the way from e to s. The camera's share is
   where a static surface at the point's depth would go (:func:`worldtree.priors.flow.rigid_transfer`, the
   depth-guided initialisation of flow and Lucas-Kanade); without depth and poses it is taken as zero (plain
   constant velocity in the image). On the NVIDIA rig every step changes camera, so a gap of a few frames
   holds several camera jumps that the image velocity alone does not continue.
2. **velocity**: when B has a second visible frame, its own motion ``v_B`` (camera removed the same way)
   agrees with ``v_A`` within ``track_link_px + track_link_rel max(|v_A|, |v_B|)`` per frame; two objects
   crossing pass through the same place with different motions.
3. **appearance**: the zero-mean normalised cross-correlation of the grey patches (side
   ``2 track_link_patch_px + 1``) around ``x_A(e)`` in frame e and ``x_B(s)`` in frame s is at least
   ``track_link_ncc``; a flat patch (standard deviation under 1/255) never agrees. Off without images.

Candidates are joined greedily, best first (position error in units of its tolerance plus ``1 - NCC``); every
end and every start is used once, so a chain A -> B -> C forms one track.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from worldtree.priors.config import MotionConfig
from worldtree.priors.flow import rigid_transfer, to_gray_u8

__all__ = ["LinkStats", "link_pieces", "patch_ncc"]

_FLAT = 1.0 / 255.0
"""Patches whose grey standard deviation is below this carry no appearance to compare (default)."""


@dataclass
class LinkStats:
    """Counts of one linking pass (recorded in ``priors.json`` and the Base run's ``motion_refine``)."""

    pieces: int = 0
    """Tracks given to the linker."""
    candidates: int = 0
    """(end, start) pairs within the gap whose start lies near the predicted position."""
    rejected_velocity: int = 0
    """... of which the two motions disagree."""
    rejected_appearance: int = 0
    """... of which the patches do not correlate (and the motions agree)."""
    links: int = 0
    """Joins made (a track made of k pieces counts k - 1)."""
    parts: np.ndarray | None = None
    """``[N]`` pieces joined into each column (1 = not linked, 0 = emptied into another column)."""

    def as_dict(self) -> dict[str, int]:
        """The counts (``parts`` left out)."""
        return {k: v for k, v in self.__dict__.items() if k != "parts"}


def patch_ncc(
    gray_a: np.ndarray,
    pa: np.ndarray,
    gray_b: np.ndarray,
    pb: np.ndarray,
    half: int,
    min_std: float = _FLAT,
) -> np.ndarray:
    """Zero-mean NCC ``[N]`` in [-1, 1] of the patches around ``pa`` [N, 2] in ``gray_a`` [H, W] and ``pb``
    [N, 2] in ``gray_b`` (x, y pixels, sub-pixel; float images in [0, 1]). Side ``2 half + 1``; NaN where either
    patch's standard deviation is below ``min_std`` (too flat to compare: its NCC would be noise)."""
    side = 2 * half + 1
    out = np.full(len(pa), np.nan)
    for n in range(len(pa)):
        a = cv2.getRectSubPix(gray_a, (side, side), (float(pa[n, 0]), float(pa[n, 1]))).astype(np.float64)
        b = cv2.getRectSubPix(gray_b, (side, side), (float(pb[n, 0]), float(pb[n, 1]))).astype(np.float64)
        a, b = a - a.mean(), b - b.mean()
        sa, sb = np.sqrt((a * a).mean()), np.sqrt((b * b).mean())
        if sa < min_std or sb < min_std:
            continue
        out[n] = float((a * b).mean() / (sa * sb))
    return out


class _Camera:
    """The camera's share of a point's image motion between two frames (zeros without depth and poses)."""

    def __init__(self, depth: np.ndarray | None, Ks: np.ndarray | None, w2cs: np.ndarray | None):
        self.on = depth is not None and Ks is not None and w2cs is not None
        self.depth, self.Ks, self.w2cs = depth, Ks, w2cs

    def shift(self, t: int, u: int, pts: np.ndarray) -> np.ndarray:
        """``[N, 2]``: where static points at ``pts`` [N, 2] of frame t go in frame u, minus ``pts``."""
        pts = np.asarray(pts, np.float32).reshape(-1, 2)
        if not self.on or t == u or len(pts) == 0:
            return np.zeros_like(pts)
        d, K, w = self.depth, self.Ks, self.w2cs
        return rigid_transfer(d[t], K[t], w[t], K[u], w[u], pts) - pts


def _own_velocity(
    cam: _Camera, xy: np.ndarray, t0: np.ndarray, t1: np.ndarray, ids: np.ndarray
) -> np.ndarray:
    """Per-frame object motion ``[M, 2]`` of tracks ``ids`` between their frames t0 < t1, camera removed,
    in frame t1's image; 0 where t0 < 0 (a single visible frame)."""
    v = np.zeros((len(ids), 2), np.float32)
    for k, n in enumerate(ids):
        a, b = int(t0[n]), int(t1[n])
        if a < 0 or a == b:
            continue
        p0, p1 = xy[a, n][None], xy[b, n][None]
        v[k] = ((p1 - p0 - cam.shift(a, b, p0)) / (b - a))[0]
    return v


def link_pieces(
    xy: np.ndarray,
    vis: np.ndarray,
    cfg: MotionConfig,
    images: np.ndarray | None = None,
    depth: np.ndarray | None = None,
    Ks: np.ndarray | None = None,
    w2cs: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, LinkStats]:
    """Join the pieces of one point (see the module docstring).

    Args:
        xy: ``[T, N, 2]`` positions (pixels, x y); only visible entries are read.
        vis: ``[T, N]`` bool visibility.
        cfg: ``track_link_gap`` (0 = no linking), ``track_link_px``, ``track_link_rel``, ``track_link_ncc``,
            ``track_link_patch_px``, ``track_link_camera``.
        images: ``[T, H, W, 3]`` in [0, 1] (or uint8) for the appearance check; None skips it.
        depth: ``[T, H, W]`` metric depth (scene units), ``Ks`` ``[T, 3, 3]``, ``w2cs`` ``[T, 4, 4]``: the camera's
            share of the motion; None (any of them) keeps plain image velocities.

    Returns:
        ``(xy, vis, stats)``: joined pieces are merged into the earliest piece's column, the later columns left
        with no visible frame (same shapes; callers drop empty columns); ``stats.parts`` [N] counts the
        pieces of each column.
    """
    T, N = vis.shape
    stats = LinkStats(pieces=int(vis.any(0).sum()), parts=vis.any(0).astype(np.int64))
    gap = int(cfg.track_link_gap)
    if N == 0 or gap < 1:
        return xy, vis, stats
    xy, vis = xy.copy(), vis.copy()
    cam = _Camera(depth, Ks, w2cs) if cfg.track_link_camera else _Camera(None, None, None)
    grays = None
    if images is not None and cfg.track_link_ncc > -1.0:
        grays = [to_gray_u8(im).astype(np.float32) / 255.0 for im in images]
    any_vis = vis.any(0)
    t_idx = np.arange(T)[:, None]
    first = np.where(any_vis, vis.argmax(0), T)
    last = np.where(any_vis, T - 1 - vis[::-1].argmax(0), -1)
    # The second visible frame from each end (-1 / T where a piece has one frame only).
    before_last = np.where(vis & (t_idx < last[None]), t_idx, -1).max(0)
    after_first = np.where(vis & (t_idx > first[None]), t_idx, T).min(0)

    cands: list[tuple[float, int, int]] = []
    for e in range(T - 1):
        ends = np.flatnonzero(any_vis & (last == e))
        starts = np.flatnonzero(any_vis & (first > e) & (first <= e + gap))
        if not len(ends) or not len(starts):
            continue
        va = _own_velocity(cam, xy, before_last, last, ends)
        vb = _own_velocity(cam, xy, first, np.where(after_first < T, after_first, -1), starts)
        vb[after_first[starts] >= T] = np.nan  # no second frame: velocity unknown
        pe = xy[e, ends]
        for s in np.unique(first[starts]):
            bs = np.flatnonzero(first[starts] == s)
            moved = pe + va * (s - e)
            q = moved + cam.shift(e, int(s), moved)
            d = np.linalg.norm(xy[s, starts[bs]][None] - q[:, None], axis=-1)  # [ends, starts at s]
            speed = np.linalg.norm(va, axis=-1)
            tol = cfg.track_link_px + cfg.track_link_rel * speed * (s - e)
            ia, ib = np.nonzero(d <= tol[:, None])
            if not len(ia):
                continue
            stats.candidates += len(ia)
            wb = vb[bs[ib]]
            known = ~np.isnan(wb[:, 0])
            dv = np.linalg.norm(np.nan_to_num(wb) - va[ia], axis=-1)
            vmax = np.maximum(speed[ia], np.linalg.norm(np.nan_to_num(wb), axis=-1))
            ok_v = ~known | (dv <= cfg.track_link_px + cfg.track_link_rel * vmax)
            stats.rejected_velocity += int((~ok_v).sum())
            ia, ib = ia[ok_v], ib[ok_v]
            ncc = np.ones(len(ia))
            if grays is not None and len(ia):
                ncc = patch_ncc(
                    grays[e], pe[ia], grays[int(s)], xy[s, starts[bs[ib]]], cfg.track_link_patch_px
                )
                ok_a = ncc >= cfg.track_link_ncc  # a flat patch (NaN) never agrees
                stats.rejected_appearance += int((~ok_a).sum())
                ia, ib, ncc = ia[ok_a], ib[ok_a], ncc[ok_a]
            for a, b, c in zip(ia, ib, ncc, strict=True):
                cost = float(d[a, b] / max(tol[a], 1e-6)) + float(1.0 - c)
                cands.append((cost, int(ends[a]), int(starts[bs[b]])))

    used_end: set[int] = set()
    used_start: set[int] = set()
    root = np.arange(N)

    def find(n: int) -> int:
        while root[n] != n:
            n = int(root[n])
        return n

    for _, a, b in sorted(cands):
        if a in used_end or b in used_start or find(a) == b:
            continue
        used_end.add(a)
        used_start.add(b)
        root[b] = a
        stats.links += 1
    for b in range(N):
        r = find(b)
        if r != b:
            xy[vis[:, b], r] = xy[vis[:, b], b]
            vis[:, r] |= vis[:, b]
            vis[:, b] = False
            stats.parts[r] += stats.parts[b]
            stats.parts[b] = 0
    return xy, vis, stats
