"""Long-term 2D point tracks through a video: pyramidal Lucas-Kanade chained frame to frame.

Seeds are a regular grid plus Shi-Tomasi corners at the first frame. Each step t -> t+1 tracks every live point
forward, tracks the result back, and keeps it when it comes home within ``fb_max_px`` (and stays inside the
image); a point that fails is finished for good (no re-identification), and a seed that fails within
``min_length`` frames is discarded at once (its slot is reused). Every ``reseed_every`` frames, uncovered areas
(farther than ``min_distance`` from any live point) get new grid and corner seeds, while fewer than
``max_tracks`` slots are in use.
With ``bidirectional`` the points seeded after the first frame are also tracked backwards in time, so a track
can start before its seed frame.

Output follows CoTracker's layout: positions ``[T, N, 2]`` (x, y pixels) and visibility ``[T, N]``. Where a
track is not visible its position holds the nearest visible one (a placeholder, not a prediction).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from worldtree.priors.config import TrackConfig
from worldtree.priors.flow import rigid_transfer, to_gray_u8


@dataclass
class Tracks:
    """Point tracks: ``xy`` [T,N,2] float32 pixels, ``visible`` [T,N] bool, ``seed_frame`` [N] int."""

    xy: np.ndarray
    visible: np.ndarray
    seed_frame: np.ndarray
    pieces: np.ndarray | None = None
    """``[N]`` track pieces joined into each track (:mod:`worldtree.priors.track_linking`); None when the
    tracker does not link pieces."""

    @property
    def num_tracks(self) -> int:
        return int(self.visible.shape[1])


Predictor = Callable[[int, int, np.ndarray], np.ndarray]
"""``predict(src, dst, pts [N,2]) -> [N,2]``: a guess of where points of frame src are in frame dst."""


def _lk(g0: np.ndarray, g1: np.ndarray, p0: np.ndarray, guess: np.ndarray | None, cfg: TrackConfig):
    pts0 = p0.reshape(-1, 1, 2).astype(np.float32)
    kw = {
        "winSize": (cfg.win_size, cfg.win_size),
        "maxLevel": cfg.levels,
        "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
        "minEigThreshold": cfg.min_eigen,
    }
    if guess is None:
        p1, st, _ = cv2.calcOpticalFlowPyrLK(g0, g1, pts0, None, **kw)
    else:
        start = np.ascontiguousarray(guess.reshape(-1, 1, 2), dtype=np.float32).copy()
        p1, st, _ = cv2.calcOpticalFlowPyrLK(g0, g1, pts0, start, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **kw)
    return p1.reshape(-1, 2), st.ravel() == 1


def _lk_step(
    g0: np.ndarray,
    g1: np.ndarray,
    p0: np.ndarray,
    cfg: TrackConfig,
    guess_fwd: Callable[[np.ndarray], np.ndarray] | None = None,
    guess_bwd: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Track p0 [N,2] from g0 to g1 with a forward-backward check: (p1 [N,2], ok [N]).

    ``guess_fwd(p0)`` / ``guess_bwd(p1)`` give optional starting positions for each direction (the backward
    guess never sees p0, so the check stays honest).
    """
    if len(p0) == 0:
        return p0.copy(), np.zeros(0, bool)
    p1, st1 = _lk(g0, g1, p0, None if guess_fwd is None else guess_fwd(p0), cfg)
    p0b, st2 = _lk(g1, g0, np.nan_to_num(p1, nan=-1e6), None if guess_bwd is None else guess_bwd(p1), cfg)
    H, W = g0.shape
    ok = st1 & st2
    ok &= np.all(np.isfinite(p1), 1) & np.all(np.isfinite(p0b), 1)
    ok &= np.linalg.norm(np.nan_to_num(p0b - p0, nan=1e9), axis=1) < cfg.fb_max_px
    ok &= (p1[:, 0] >= 0) & (p1[:, 0] <= W - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= H - 1)
    return p1, ok


def seed_points(
    gray: np.ndarray, live: np.ndarray, cfg: TrackConfig, budget: int, corners: int
) -> np.ndarray:
    """New seeds [M,2] (M <= budget) on a grid and on corners, away from ``live`` points [N,2]."""
    if budget <= 0:
        return np.zeros((0, 2), np.float32)
    H, W = gray.shape
    free = np.full((H, W), 255, np.uint8)
    r = max(1, cfg.min_distance)
    for x, y in np.round(live).astype(int):
        cv2.circle(free, (int(x), int(y)), r, 0, -1)
    margin = max(2, cfg.win_size // 4)
    s = max(2, cfg.grid_step)
    gy, gx = np.mgrid[margin + s // 2 : H - margin : s, margin + s // 2 : W - margin : s]
    grid = np.stack([gx.ravel(), gy.ravel()], -1).astype(np.float32)
    grid = grid[free[grid[:, 1].astype(int), grid[:, 0].astype(int)] > 0] if len(grid) else grid
    # Corners may sit between grid seeds (only exact duplicates are avoided); near live points they may not.
    for x, y in np.round(grid).astype(int):
        cv2.circle(free, (int(x), int(y)), max(1, r // 3), 0, -1)
    free[:margin], free[H - margin :], free[:, :margin], free[:, W - margin :] = 0, 0, 0, 0
    pts = [grid]
    if corners > 0:
        c = cv2.goodFeaturesToTrack(gray, corners, cfg.corner_quality, cfg.min_distance, mask=free)
        if c is not None:
            pts.append(c.reshape(-1, 2).astype(np.float32))
    out = np.concatenate(pts, 0)
    return out[:budget]


def track_video(
    images: np.ndarray,
    cfg: TrackConfig,
    on_frame: Callable[[int], None] | None = None,
    predict: Predictor | None = None,
) -> Tracks:
    """Track points through ``images`` [T,H,W,3] (float in [0,1] or uint8); see the module doc.

    ``predict`` (e.g. the static-scene transfer by depth and poses) gives Lucas-Kanade its starting positions.
    """

    def guesses(a: int, b: int) -> tuple:
        if predict is None:
            return None, None
        return (lambda p: predict(a, b, p)), (lambda p: predict(b, a, p))

    grays = [to_gray_u8(im) for im in images]
    T = len(grays)
    cap = cfg.max_tracks
    xy = np.zeros((T, cap, 2), np.float32)
    vis = np.zeros((T, cap), bool)
    seed = np.zeros(cap, np.int64)
    n = 0  # slots used so far
    free: list[int] = []  # slots of seeds that died young, reused before new ones

    def add(t: int, pts: np.ndarray) -> np.ndarray:
        nonlocal n, free
        reuse = free[: len(pts)]
        free = free[len(reuse) :]
        m = min(len(pts) - len(reuse), cap - n)
        idx = np.concatenate([np.asarray(reuse, np.int64), np.arange(n, n + m)])
        xy[t, idx] = pts[: len(idx)]
        vis[t, idx] = True
        seed[idx] = t
        n += m
        return idx

    def retire(dead: np.ndarray) -> None:
        # Seeds lost within min_length frames (textureless, occluded) would be dropped at the end anyway;
        # freeing their slots at once keeps max_tracks for tracks that last.
        young = dead[vis[:, dead].sum(0) < cfg.min_length]
        vis[:, young] = False
        xy[:, young] = 0.0
        free.extend(young.tolist())

    active = add(0, seed_points(grays[0], np.zeros((0, 2)), cfg, cap, cfg.max_corners))
    if on_frame is not None:
        on_frame(0)
    for t in range(T - 1):
        p1, ok = _lk_step(grays[t], grays[t + 1], xy[t, active], cfg, *guesses(t, t + 1))
        retire(active[~ok])
        active = active[ok]
        xy[t + 1, active] = p1[ok]
        vis[t + 1, active] = True
        budget = cap - n + len(free)
        if (t + 1) % max(1, cfg.reseed_every) == 0 and budget > 0:
            new = seed_points(grays[t + 1], xy[t + 1, active], cfg, budget, cfg.max_corners // 4)
            active = np.concatenate([active, add(t + 1, new)])
        if on_frame is not None:
            on_frame(t + 1)

    if cfg.bidirectional:
        back = np.zeros(0, np.int64)
        for t in range(T - 1, 0, -1):
            back = np.concatenate([back, np.flatnonzero(seed[:n] == t)])
            p0, ok = _lk_step(grays[t], grays[t - 1], xy[t, back], cfg, *guesses(t, t - 1))
            back = back[ok]
            xy[t - 1, back] = p0[ok]
            vis[t - 1, back] = True

    xy, vis, seed = xy[:, :n], vis[:, :n], seed[:n]
    keep = vis.sum(0) >= cfg.min_length  # also drops retired slots that were never reused
    xy, vis, seed = xy[:, keep], vis[:, keep], seed[keep]
    return Tracks(hold_invisible(xy, vis), vis, seed)


def hold_invisible(xy: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """Fill positions [T,N,2] where not visible with the nearest visible position in time (earlier wins ties)."""
    T, N = vis.shape
    if N == 0 or T == 0:
        return xy.copy()
    t_idx = np.arange(T)[:, None]
    last = np.maximum.accumulate(np.where(vis, t_idx, -1), axis=0)  # latest visible frame <= t
    nxt = np.flip(np.minimum.accumulate(np.flip(np.where(vis, t_idx, T), 0), axis=0), 0)  # earliest >= t
    use_last = (last >= 0) & ((nxt >= T) | (t_idx - last <= nxt - t_idx))
    src = np.where(use_last, last, np.where(nxt < T, nxt, 0))
    return np.take_along_axis(xy, np.repeat(src[..., None], 2, -1), 0)


def depth_predictor(depth: np.ndarray, Ks: np.ndarray, w2cs: np.ndarray) -> Predictor:
    """A :data:`Predictor` moving points as static surfaces: depth ``[T,H,W]``, ``Ks`` [T,3,3], ``w2cs`` [T,4,4]."""

    def predict(src: int, dst: int, pts: np.ndarray) -> np.ndarray:
        return rigid_transfer(depth[src], Ks[src], w2cs[src], Ks[dst], w2cs[dst], pts)

    return predict
