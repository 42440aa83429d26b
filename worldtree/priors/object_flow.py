"""Flow inside the dynamic masks recomputed from each object's displacement (masked template matching).

DIS refines flow coarse to fine with a small search, so it follows the rigid flow it starts from
(:func:`worldtree.priors.flow.compute_flows`) but not an object moving 6-30 px per frame at 160x90
(measured in docs/priors.md, "Object-motion flow inside the masks"). The chained dynamic tracks
(:mod:`worldtree.priors.dynamic_tracks`) then drift or stop after a few frames. For every flow pair (t, u) the
chaining uses:

1. **components**: the mask of frame t, dilated like the chaining's (``track_mask_dilate_px``), is split into
   connected components; those under ``object_min_area_px`` are left alone.
2. **match**: each component's bounding-box patch of the grey frame t, weighted by the component's pixels of
   the undilated mask, is searched in frame u by zero-mean NCC over the masked pixels, within
   ``object_search_px`` per frame of gap around where the rigid flow (or, without metric depth, the current
   flow) puts it, among the positions that put at least ``object_min_inside`` of it inside frame u's dilated
   mask. A best NCC below ``object_min_score``, a flat template or frame-u window (NCC undefined) or a window
   smaller than the patch (object leaving the image) refuses the component: it keeps the old flow.
3. **flow**: DIS runs from the initial flow (rigid flow, the matched displacement inside matched components),
   both directions. DIS medium recovers only half of a 20x20 px object moving 20 px even from the exact start
   (its coarse patches mix object and background), so per pixel of a matched component the constant
   displacement replaces the DIS result where it explains the image better (local photometric residual). The
   forward-backward and photometric checks of :func:`worldtree.priors.flow.pair_validity` then apply.
4. Only the matched components' pixels take the new flow and validity; elsewhere the pair is unchanged.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from worldtree.infra.parallel import ordered_map
from worldtree.priors.config import FlowConfig, MotionConfig
from worldtree.priors.dynamic_tracks import chain_gaps, dilate_masks
from worldtree.priors.flow import (
    FlowPair,
    dis_flow,
    pair_validity,
    photometric_residual,
    rigid_flow,
    to_gray_u8,
)
from worldtree.priors.track_linking import _FLAT

_RESIDUAL_WIN = 5
"""Side (px) of the box over which the photometric residuals of DIS and of the translation are compared: one
pixel's residual is too noisy to choose between two flows."""


@dataclass
class ObjectFlowStats:
    """Counts over all (pair, component) matches of one run (a component is tried once per pair direction)."""

    components: int = 0
    """Components tried (large enough)."""
    matched: int = 0
    """Matched: their pixels took the new flow."""
    refused_flat: int = 0
    """Template (or every window position in frame u) too flat for NCC to mean anything."""
    refused_window: int = 0
    """Search window, clipped to the image, smaller than the template."""
    refused_mask: int = 0
    """No position of the window keeps ``object_min_inside`` of the component inside frame u's mask."""
    refused_score: int = 0
    """Best NCC below ``object_min_score``."""
    pairs_changed: int = 0
    """Directed flow pairs with at least one matched component."""

    def as_dict(self) -> dict[str, int]:
        return {f"object_flow_{k}": int(v) for k, v in asdict(self).items()}


@dataclass
class Match:
    """One component's match: ``displacement`` [2] px (x, y) or None when refused, its NCC, why."""

    displacement: np.ndarray | None
    score: float
    reason: str  # "matched", "flat", "window", "mask" or "score"


def _ccorr(image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """``sum_k image[y + k] kernel[k]`` for every placement of ``kernel`` [h, w] fully inside ``image``."""
    return cv2.matchTemplate(image, kernel, cv2.TM_CCORR)


def _subpixel(score: np.ndarray, y: int, x: int) -> tuple[float, float]:
    """Parabolic refinement ``(dx, dy)`` in [-0.5, 0.5] of the peak ``score[y, x]`` (0 at the border)."""
    out = []
    for a, b, c in (
        (score[y, x - 1], score[y, x], score[y, x + 1]) if 0 < x < score.shape[1] - 1 else (0, 0, 0),
        (score[y - 1, x], score[y, x], score[y + 1, x]) if 0 < y < score.shape[0] - 1 else (0, 0, 0),
    ):
        den = a - 2 * b + c
        ok = np.isfinite(den) and den < -1e-12  # a real maximum
        out.append(float(np.clip(0.5 * (a - c) / den, -0.5, 0.5)) if ok else 0.0)
    return out[0], out[1]


def match_component(
    gray_t: np.ndarray,
    gray_u: np.ndarray,
    template_mask: np.ndarray,
    box: tuple[int, int, int, int],
    predicted: np.ndarray,
    radius: int,
    inside_u: np.ndarray,
    min_score: float,
    min_inside: float,
    min_std: float = _FLAT,
) -> Match:
    """Find where the masked patch of ``gray_t`` goes in ``gray_u`` (both float [H, W] in [0, 1]).

    Args:
        template_mask: ``[h, w]`` bool, the object's pixels inside ``box`` = ``(x, y, w, h)`` of frame t.
        predicted: ``[2]`` predicted displacement (x, y) px; the search covers ``+- radius`` px around it.
        inside_u: ``[H, W]`` bool dilated mask of frame u; a candidate must put ``min_inside`` of the
            template's pixels in it.
        min_score: lowest accepted zero-mean NCC over the masked pixels.
        min_std: templates or frame-u windows whose masked grey standard deviation is below this are flat.

    Returns:
        :class:`Match` (displacement sub-pixel, from a parabola through the NCC peak).
    """
    H, W = gray_u.shape
    x, y, w, h = box
    m = template_mask.astype(np.float32)
    n = float(m.sum())
    tpl = gray_t[y : y + h, x : x + w].astype(np.float32)
    if n < 2:
        return Match(None, float("nan"), "flat")
    tz = (tpl - float((tpl * m).sum()) / n) * m  # zero mean on the mask, zero off it
    t_ss = float((tz * tz).sum())
    if t_ss < n * min_std**2:
        return Match(None, float("nan"), "flat")
    px, py = int(round(x + predicted[0])), int(round(y + predicted[1]))
    x0, y0 = max(0, px - radius), max(0, py - radius)
    x1, y1 = min(W, px + radius + w), min(H, py + radius + h)
    if x1 - x0 < w or y1 - y0 < h:
        return Match(None, float("nan"), "window")
    win = gray_u[y0:y1, x0:x1].astype(np.float32)
    s_it = _ccorr(win, tz)  # sum(tz) = 0: the window's mean cancels from the numerator
    s_i = _ccorr(win, m)
    var = _ccorr(win * win, m) - s_i * s_i / n  # n x masked variance of each window position
    inside = _ccorr(inside_u[y0:y1, x0:x1].astype(np.float32), m) / n
    ok = (var >= n * min_std**2) & (inside >= min_inside - 1e-6)
    if not ok.any():
        return Match(None, float("nan"), "flat" if not (var >= n * min_std**2).any() else "mask")
    score = np.where(ok, s_it / np.sqrt(np.maximum(var, 1e-12) * t_ss), -np.inf)
    by, bx = np.unravel_index(int(np.argmax(score)), score.shape)
    best = float(score[by, bx])
    if not np.isfinite(best) or best < min_score:
        return Match(None, best, "score")
    sx, sy = _subpixel(score, by, bx)
    return Match(np.array([x0 + bx + sx - x, y0 + by + sy - y], np.float32), best, "matched")


def _components(
    inside: np.ndarray, mask: np.ndarray, min_area: int
) -> list[tuple[np.ndarray, tuple, np.ndarray]]:
    """Components of the dilated mask ``inside`` [H, W] with at least ``min_area`` px: ``(pixels [H, W] bool,
    box (x, y, w, h), template mask [h, w] bool)``; the template keeps the undilated ``mask``'s pixels (the
    ring of the dilation is mostly background, which moves otherwise)."""
    n, labels, st, _ = cv2.connectedComponentsWithStats(inside.astype(np.uint8), connectivity=8)
    out = []
    for k in range(1, n):
        x, y, w, h, area = (int(v) for v in st[k])
        if area < max(1, min_area):
            continue
        comp = labels == k
        tm = (comp & mask)[y : y + h, x : x + w]
        out.append((comp, (x, y, w, h), tm if tm.any() else comp[y : y + h, x : x + w]))
    return out


def _prefer_translation(
    gray_i: np.ndarray, gray_j: np.ndarray, dis: np.ndarray, init: np.ndarray, region: np.ndarray
) -> np.ndarray:
    """``dis`` [H, W, 2] with the constant displacements of ``init`` taken on the ``region`` pixels where they
    leave the smaller local photometric residual."""
    if not region.any():
        return dis
    k = (_RESIDUAL_WIN, _RESIDUAL_WIN)
    r_dis = cv2.boxFilter(photometric_residual(gray_i, gray_j, dis), -1, k)
    r_init = cv2.boxFilter(photometric_residual(gray_i, gray_j, init), -1, k)
    take = region & (r_init < r_dis)
    return np.where(take[..., None], init, dis).astype(np.float32)


def object_flows(
    flows: Mapping[tuple[int, int], FlowPair],
    masks: np.ndarray,
    images: np.ndarray,
    cfg: MotionConfig,
    flow_cfg: FlowConfig,
    depth: np.ndarray | None = None,
    Ks: np.ndarray | None = None,
    w2cs: np.ndarray | None = None,
    stats: dict | None = None,
    threads: int = 1,
) -> dict[tuple[int, int], FlowPair]:
    """The flow pairs with the chaining's pairs recomputed inside the masks (see the module docstring).

    Args:
        flows: ``(i, j) -> FlowPair`` (not modified).
        masks: ``[T, H, W]`` bool dynamic masks.
        images: ``[T, H, W, 3]`` frames (float in [0, 1] or uint8).
        cfg: the ``object_*`` fields, ``track_gaps`` and ``track_mask_dilate_px``.
        flow_cfg: DIS preset and the validity checks (as for the flow prior).
        depth: metric depth ``[T, H, W]`` with ``Ks`` [T, 3, 3], ``w2cs`` [T, 4, 4]: the rigid flow starts DIS
            outside the objects and predicts where they go; without it the current flow does both.
        stats: receives :meth:`ObjectFlowStats.as_dict`.
        threads: the chaining's frame pairs computed at once (the same flows and counts for any number).

    Returns:
        A new dict: the same pairs, those of the chaining's gaps changed only on matched components.
    """
    T = len(masks)
    st = ObjectFlowStats()
    out = dict(flows)
    if T == 0 or not masks.any():
        if stats is not None:
            stats.update(st.as_dict())
        return out
    inside = dilate_masks(masks, cfg.track_mask_dilate_px)
    comps = [_components(inside[t], masks[t], cfg.object_min_area_px) for t in range(T)]
    gu8 = [to_gray_u8(im) for im in images]
    grays = [g.astype(np.float32) / 255.0 for g in gu8]
    rigid = depth is not None and Ks is not None and w2cs is not None

    def start(i: int, j: int, st: ObjectFlowStats) -> tuple[np.ndarray, np.ndarray]:
        """Initial flow i -> j [H, W, 2] and the pixels of its matched components [H, W]."""
        if rigid:
            base = rigid_flow(depth[i], Ks[i], w2cs[i], Ks[j], w2cs[j])
        else:
            base = flows[(i, j)].flow.copy()
        init, region = base.copy(), np.zeros(masks.shape[1:], bool)
        for comp, box, tm in comps[i]:
            st.components += 1
            valid = comp if rigid else comp & flows[(i, j)].valid
            pred = np.median(base[valid], 0) if valid.any() else np.zeros(2, np.float32)
            radius = max(1, cfg.object_search_px) * abs(j - i)
            m = match_component(
                grays[i],
                grays[j],
                tm,
                box,
                pred,
                radius,
                inside[j],
                cfg.object_min_score,
                cfg.object_min_inside,
            )
            if m.displacement is None:
                setattr(st, f"refused_{m.reason}", getattr(st, f"refused_{m.reason}") + 1)
                continue
            st.matched += 1
            init[comp] = m.displacement
            region |= comp
        return init, region

    def pair(tu: tuple[int, int]) -> tuple[list[tuple[tuple[int, int], FlowPair]], ObjectFlowStats]:
        """The changed directed pairs of the gap t -> u and the counts of its matches (its own, so that pairs
        can run on several threads)."""
        t, u = tu
        own = ObjectFlowStats()
        init_f, reg_f = start(t, u, own)
        init_b, reg_b = start(u, t, own)
        if not (reg_f.any() or reg_b.any()):
            return [], own
        f = _prefer_translation(
            gu8[t], gu8[u], dis_flow(gu8[t], gu8[u], flow_cfg.preset, init_f), init_f, reg_f
        )
        b = _prefer_translation(
            gu8[u], gu8[t], dis_flow(gu8[u], gu8[t], flow_cfg.preset, init_b), init_b, reg_b
        )
        changed = []
        for (i, j), fwd, bwd, reg in (((t, u), f, b, reg_f), ((u, t), b, f, reg_b)):
            if not reg.any():
                continue
            old = flows[(i, j)]
            valid = pair_validity(gu8[i], gu8[j], fwd, bwd, flow_cfg)
            changed.append(
                (
                    (i, j),
                    FlowPair(
                        np.where(reg[..., None], fwd, old.flow).astype(np.float32),
                        np.where(reg, valid, old.valid),
                    ),
                )
            )
            own.pairs_changed += 1
        return changed, own

    gaps = [
        (t, t + g)
        for t in range(T)
        for g in chain_gaps(cfg)
        if t + g < T and (t, t + g) in flows and (t + g, t) in flows and (comps[t] or comps[t + g])
    ]
    for changed, own in ordered_map(pair, gaps, threads):
        out.update(changed)
        for k, v in asdict(own).items():
            setattr(st, k, getattr(st, k) + v)
    if stats is not None:
        stats.update(st.as_dict())
    return out
