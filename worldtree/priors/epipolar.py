"""Epipolar error maps and dynamic (EPI) masks from optical flow and camera poses.

For a flow pair i -> j, a static point seen at ``x1`` in frame i must land on the epipolar line ``F x1`` in
frame j. With known poses (OpenCV world-to-camera ``[R | t]``), the relative motion is
``R = R_j R_i^T``, ``t = t_j - R t_i`` and

    F = K_j^-T [t]_x R K_i^-1.

The error of a correspondence ``(x1, x2 = x1 + flow)`` is its Sampson distance, the first-order distance in
pixels to the epipolar geometry:

    d = |x2^T F x1| / sqrt((F x1)_0^2 + (F x1)_1^2 + (F^T x2)_0^2 + (F^T x2)_1^2).

The error map of frame i is the maximum of d over its flow pairs (pixels failing the flow consistency check
contribute 0); a pair whose median error exceeds ``max_pair_median_px`` is skipped as failed. When a pair's cameras share a centre (zero baseline, e.g. the same rig camera twice), a static
point must follow the rotation homography ``H = K_j R K_i^-1`` and the error is ``|x2 - H x1|``. A pixel is
dynamic when its error exceeds ``EpiConfig.threshold_px``. Motion along the epipolar line is invisible to this
test (a limit of every epipolar mask).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import cv2
import numpy as np

from worldtree.infra.parallel import ordered_map
from worldtree.priors.config import EpiConfig
from worldtree.priors.flow import FlowPair

_EPS = 1e-12


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v]_x`` [3,3] of a 3-vector."""
    x, y, z = (float(a) for a in v)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def relative_pose(w2c_i: np.ndarray, w2c_j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R [3,3], t [3]) taking camera-i coordinates to camera-j coordinates."""
    Ri, ti = w2c_i[:3, :3], w2c_i[:3, 3]
    Rj, tj = w2c_j[:3, :3], w2c_j[:3, 3]
    R = Rj @ Ri.T
    return R, tj - R @ ti


def fundamental_from_poses(
    K_i: np.ndarray, w2c_i: np.ndarray, K_j: np.ndarray, w2c_j: np.ndarray
) -> np.ndarray:
    """Fundamental matrix [3,3] with ``x_j^T F x_i = 0`` for static points (pixels, homogeneous)."""
    R, t = relative_pose(np.asarray(w2c_i, np.float64), np.asarray(w2c_j, np.float64))
    E = skew(t) @ R
    F = np.linalg.inv(np.asarray(K_j, np.float64)).T @ E @ np.linalg.inv(np.asarray(K_i, np.float64))
    n = np.linalg.norm(F)
    return F / n if n > _EPS else F


def sampson_distance(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Sampson distance in pixels of correspondences ``x1 -> x2`` ([..., 2] each) under ``F`` [3,3]."""
    F = np.asarray(F, np.float64)
    h1 = np.concatenate([x1, np.ones_like(x1[..., :1])], -1).astype(np.float64)
    h2 = np.concatenate([x2, np.ones_like(x2[..., :1])], -1).astype(np.float64)
    Fx1 = h1 @ F.T
    Ftx2 = h2 @ F
    num = np.abs(np.sum(h2 * Fx1, -1))
    den = np.sqrt(Fx1[..., 0] ** 2 + Fx1[..., 1] ** 2 + Ftx2[..., 0] ** 2 + Ftx2[..., 1] ** 2)
    return num / np.maximum(den, _EPS)


def homography_transfer_error(H: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """``|x2 - H(x1)|`` in pixels for a pure-rotation pair; [..., 2] -> [...]."""
    h1 = np.concatenate([x1, np.ones_like(x1[..., :1])], -1).astype(np.float64)
    p = h1 @ np.asarray(H, np.float64).T
    z = p[..., 2:3]
    z = np.where(np.abs(z) < _EPS, _EPS, z)
    return np.linalg.norm(p[..., :2] / z - x2, axis=-1)


def estimate_fundamental(
    x1: np.ndarray, x2: np.ndarray, rng: np.random.Generator, max_points: int
) -> np.ndarray | None:
    """Robust F from correspondences [N,2] with LMedS (cv2.findFundamentalMat); None when degenerate."""
    if len(x1) < 16:
        return None
    if len(x1) > max_points:
        idx = rng.choice(len(x1), max_points, replace=False)
        x1, x2 = x1[idx], x2[idx]
    # Nearly identical point sets (no motion at all) give no epipolar geometry to estimate.
    if np.median(np.linalg.norm(x2 - x1, axis=-1)) < 1e-3:
        return None
    F, _ = cv2.findFundamentalMat(x1.astype(np.float64), x2.astype(np.float64), cv2.FM_LMEDS)
    if F is None or F.shape != (3, 3) or not np.all(np.isfinite(F)):
        return None
    return F


def pair_error(
    pair: FlowPair,
    K_i: np.ndarray | None,
    w2c_i: np.ndarray | None,
    K_j: np.ndarray | None,
    w2c_j: np.ndarray | None,
    cfg: EpiConfig,
    rng: np.random.Generator,
) -> np.ndarray:
    """Error map [H,W] (pixels, float32) of one flow pair; 0 where the flow is not consistent."""
    H, W = pair.flow.shape[:2]
    py, px = np.mgrid[0:H, 0:W].astype(np.float64)
    x1 = np.stack([px, py], -1)
    x2 = x1 + pair.flow
    err = np.zeros((H, W), np.float64)
    v = pair.valid
    if not v.any():
        return err.astype(np.float32)
    if cfg.use_poses and w2c_i is not None and w2c_j is not None:
        R, t = relative_pose(np.asarray(w2c_i, np.float64), np.asarray(w2c_j, np.float64))
        centre_i = -w2c_i[:3, :3].T @ w2c_i[:3, 3]
        centre_j = -w2c_j[:3, :3].T @ w2c_j[:3, 3]
        if np.linalg.norm(centre_i - centre_j) < cfg.min_baseline:
            Hm = np.asarray(K_j, np.float64) @ R @ np.linalg.inv(np.asarray(K_i, np.float64))
            err[v] = homography_transfer_error(Hm, x1[v], x2[v])
        else:
            err[v] = sampson_distance(fundamental_from_poses(K_i, w2c_i, K_j, w2c_j), x1[v], x2[v])
    else:
        F = estimate_fundamental(x1[v], x2[v], rng, cfg.lmeds_points)
        if F is not None:
            err[v] = sampson_distance(F, x1[v], x2[v])
        else:
            # No estimable geometry: treat the pair as a pure rotation about nothing (identity transfer).
            err[v] = np.linalg.norm(x2[v] - x1[v], axis=-1)
    return np.nan_to_num(err, nan=0.0, posinf=0.0).astype(np.float32)


def epipolar_error_maps(
    flows: Mapping[tuple[int, int], FlowPair],
    num_frames: int,
    Ks: np.ndarray | None,
    w2cs: np.ndarray | None,
    cfg: EpiConfig,
    on_frame: Callable[[int], None] | None = None,
    seed: int = 0,
    threads: int = 1,
) -> np.ndarray:
    """Per-frame error ``[T, H, W]`` (pixels): the maximum over the flow pairs leaving each frame.

    ``Ks`` [T,3,3] and ``w2cs`` [T,4,4] give known poses; pass None (or ``cfg.use_poses=False``) to estimate
    each pair's fundamental matrix from the flow with LMedS. Frames without any flow pair get zeros. With
    known poses the pairs are computed on ``threads`` threads (the same maps for any count); the LMedS
    estimate draws its samples from one seeded sequence, pair after pair, so it stays on one thread.
    """
    if not flows:
        raise ValueError("epipolar_error_maps needs at least one flow pair")
    H, W = next(iter(flows.values())).flow.shape[:2]
    out = np.zeros((num_frames, H, W), np.float32)
    rng = np.random.default_rng(seed)
    by_src: dict[int, list[int]] = {}
    for i, j in flows:
        by_src.setdefault(i, []).append(j)
    order = [(i, j) for i in range(num_frames) for j in sorted(by_src.get(i, []))]

    def one(ij: tuple[int, int]) -> np.ndarray:
        i, j = ij
        return pair_error(
            flows[ij],
            None if Ks is None else Ks[i],
            None if w2cs is None else w2cs[i],
            None if Ks is None else Ks[j],
            None if w2cs is None else w2cs[j],
            cfg,
            rng,
        )

    posed = cfg.use_poses and w2cs is not None
    errors = ordered_map(one, order, threads if posed else 1)
    for i in range(num_frames):
        for j in sorted(by_src.get(i, [])):
            e = next(errors)
            v = flows[(i, j)].valid
            # A pair whose typical (median) error is large failed as a whole (flow lost across a wide
            # camera jump): it says nothing about which pixels move, so it is skipped.
            if v.any() and float(np.median(e[v])) > cfg.max_pair_median_px:
                continue
            np.maximum(out[i], e, out=out[i])
        if on_frame is not None:
            on_frame(i)
    return out


def epi_masks(errors: np.ndarray, cfg: EpiConfig) -> np.ndarray:
    """Dynamic masks ``[T, H, W]`` bool: error above ``cfg.threshold_px``, isolated pixels and regions smaller
    than ``cfg.min_area_frac`` of the frame removed.

    An all-static scene simply gives all-false masks.
    """
    masks = errors > cfg.threshold_px
    if cfg.open_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * cfg.open_px + 1, 2 * cfg.open_px + 1))
        masks = np.stack([cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_OPEN, k) > 0 for m in masks])
    if cfg.min_area_frac > 0 and masks.size:
        min_area = cfg.min_area_frac * masks.shape[1] * masks.shape[2]
        for t in range(len(masks)):
            if not masks[t].any():
                continue
            _, lab, stats, _ = cv2.connectedComponentsWithStats(masks[t].astype(np.uint8), connectivity=8)
            small = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] < min_area)
            small = small[small > 0]  # label 0 is the background
            if small.size:
                masks[t] &= ~np.isin(lab, small)
    return masks


def label_dynamic_tracks(
    tracks: np.ndarray, visible: np.ndarray, masks: np.ndarray, min_frames: int = 2
) -> np.ndarray:
    """Tracks ``[T,N,2]`` (visibility ``[T,N]``) on a dynamic-mask pixel in >= ``min_frames`` frames: ``[N]`` bool.

    Zero tracks or empty masks give an all-false (possibly empty) result, never an error.
    """
    T, N = visible.shape
    if N == 0:
        return np.zeros(0, bool)
    H, W = masks.shape[1:]
    xi = np.clip(np.round(tracks[..., 0]).astype(np.int64), 0, W - 1)
    yi = np.clip(np.round(tracks[..., 1]).astype(np.int64), 0, H - 1)
    tt = np.broadcast_to(np.arange(T)[:, None], (T, N))
    hits = masks[tt, yi, xi] & visible
    return hits.sum(0) >= min_frames
