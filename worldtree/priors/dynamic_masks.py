"""Per-frame dynamic masks with a confidence, fused from the motion cues of :mod:`worldtree.priors.motion_cues`.

Fusion is a noisy-OR of the cues' evidence maps, ``p = 1 - prod_k (1 - e_k)`` (any cue that is sure decides;
weak cues that agree add up), followed by the temporal agreement over neighbouring frames. The confidence is
that fused value; a pixel is dynamic when it exceeds ``MotionConfig.threshold``. The mask is then cleaned:
closing (joins the parts of one object that the cues found separately), opening by ``EpiConfig.open_px``,
regions under ``EpiConfig.min_area_frac`` dropped, and a final dilation (object borders).

Two moments use it (``worldtree.priors.api`` and the Base method):

1. with the priors, from the epipolar and depth-consistency cues (no model exists yet);
2. after the static warm-up, again with the residual of the warm-up model on every training frame added
   (:func:`refine_with_residual`): what a static scene cannot explain is dynamic.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from worldtree.priors import motion_cues as cues
from worldtree.priors.config import EpiConfig, MotionConfig
from worldtree.priors.flow import FlowPair


@dataclass
class DynamicMasks:
    """``mask`` ``[T, H, W]`` bool, ``confidence`` ``[T, H, W]`` float32 in [0, 1], and the cues' evidence
    (``{name: [T, H, W]}``) they were fused from."""

    mask: np.ndarray
    confidence: np.ndarray
    evidence: dict[str, np.ndarray]


def noisy_or(maps: list[np.ndarray]) -> np.ndarray:
    """``1 - prod_k (1 - m_k)`` of evidence maps in [0, 1] (all the same shape); zeros when ``maps`` is empty."""
    if not maps:
        raise ValueError("noisy_or needs at least one map")
    keep = np.ones_like(maps[0], dtype=np.float32)
    for m in maps:
        keep *= 1.0 - np.clip(m, 0.0, 1.0)
    return 1.0 - keep


def _disk(r: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def clean_mask(mask: np.ndarray, motion: MotionConfig, epi: EpiConfig) -> np.ndarray:
    """Closing, opening, small-region removal and dilation of one frame's mask ``[H, W]`` bool."""
    m = mask.astype(np.uint8)
    if motion.close_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, _disk(motion.close_px))
    if epi.open_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, _disk(epi.open_px))
    if epi.min_area_frac > 0 and m.any():
        min_area = epi.min_area_frac * m.shape[0] * m.shape[1]
        n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
        small = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] < min_area)
        small = small[small > 0]
        if small.size:
            m[np.isin(lab, small)] = 0
    if motion.dilate_px > 0 and m.any():
        m = cv2.dilate(m, _disk(motion.dilate_px))
    return m > 0


def fuse(
    evidence: dict[str, np.ndarray],
    flows: Mapping[tuple[int, int], FlowPair],
    motion: MotionConfig,
    epi: EpiConfig,
) -> DynamicMasks:
    """Fuse evidence maps ``{name: [T, H, W]}`` into :class:`DynamicMasks` (see the module docstring)."""
    p = noisy_or(list(evidence.values()))
    conf = cues.temporal_agreement(p, flows, motion.temporal_self_weight)
    raw = conf > motion.threshold
    mask = np.stack([clean_mask(m, motion, epi) for m in raw]) if len(raw) else raw
    return DynamicMasks(mask, conf.astype(np.float32), evidence)


def prior_evidence(
    epi_error: np.ndarray,
    flows: Mapping[tuple[int, int], FlowPair],
    depth: np.ndarray | None,
    Ks: np.ndarray,
    w2cs: np.ndarray,
    motion: MotionConfig,
    epi: EpiConfig,
    threads: int = 1,
) -> dict[str, np.ndarray]:
    """Evidence of the cues available with the priors: ``epipolar`` (from ``epi_error`` [T, H, W] px) and, when
    ``depth`` [T, H, W] is metric and the poses are used, ``rigid`` (depth consistency of the flow, its flow
    pairs computed on ``threads`` threads)."""
    ev: dict[str, np.ndarray] = {}
    if motion.use_epipolar:
        ev["epipolar"] = cues.epipolar_evidence(epi_error, epi.threshold_px)
    # Without trusted poses (``epi.use_poses`` false, e.g. a frames-only clip with identity poses) the rigid
    # flow means nothing.
    if motion.use_rigid and depth is not None and epi.use_poses:
        ev["rigid"] = cues.rigid_evidence_maps(
            flows, depth, Ks, w2cs, motion.rigid_tol_px, motion.rigid_rel_depth, threads=threads
        )
    if not ev:
        ev["none"] = np.zeros_like(epi_error, dtype=np.float32)
    return ev


def residual_evidence_maps(
    images: np.ndarray, renders: np.ndarray, static_hint: np.ndarray | None, motion: MotionConfig
) -> np.ndarray:
    """``[T, H, W]`` residual evidence of the static model: ``images`` and ``renders`` ``[T, H, W, 3]`` in
    [0, 1]; ``static_hint`` ``[T, H, W]`` bool (pixels believed static, for the noise statistics) or None."""
    out = np.zeros(images.shape[:3], np.float32)
    for t in range(len(images)):
        r = cues.residual_map(images[t], renders[t])
        w = None if static_hint is None else (~static_hint[t]).astype(np.float32)
        out[t] = cues.residual_evidence(
            r, motion.residual_z_low, motion.residual_z_high, motion.residual_floor, w
        )
    return out


def refine_with_residual(
    evidence: dict[str, np.ndarray],
    images: np.ndarray,
    renders: np.ndarray,
    flows: Mapping[tuple[int, int], FlowPair],
    previous_mask: np.ndarray | None,
    motion: MotionConfig,
    epi: EpiConfig,
) -> DynamicMasks:
    """Masks from the prior cues ``evidence`` plus the static model's residual (``renders`` of the warm-up
    model at every training frame, ``[T, H, W, 3]``); ``previous_mask`` [T, H, W] (the masks the warm-up
    excluded) sets aside the pixels whose residual noise is not static noise."""
    ev = dict(evidence)
    ev["residual"] = residual_evidence_maps(images, renders, previous_mask, motion)
    return fuse(ev, flows, motion, epi)
