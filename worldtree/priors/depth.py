"""Metric depth by multi-view plane-sweep stereo over neighbouring training frames (known poses).

For a reference frame r, ``num_planes`` fronto-parallel planes ``z = d`` (uniform in inverse depth between near
and far, in scene units) are swept. A source frame s is warped onto each plane by the plane-induced homography

    H_d = K_s (R + t n^T / d) K_r^-1,        n = (0, 0, 1),  (R, t): camera r -> camera s,

and compared with the reference by zero-mean normalised cross-correlation (ZNCC) over a ``patch x patch``
window. The cost of a hypothesis is the mean of the ``best_k`` lowest source costs ``1 - ZNCC`` (robust to
occlusion and to moving objects in some sources). Winner-take-all picks the plane, a parabola through the
neighbouring costs refines it, and the confidence is the winning ZNCC, zeroed on textureless patches. Pixels
with confidence below ``min_conf`` are filled edge-aware: a confidence-weighted fast global smoother
(cv2.ximgproc) of the inverse depth, guided by the reference image.

The training frames of a monocular video come from different rig cameras, so neighbours in time see the static
scene from other viewpoints; moving objects break photo-consistency and get low confidence (then filled).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from worldtree.imageio import as_uint8_array
from worldtree.priors.config import DepthConfig
from worldtree.priors.epipolar import relative_pose

_BAD_COST = 2.0  # 1 - ZNCC ranges over [0, 2]; out-of-view hypotheses get the worst cost


@dataclass
class DepthResult:
    """Depth of one frame: ``depth`` [H,W] scene units, ``conf`` [H,W] in [0,1] (0 where filled)."""

    depth: np.ndarray
    conf: np.ndarray


def camera_centre(w2c: np.ndarray) -> np.ndarray:
    """World position [3] of a camera given its world-to-camera matrix [4,4]."""
    return -w2c[:3, :3].T @ w2c[:3, 3]


def select_sources(ref: int, w2cs: np.ndarray, cfg: DepthConfig, far: float) -> list[int]:
    """Source frames for ``ref``: nearest in time within ``max_time_gap`` whose baseline is usable."""
    c_ref = camera_centre(w2cs[ref])
    cands = []
    for s in range(len(w2cs)):
        gap = abs(s - ref)
        if s == ref or gap > cfg.max_time_gap:
            continue
        if np.linalg.norm(camera_centre(w2cs[s]) - c_ref) < cfg.min_baseline_ratio * far:
            continue
        cands.append((gap, s))
    return [s for _, s in sorted(cands)[: cfg.num_sources]]


def _box(img: np.ndarray, k: int) -> np.ndarray:
    return cv2.boxFilter(img, cv2.CV_32F, (k, k), normalize=True, borderType=cv2.BORDER_REFLECT)


def _gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image, np.float32)
    if img.max() > 1.5:
        img = img / 255.0
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img


def plane_sweep_cost(
    ref_img: np.ndarray,
    src_imgs: list[np.ndarray],
    K_ref: np.ndarray,
    w2c_ref: np.ndarray,
    K_srcs: list[np.ndarray],
    w2c_srcs: list[np.ndarray],
    inv_depths: np.ndarray,
    cfg: DepthConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Cost volume ``[D, H, W]`` (1 - ZNCC, best_k-averaged) and the reference patch std ``[H, W]``."""
    k = cfg.patch
    ref = _gray(ref_img)
    H, W = ref.shape
    mu_r = _box(ref, k)
    var_r = np.maximum(_box(ref * ref, k) - mu_r * mu_r, 0.0)
    std_r = np.sqrt(var_r)
    Kr_inv = np.linalg.inv(np.asarray(K_ref, np.float64))
    n = np.array([[0.0, 0.0, 1.0]])
    srcs = [np.dstack([_gray(s), np.ones_like(_gray(s))]) for s in src_imgs]
    rel = [relative_pose(np.asarray(w2c_ref, np.float64), np.asarray(w, np.float64)) for w in w2c_srcs]
    D = len(inv_depths)
    volume = np.empty((D, H, W), np.float32)
    kk = min(cfg.best_k, len(srcs))
    per_src = np.empty((len(srcs), H, W), np.float32)
    for di, inv_d in enumerate(inv_depths):
        for si, (src, Ks, (R, t)) in enumerate(zip(srcs, K_srcs, rel, strict=True)):
            Hd = np.asarray(Ks, np.float64) @ (R + t[:, None] @ n * inv_d) @ Kr_inv
            warped = cv2.warpPerspective(
                src, Hd, (W, H), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT
            )
            g, inside = warped[..., 0], warped[..., 1]
            mu_w = _box(g, k)
            var_w = np.maximum(_box(g * g, k) - mu_w * mu_w, 0.0)
            cov = _box(ref * g, k) - mu_r * mu_w
            zncc = cov / np.sqrt(var_r * var_w + 1e-8)
            cost = 1.0 - np.clip(zncc, -1.0, 1.0)
            # A window partly outside the source image has no reliable match.
            per_src[si] = np.where(_box(inside, k) > 0.999, cost, _BAD_COST)
        if kk == 1:
            volume[di] = per_src.min(0)
        else:
            volume[di] = np.sort(per_src, axis=0)[:kk].mean(0)
    return volume, std_r


def winner_take_all(volume: np.ndarray, inv_depths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sub-plane inverse depth ``[H,W]`` and the winning cost ``[H,W]`` from a cost volume ``[D,H,W]``."""
    D = volume.shape[0]
    idx = np.argmin(volume, 0)
    c0 = np.take_along_axis(volume, idx[None], 0)[0]
    offset = np.zeros_like(c0)
    if D >= 3:
        im = np.clip(idx - 1, 0, D - 1)
        ip = np.clip(idx + 1, 0, D - 1)
        cm = np.take_along_axis(volume, im[None], 0)[0]
        cp = np.take_along_axis(volume, ip[None], 0)[0]
        den = cm - 2 * c0 + cp
        interior = (idx > 0) & (idx < D - 1) & (den > 1e-6)
        offset = np.where(interior, np.clip(0.5 * (cm - cp) / np.where(interior, den, 1.0), -0.5, 0.5), 0.0)
    step = (inv_depths[-1] - inv_depths[0]) / max(D - 1, 1)
    inv = inv_depths[0] + (idx + offset) * step
    return inv.astype(np.float32), c0


def edge_aware_fill(
    inv_depth: np.ndarray,
    weight: np.ndarray,
    guide_rgb: np.ndarray,
    lam: float,
    sigma: float,
    support: float = 0.0,
) -> np.ndarray:
    """Confidence-weighted fast global smoothing of ``inv_depth`` [H,W] guided by ``guide_rgb`` [H,W,3].

    Returns the normalised smoothed map ``(FGS(w * x) + s * P) / (FGS(w) + s)``, where ``s = support`` and
    ``P`` is :func:`plane_fit` of the weighted pixels: the smoothed map wherever confident pixels reach (their
    smoothed weight ``FGS(w)`` much above ``s``), the plane where none does. With ``support = 0`` the
    plain ``FGS(w * x) / FGS(w)``, and where no confident pixel reaches, the weighted mean of the frame.
    """
    guide = as_uint8_array(guide_rgb)
    w = weight.astype(np.float32)
    num = cv2.ximgproc.fastGlobalSmootherFilter(guide, (inv_depth * w).astype(np.float32), lam, sigma)
    den = cv2.ximgproc.fastGlobalSmootherFilter(guide, w, lam, sigma)
    if support > 0:
        plane = plane_fit(inv_depth, w)
        # The smoother can ring slightly negative far from its support: clamp before blending.
        num, den = np.maximum(num, 0.0), np.maximum(den, 0.0)
        return ((num + support * plane) / (den + support)).astype(np.float32)
    mean = float((inv_depth * w).sum() / max(w.sum(), 1e-12))
    return np.where(den > 1e-4, num / np.maximum(den, 1e-4), mean).astype(np.float32)


def plane_fit(inv_depth: np.ndarray, weight: np.ndarray, rounds: int = 10, keep: float = 0.8) -> np.ndarray:
    """``[H, W]``: the affine function ``a u + b v + c`` of the pixel coordinates fitted to ``inv_depth``
    [H, W] by weighted least squares (``weight`` [H, W] >= 0), refitted on the ``keep`` share of the weighted
    pixels it fits best until that share stops changing (at most ``rounds`` fits). The inverse depth of a plane
    seen by a pinhole camera is exactly affine in the pixel coordinates, so a wall's fit continues the wall.
    The weighted mean (a constant) where fewer than three pixels have weight or the system is singular."""
    H, W = inv_depth.shape
    w = np.where(np.isfinite(inv_depth), weight, 0.0).astype(np.float64)
    x = np.where(w > 0, inv_depth, 0.0).astype(np.float64)
    total = w.sum()
    mean = float((x * w).sum() / total) if total > 0 else 0.0
    v, u = np.nonzero(w > 0)
    if u.size < 3:
        return np.full((H, W), mean, np.float32)
    # Coordinates centred and scaled to about [-1, 1] for a well-conditioned system.
    su, sv = (u - W / 2) / max(W, 1), (v - H / 2) / max(H, 1)
    A = np.stack([su, sv, np.ones_like(su)], 1)
    b, wi = x[v, u], w[v, u]
    sel = np.ones(u.size, bool)
    coef = None
    for _ in range(max(rounds, 1)):
        Aw = A[sel] * wi[sel, None]
        # einsum, not a BLAS product: its sums run in one fixed order whatever BLAS's threading does, so
        # the fit is the same on any thread (frames are computed on a pool: worldtree.infra.parallel).
        M = np.einsum("ni,nj->ij", A[sel], Aw)
        if np.linalg.cond(M) > 1e12:
            break
        coef = np.linalg.solve(M, np.einsum("ni,n->i", Aw, b[sel]))
        res = np.abs(A[:, 0] * coef[0] + A[:, 1] * coef[1] + A[:, 2] * coef[2] - b)
        new = res <= np.quantile(res, keep)
        if np.array_equal(new, sel):
            break
        sel = new
    if coef is None:
        return np.full((H, W), mean, np.float32)
    vv, uu = np.mgrid[0:H, 0:W]
    return (coef[0] * (uu - W / 2) / max(W, 1) + coef[1] * (vv - H / 2) / max(H, 1) + coef[2]).astype(np.float32)


def frame_depth(
    ref: int,
    images: np.ndarray,
    Ks: np.ndarray,
    w2cs: np.ndarray,
    near: float,
    far: float,
    cfg: DepthConfig,
) -> DepthResult:
    """Depth of training frame ``ref`` from ``images`` [T,H,W,3], ``Ks`` [T,3,3], ``w2cs`` [T,4,4].

    Near/far (scene units, 0 < near < far) bound the hypotheses. Without any usable source frame (e.g. a
    single-camera video) the result is constant ``sqrt(near * far)`` with zero confidence.
    """
    if not (0 < near < far) or not np.isfinite(far):
        raise ValueError(f"plane sweep needs 0 < near < far, got near={near}, far={far}")
    srcs = select_sources(ref, w2cs, cfg, far)
    H, W = images.shape[1:3]
    if not srcs:
        return DepthResult(np.full((H, W), np.sqrt(near * far), np.float32), np.zeros((H, W), np.float32))
    inv_depths = np.linspace(1.0 / far, 1.0 / near, cfg.num_planes)
    volume, std_r = plane_sweep_cost(
        images[ref], [images[s] for s in srcs], Ks[ref], w2cs[ref], [Ks[s] for s in srcs],
        [w2cs[s] for s in srcs], inv_depths, cfg,
    )  # fmt: skip
    inv, c_best = winner_take_all(volume, inv_depths)
    conf = np.clip(1.0 - c_best, 0.0, 1.0)
    conf = np.where(std_r >= cfg.min_texture, conf, 0.0).astype(np.float32)
    good = conf >= cfg.min_conf
    if good.any():
        filled = edge_aware_fill(
            inv, good.astype(np.float32) * conf, images[ref], cfg.fill_lambda, cfg.fill_sigma, cfg.fill_support
        )
        inv = np.where(good, inv, filled)
    else:
        inv = np.full_like(inv, 1.0 / np.sqrt(near * far))
    inv = np.clip(inv, 1.0 / far, 1.0 / near)
    conf = np.where(good, conf, 0.0).astype(np.float32)
    return DepthResult((1.0 / inv).astype(np.float32), conf)


def abs_rel(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean ``|pred - gt| / gt`` over ``mask`` and ``gt > 0``; NaN when no pixel qualifies."""
    sel = gt > 0
    if mask is not None:
        sel &= mask
    if not sel.any():
        return float("nan")
    return float(np.mean(np.abs(pred[sel] - gt[sel]) / gt[sel]))
