"""One scale factor that puts imported depth in the units of the scene's cameras (two-view triangulation).

Depth from a network, from another reconstruction or from a generator comes in its own units; the scene's
cameras fix the world's scale (their baselines, and the test camera's pose with them). Base's bundle
adjustment frees only *relative* per-frame depth scales (their mean log is held at 0), so a depth prior that
is globally 8 % too deep stays 8 % too deep: the static points it lifts do not reproject, and the static
warm-up, the photometric depth term and the scaffold all inherit the error. This module measures the factor
from the flow between training frames: a static pixel seen in frames i and j lies, along camera i's ray, at
the depth where its match in j is reprojected (closed-form least squares), and the factor is the robust
median of ``triangulated / imported`` over matches with enough parallax and a small residual (moving pixels
leave their epipolar line and are dropped by the residual test, or outvoted).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from worldtree.priors.epipolar import relative_pose
from worldtree.priors.flow import FlowPair


@dataclass
class DepthScaleFit:
    """Result of :func:`fit_depth_scale`.

    Attributes:
        scale: factor to multiply the imported depth by (1.0 when not observable).
        matches: flow matches used.
        spread: robust standard deviation (1.4826 x MAD) of their log ratio.
        observable: False when fewer than ``min_matches`` matches had parallax (e.g. the camera only rotates).
    """

    scale: float
    matches: int
    spread: float
    observable: bool


def triangulate_along_ray(
    pts_i: np.ndarray,
    pts_j: np.ndarray,
    K_i: np.ndarray,
    w2c_i: np.ndarray,
    K_j: np.ndarray,
    w2c_j: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth along camera i's z axis of points seen at ``pts_i`` in frame i and ``pts_j`` in frame j.

    Args:
        pts_i, pts_j: ``[N, 2]`` pixels (x, y). K_*: ``[3, 3]``. w2c_*: ``[4, 4]`` OpenCV world-to-camera.

    Returns:
        ``(z [N], residual_px [N], parallax_px [N])``: the depth minimising the two image equations of
        frame j (least squares, in pixels; not finite where the ray is parallel to the baseline), the
        distance in pixels from ``pts_j`` to where that point projects, and how many pixels in frame j the
        projection moves per unit of log depth (0 without baseline: depth is then not observable).
    """
    pi = np.asarray(pts_i, np.float64).reshape(-1, 2)
    pj = np.asarray(pts_j, np.float64).reshape(-1, 2)
    Ki, Kj = np.asarray(K_i, np.float64), np.asarray(K_j, np.float64)
    R, t = relative_pose(np.asarray(w2c_i, np.float64), np.asarray(w2c_j, np.float64))
    ray = np.stack([(pi[:, 0] - Ki[0, 2]) / Ki[0, 0], (pi[:, 1] - Ki[1, 2]) / Ki[1, 1], np.ones(len(pi))], -1)
    d = ray @ R.T  # camera-j direction of the ray; the point is z * d + t in camera j
    f = np.array([Kj[0, 0], Kj[1, 1]])
    ab = (pj - Kj[:2, 2]) / f  # normalised coordinates of the match
    # (z d_xy + t_xy) - ab (z d_z + t_z) = 0, scaled to pixels: A z = B, two rows per match.
    A = (d[:, :2] - ab * d[:, 2:]) * f
    B = (ab * t[2] - t[:2]) * f
    den = (A * A).sum(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(den > 1e-18, (A * B).sum(1) / den, np.nan)
        cam = z[:, None] * d + t
        front = cam[:, 2] > 1e-12
        proj = cam[:, :2] / np.where(front, cam[:, 2], 1.0)[:, None] * f + Kj[:2, 2]
        res = np.where(front, np.linalg.norm(proj - pj, axis=1), np.inf)
        # d proj / d log z = z f (d_xy t_z - t_xy d_z) / (z d_z + t_z)^2
        dpdl = (
            z[:, None]
            * f
            * (d[:, :2] * t[2] - t[:2] * d[:, 2:])
            / np.where(front, cam[:, 2], 1.0)[:, None] ** 2
        )
        par = np.where(front, np.linalg.norm(dpdl, axis=1), 0.0)
    return z, res, par


def _weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    order = np.argsort(x)
    cw = np.cumsum(w[order])
    return float(x[order][np.searchsorted(cw, 0.5 * cw[-1])])


def fit_depth_scale(
    depth: np.ndarray,
    flows: dict[tuple[int, int], FlowPair],
    Ks: np.ndarray,
    w2cs: np.ndarray,
    max_residual_px: float = 1.0,
    min_parallax_px: float = 2.0,
    stride: int = 2,
    min_matches: int = 50,
) -> DepthScaleFit:
    """The factor that best makes ``depth`` agree with the cameras, from the flow matches of every pair.

    Args:
        depth: ``[T, H, W]`` depth along each camera's z axis (any units); values <= 0 are skipped.
        flows: ``{(i, j): FlowPair}`` flow from frame i to j with its validity (pairs with i < j are used).
        Ks: ``[T, 3, 3]``; w2cs: ``[T, 4, 4]`` OpenCV world-to-camera poses, in the scene's units.
        max_residual_px: a match whose triangulated point reprojects farther than this from it is dropped
            (wrong flow, moving surface).
        min_parallax_px: matches whose projection moves less than this many pixels per unit of log depth
            are dropped (no baseline: their depth is not measured).
        stride: pixel spacing of the matches taken from each flow field.
        min_matches: fewer usable matches than this leave the scale at 1 (``observable=False``).

    Returns:
        :class:`DepthScaleFit`; each match weighs by its parallax squared (the inverse variance of its log
        depth for a fixed flow error).
    """
    T, H, W = depth.shape
    ys, xs = np.mgrid[0:H:stride, 0:W:stride]
    logs, weights = [], []
    for (i, j), fp in flows.items():
        if not i < j:
            continue
        ok = fp.valid[ys, xs] & (depth[i][ys, xs] > 0) & np.isfinite(depth[i][ys, xs])
        if not ok.any():
            continue
        p = np.stack([xs[ok], ys[ok]], -1).astype(np.float64)
        q = p + fp.flow[ys[ok], xs[ok]].astype(np.float64)
        z, res, par = triangulate_along_ray(p, q, Ks[i], w2cs[i], Ks[j], w2cs[j])
        good = np.isfinite(z) & (z > 0) & (res <= max_residual_px) & (par >= min_parallax_px)
        if not good.any():
            continue
        logs.append(np.log(z[good] / depth[i][ys[ok], xs[ok]][good].astype(np.float64)))
        weights.append(par[good] ** 2)
    n = int(sum(len(v) for v in logs))
    if n < min_matches:
        return DepthScaleFit(1.0, n, float("nan"), False)
    lr, w = np.concatenate(logs), np.concatenate(weights)
    med = _weighted_median(lr, w)
    spread = 1.4826 * _weighted_median(np.abs(lr - med), w)
    return DepthScaleFit(float(np.exp(med)), n, float(spread), True)
