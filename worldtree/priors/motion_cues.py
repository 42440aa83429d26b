"""Per-frame evidence that a pixel moves, from the cues the pipeline already has (no network).

Every cue maps a frame to an *evidence* map ``[H, W]`` in [0, 1] (0 = explained by a static world, 1 = surely
moving; a linear ramp between a ``low`` and a ``high`` level of the cue's own measure):

- **residual** (:func:`residual_evidence`): what a static model of the scene fails to render. The static
  warm-up model is fitted to every training frame at once; a moving object cannot be explained by it and
  leaves a residual in every frame where it is not at its average position. Measured as the blurred mean
  absolute colour difference, in robust units of the frame's own residual noise (median + MAD), and above an
  absolute floor so a well-fitted static scene gives no evidence at all.
- **epipolar** (:func:`epipolar_evidence`): the Sampson distance of the flow to the epipolar geometry of the
  known poses (``worldtree.priors.epipolar``); blind to motion along the epipolar lines.
- **depth consistency** (:func:`rigid_evidence`): where the depth prior and the poses say a static pixel must
  land in the other frame (the rigid flow) against where the flow says it went. Along the epipolar line
  this is exactly the disagreement of the depth triangulated by the flow with the depth prior, so it sees the
  motion the epipolar test cannot; the tolerance grows with the translational parallax, because a relative
  depth error ``e`` moves the prediction by ``e`` times the parallax.
- **temporal agreement** (:func:`temporal_agreement`): a moving object keeps moving, noise flickers. The
  fused evidence of the neighbouring frames is carried into frame t along the flow and averaged with frame
  t's own.

:mod:`worldtree.priors.dynamic_masks` fuses them into masks with a confidence.
"""

from __future__ import annotations

from collections.abc import Mapping

import cv2
import numpy as np

from worldtree.infra.parallel import ordered_map
from worldtree.priors.flow import FlowPair, rigid_flow

_EPS = 1e-9


def ramp(x: np.ndarray, low: float, high: float) -> np.ndarray:
    """``clip((x - low) / (high - low), 0, 1)`` as float32 (``high > low``)."""
    return np.clip((np.asarray(x, np.float64) - low) / max(high - low, _EPS), 0.0, 1.0).astype(np.float32)


def _blur(x: np.ndarray, sigma: float) -> np.ndarray:
    if sigma <= 0:
        return x.astype(np.float32)
    return cv2.GaussianBlur(x.astype(np.float32), (0, 0), sigma)


def _unit(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    return a.astype(np.float32) / np.float32(255.0) if a.dtype == np.uint8 else np.asarray(a, np.float32)


def residual_map(image: np.ndarray, render: np.ndarray, blur_px: float = 1.0) -> np.ndarray:
    """Mean absolute colour difference ``[H, W]`` (image units) of ``image`` and ``render`` ``[H, W, 3]`` in
    [0, 1] (either may be ``uint8``, read as ``v / 255``: frames are held as read, one converted at a time),
    Gaussian-blurred by ``blur_px`` (a single noisy pixel is not an object)."""
    d = np.abs(_unit(image) - _unit(render)).mean(-1)
    return _blur(d, blur_px)


def residual_evidence(
    residual: np.ndarray,
    z_low: float = 3.0,
    z_high: float = 6.0,
    floor: float = 0.04,
    weight: np.ndarray | None = None,
) -> np.ndarray:
    """Evidence ``[H, W]`` from one frame's static-model residual ``[H, W]`` (image units).

    ``z = (r - median) / (1.4826 MAD)`` over the pixels with ``weight > 0.5`` (all when None: use the
    static-labelled pixels so that a large moving object does not inflate its own noise estimate); evidence
    ramps from ``z_low`` to ``z_high``, and is 0 wherever ``r < floor`` (a static scene rendered within
    ``floor`` has no moving pixel, whatever its noise statistics say).
    """
    r = np.asarray(residual, np.float32)
    ref = r[weight > 0.5] if weight is not None and (weight > 0.5).sum() >= 16 else r.ravel()
    med = float(np.median(ref))
    mad = 1.4826 * float(np.median(np.abs(ref - med)))
    z = (r - med) / max(mad, 1e-3)
    ev = ramp(z, z_low, z_high)
    # The absolute floor ramps in over half its value so that the evidence stays continuous.
    return ev * ramp(r, 0.5 * floor, floor)


def epipolar_evidence(error: np.ndarray, threshold_px: float) -> np.ndarray:
    """Evidence ``[H, W]`` from an epipolar error map (pixels): 0 below half the EPI threshold, 1 from 1.5x."""
    return ramp(error, 0.5 * threshold_px, 1.5 * threshold_px)


def rigid_residual(
    flow_ij: FlowPair,
    depth_i: np.ndarray,
    K_i: np.ndarray,
    w2c_i: np.ndarray,
    K_j: np.ndarray,
    w2c_j: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """``(residual [H, W] px, parallax [H, W] px)`` of the flow i -> j against the rigid flow of depth ``depth_i``.

    ``residual = |f(x) - rigid(x)|``; ``parallax = |rigid(x) - rotation-only(x)|``, the part of the rigid flow
    that depends on depth (the scale of the prediction's error for a given relative depth error). Invalid
    flow pixels get residual 0.
    """
    rig = rigid_flow(depth_i, K_i, w2c_i, K_j, w2c_j)
    # Depth at infinity gives the rotation-only flow.
    far = rigid_flow(np.full_like(depth_i, 1e9, dtype=np.float64), K_i, w2c_i, K_j, w2c_j)
    res = np.linalg.norm(flow_ij.flow - rig, axis=-1)
    par = np.linalg.norm(rig - far, axis=-1)
    return np.where(flow_ij.valid, res, 0.0).astype(np.float32), par.astype(np.float32)


def rigid_evidence(
    residual: np.ndarray, parallax: np.ndarray, tol_px: float = 1.5, rel_depth_tol: float = 0.3
) -> np.ndarray:
    """Evidence ``[H, W]`` of a rigid-flow residual: ramps from ``tol`` to ``2 tol`` with
    ``tol = tol_px + rel_depth_tol * parallax`` (pixels)."""
    tol = tol_px + rel_depth_tol * np.asarray(parallax, np.float32)
    return ramp(residual / np.maximum(tol, _EPS), 1.0, 2.0)


def rigid_evidence_maps(
    flows: Mapping[tuple[int, int], FlowPair],
    depth: np.ndarray,
    Ks: np.ndarray,
    w2cs: np.ndarray,
    tol_px: float = 1.5,
    rel_depth_tol: float = 0.3,
    max_pair_median: float = 0.5,
    threads: int = 1,
) -> np.ndarray:
    """``[T, H, W]`` depth-consistency evidence of every frame: the maximum of :func:`rigid_evidence` over the
    flow pairs leaving it. A pair whose median evidence over valid pixels exceeds ``max_pair_median`` is a
    failed flow (or depth) and is skipped, as the epipolar test does. Pairs are computed on ``threads``
    threads (the same maps for any count)."""
    T, H, W = depth.shape
    out = np.zeros((T, H, W), np.float32)
    pairs = list(flows.items())

    def one(item: tuple[tuple[int, int], FlowPair]) -> np.ndarray | None:
        (i, j), fp = item
        res, par = rigid_residual(fp, depth[i], Ks[i], w2cs[i], Ks[j], w2cs[j])
        ev = rigid_evidence(res, par, tol_px, rel_depth_tol)
        ok = fp.valid
        if ok.any() and float(np.median(ev[ok])) > max_pair_median:
            return None
        return np.where(ok, ev, 0.0)

    for ((i, _), _), ev in zip(pairs, ordered_map(one, pairs, threads), strict=True):
        if ev is not None:
            out[i] = np.maximum(out[i], ev)
    return out


def warp_to(values_j: np.ndarray, flow_ij: FlowPair) -> tuple[np.ndarray, np.ndarray]:
    """``values_j`` ``[H, W]`` of frame j read at ``x + f(x)`` for every pixel x of frame i: ``(values [H, W],
    valid [H, W])`` (valid = the flow is valid there)."""
    H, W = values_j.shape
    py, px = np.mgrid[0:H, 0:W].astype(np.float32)
    v = cv2.remap(
        values_j.astype(np.float32), px + flow_ij.flow[..., 0], py + flow_ij.flow[..., 1], cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )  # fmt: skip
    return v, flow_ij.valid


def temporal_agreement(
    evidence: np.ndarray, flows: Mapping[tuple[int, int], FlowPair], self_weight: float = 0.5
) -> np.ndarray:
    """``[T, H, W]``: each frame's evidence averaged with its neighbours' (t-1 and t+1, carried along the flow).

    ``out_t = self_weight * e_t + (1 - self_weight) * mean_n e_n(x + f_tn(x))`` over the neighbours with a
    valid flow at x; where none has, ``out_t = e_t``. A detection seen in one frame only is halved; one that
    the neighbours confirm is kept.
    """
    T = evidence.shape[0]
    out = evidence.astype(np.float32).copy()
    for t in range(T):
        acc = np.zeros_like(out[t])
        cnt = np.zeros_like(out[t])
        for n in (t - 1, t + 1):
            if 0 <= n < T and (t, n) in flows:
                v, ok = warp_to(evidence[n], flows[(t, n)])
                acc += np.where(ok, v, 0.0)
                cnt += ok
        have = cnt > 0
        mean = acc / np.maximum(cnt, 1.0)
        out[t] = np.where(have, self_weight * evidence[t] + (1.0 - self_weight) * mean, evidence[t])
    return out
