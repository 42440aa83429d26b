"""Dynamic tracks chained through dense flow inside the dynamic masks (survive the rig's camera changes).

Lucas-Kanade tracks (:mod:`worldtree.priors.tracks`) follow small windows from frame to frame and die at the
first camera change of the rig or on a moving object whose appearance changes. Here tracks live only inside
the dynamic masks and are carried by the dense flow pairs, which the priors already checked forward-backward
and photometrically (``FlowPair.valid``) and which were started from the rigid flow across camera changes:

1. **chain**: a point at ``x`` in frame t goes to ``x + f_{t,t+g}(x)`` (bilinear) for the first gap ``g`` of
   ``MotionConfig.track_gaps`` whose flow is valid there and lands inside the (dilated) mask of frame t+g;
   a failed step at gap 1 (e.g. a camera change) is bridged by a larger gap, the frames in between left
   invisible. With the frames given, a step must also keep the point's look (patch NCC at least
   ``track_step_ncc``): DIS flow that passes the forward-backward check can still land on another part of a
   fast, turning object, and a chain that follows it drifts. A point with no valid step ends. Small holes of the flow's validity inside the masks are filled
   first (mean of the valid flow within ``track_fill_px``), so one rejected pixel does not end a track.
2. **re-detect**: every ``track_seed_every`` frames, mask pixels on a ``track_seed_step`` grid farther than
   that step from every visible track point get new tracks, chained forwards and then backwards.
3. **link**: chained backwards, a new piece that lands within ``track_link_px`` of the end of an older piece
   (visible in no frame the new piece is) is the same point; the two become one track.
4. **link across gaps**: a piece that ends and one that starts a few frames later where the first one's
   motion (camera motion removed) carries it, moving alike and looking alike, are joined
   (:mod:`worldtree.priors.track_linking`).

Output follows the CoTracker layout of the other tracks: ``xy [T, N, 2]`` pixels, ``visible [T, N]``.
"""

from __future__ import annotations

from collections.abc import Mapping

import cv2
import numpy as np
from scipy.spatial import cKDTree

from worldtree.priors.config import MotionConfig
from worldtree.priors.flow import FlowPair, bilinear, to_gray_u8
from worldtree.priors.track_linking import _FLAT, link_pieces, patch_ncc
from worldtree.priors.tracks import Tracks, hold_invisible


class _HoleFilled:
    """Flow pairs with small holes of their validity filled inside the masks (built on first use).

    The checks reject isolated pixels of a moving object's flow (a fifth at gap 1 on the generated rig), and
    a chain of independent 80% steps dies after a few frames. A pixel whose flow failed takes the mean of the
    valid flow of the mask pixels within ``radius`` when at least ``min_frac`` of that window is valid.
    """

    def __init__(self, flows, inside: np.ndarray, radius: int, min_frac: float = 0.2):
        self.flows, self.inside, self.r, self.min_frac = flows, inside, radius, min_frac
        self.done: dict[tuple[int, int], FlowPair] = {}

    def __contains__(self, key) -> bool:
        return key in self.flows

    def __getitem__(self, key: tuple[int, int]) -> FlowPair:
        if key not in self.done:
            fp = self.flows[key]
            if self.r <= 0:
                self.done[key] = fp
            else:
                k = (2 * self.r + 1, 2 * self.r + 1)
                w = (fp.valid & self.inside[key[0]]).astype(np.float32)

                def box(x):
                    return cv2.boxFilter(x, -1, k, normalize=True, borderType=cv2.BORDER_CONSTANT)

                den = box(w)
                f = (
                    np.stack([box(fp.flow[..., c] * w) for c in range(2)], -1)
                    / np.maximum(den, 1e-6)[..., None]
                )
                fill = ~fp.valid & (den >= self.min_frac)
                self.done[key] = FlowPair(
                    np.where(fill[..., None], f, fp.flow).astype(np.float32), fp.valid | fill
                )
        return self.done[key]


def _step(
    pts: np.ndarray,
    t: int,
    direction: int,
    flows,
    inside: np.ndarray,
    gaps: tuple[int, ...],
    grays: list[np.ndarray] | None = None,
    min_ncc: float = -1.0,
    half: int = 3,
    min_std: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Carry ``pts`` [N, 2] of frame t one step: ``(positions [N, 2], target frame [N] or -1 when it ends)``.

    ``flows``: a mapping ``(t, u) -> FlowPair``."""
    T, H, W = inside.shape
    out = pts.copy()
    dst = np.full(len(pts), -1, np.int64)
    todo = np.ones(len(pts), bool)
    for g in gaps:
        u = t + direction * g
        if not todo.any() or not 0 <= u < T or (t, u) not in flows:
            continue
        fp = flows[(t, u)]
        idx = np.flatnonzero(todo)
        p = pts[idx]
        xi = np.clip(np.round(p[:, 0]).astype(np.int64), 0, W - 1)
        yi = np.clip(np.round(p[:, 1]).astype(np.int64), 0, H - 1)
        ok = fp.valid[yi, xi]
        q = p + np.stack([bilinear(fp.flow[..., 0], p), bilinear(fp.flow[..., 1], p)], -1)
        ok &= (q[:, 0] >= 0) & (q[:, 0] <= W - 1) & (q[:, 1] >= 0) & (q[:, 1] <= H - 1)
        qx = np.clip(np.round(q[:, 0]).astype(np.int64), 0, W - 1)
        qy = np.clip(np.round(q[:, 1]).astype(np.int64), 0, H - 1)
        ok &= inside[u, qy, qx]
        if grays is not None and min_ncc > -1.0 and ok.any():
            j = np.flatnonzero(ok)
            # A patch flatter than min_std (NaN) does not stop the chain; with min_std 0 the nearly uniform
            # patches (patch_ncc's own floor) do.
            c = patch_ncc(grays[t], p[j], grays[u], q[j], half, max(min_std, _FLAT))
            ok[j] = (np.isnan(c) & (min_std > 0)) | (c >= min_ncc)
        out[idx[ok]] = q[ok]
        dst[idx[ok]] = u
        todo[idx[ok]] = False
    return out, dst


def dilate_masks(masks: np.ndarray, radius: int) -> np.ndarray:
    """``masks`` [T, H, W] grown by a disc of ``radius`` px: the region a chained point must stay in."""
    r = max(0, radius)
    if r == 0 or len(masks) == 0:
        return masks.astype(bool)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return np.stack([cv2.dilate(m.astype(np.uint8), k) > 0 for m in masks])


def chain_gaps(cfg: MotionConfig) -> tuple[int, ...]:
    """The frame gaps the chaining steps over, ascending (``MotionConfig.track_gaps``; (1,) when none)."""
    return tuple(sorted(set(int(g) for g in cfg.track_gaps if g >= 1))) or (1,)


def _seeds(mask: np.ndarray, taken: np.ndarray, step: int) -> np.ndarray:
    """Grid pixels [M, 2] (x, y) of ``mask`` [H, W] farther than ``step`` from every point of ``taken``."""
    H, W = mask.shape
    gy, gx = np.mgrid[step // 2 : H : step, step // 2 : W : step]
    grid = np.stack([gx.ravel(), gy.ravel()], -1).astype(np.float32)
    grid = grid[mask[grid[:, 1].astype(int), grid[:, 0].astype(int)]]
    if len(grid) and len(taken):
        d, _ = cKDTree(taken).query(grid, k=1)
        grid = grid[d > step]
    return grid


def chain_dynamic_tracks(
    flows: Mapping[tuple[int, int], FlowPair],
    masks: np.ndarray,
    cfg: MotionConfig,
    images: np.ndarray | None = None,
    depth: np.ndarray | None = None,
    Ks: np.ndarray | None = None,
    w2cs: np.ndarray | None = None,
    stats: dict | None = None,
) -> Tracks:
    """Dynamic tracks inside ``masks`` [T, H, W] bool, chained through ``flows`` (see the module docstring).

    ``images`` [T, H, W, 3] and metric ``depth`` [T, H, W] with ``Ks`` [T, 3, 3], ``w2cs`` [T, 4, 4] make the
    last linking step compare appearance and remove the camera's motion (:func:`link_pieces`); ``stats``, when
    given, receives its counts (:class:`worldtree.priors.track_linking.LinkStats`).

    Returns :class:`worldtree.priors.tracks.Tracks` (``xy`` [T, N, 2] float32 px, ``visible`` [T, N],
    ``seed_frame`` [N], ``pieces`` [N]); N may be 0 (empty masks).
    """
    T, H, W = masks.shape
    inside = dilate_masks(masks, cfg.track_mask_dilate_px)
    gaps = chain_gaps(cfg)
    flows = _HoleFilled(flows, inside, cfg.track_fill_px)
    grays = None
    if images is not None and cfg.track_step_ncc > -1.0:
        grays = [to_gray_u8(im).astype(np.float32) / 255.0 for im in images]
    half = cfg.track_link_patch_px
    cap = max(0, cfg.max_dynamic_tracks)
    xy = np.zeros((T, cap, 2), np.float32)
    vis = np.zeros((T, cap), bool)
    seed = np.zeros(cap, np.int64)
    alive = np.zeros(cap, bool)  # still chained forwards
    n = 0
    step = max(1, cfg.track_seed_step)
    every = max(1, cfg.track_seed_every)

    # Forward: chain live points, re-detecting uncovered mask pixels every `every` frames.
    for t in range(T):
        if t % every == 0 and n < cap and masks[t].any():
            new = _seeds(masks[t], xy[t, :n][vis[t, :n]], step)
            new = new[: cap - n]
            xy[t, n : n + len(new)] = new
            vis[t, n : n + len(new)] = True
            seed[n : n + len(new)] = t
            alive[n : n + len(new)] = True
            n += len(new)
        act = np.flatnonzero(alive[:n] & vis[t, :n])
        if len(act) == 0:
            continue
        q, dst = _step(xy[t, act], t, +1, flows, inside, gaps, grays, cfg.track_step_ncc, half, cfg.track_step_min_std)
        for u in np.unique(dst[dst >= 0]):
            sel = act[dst == u]
            xy[u, sel] = q[dst == u]
            vis[u, sel] = True
        alive[act[dst < 0]] = False

    # Backward from each seed frame; a piece meeting the end of an older piece is linked to it.
    merged = np.zeros(n, bool)
    front = seed[:n].copy()  # earliest frame reached so far by each backward-chained piece
    back = np.zeros(0, np.int64)
    for t in range(T - 1, 0, -1):
        back = np.concatenate([back, np.flatnonzero(seed[:n] == t)])
        act = back[(front[back] == t) & ~merged[back]]
        if len(act) == 0:
            continue
        q, dst = _step(xy[t, act], t, -1, flows, inside, gaps, grays, cfg.track_step_ncc, half, cfg.track_step_min_std)
        stop = dst < 0
        for u in np.unique(dst[dst >= 0]):
            j = np.flatnonzero(dst == u)
            ids = act[j]
            others = np.flatnonzero(vis[u, :n] & ~merged[:n])
            if len(others):
                d, nn = cKDTree(xy[u, others]).query(q[j], k=1)
                for a in np.flatnonzero(d <= cfg.track_link_px):
                    b, other = ids[a], others[nn[a]]
                    if not (vis[:, b] & vis[:, other]).any():
                        # Same point: the newer piece's frames join the older track.
                        xy[vis[:, b], other] = xy[vis[:, b], b]
                        vis[:, other] |= vis[:, b]
                        vis[:, b] = False
                        merged[b] = True
                    # Either linked or running into a live track: stop rather than duplicate it.
                    stop[j[a]] = True
            go = j[~stop[j]]
            xy[u, act[go]] = q[go]
            vis[u, act[go]] = True
            front[act[go]] = u
        back = back[~np.isin(back, act[stop])]

    xy, vis, seed = xy[:, :n], vis[:, :n], seed[:n]
    xy, vis, links = link_pieces(xy, vis, cfg, images, depth, Ks, w2cs)
    if stats is not None:
        stats.update(links.as_dict())
    ok = vis.sum(0) >= max(1, cfg.track_min_length)
    xy, vis, seed = xy[:, ok], vis[:, ok], seed[ok]
    return Tracks(hold_invisible(xy, vis), vis, seed, links.parts[ok])
