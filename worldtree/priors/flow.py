"""Dense optical flow between frame pairs (OpenCV DIS) with a forward-backward consistency mask.

Flow ``f`` from frame i to frame j maps pixel ``x`` of i to ``x + f(x)`` in j, in pixels, shape ``[H, W, 2]``
(``[..., 0]`` horizontal). A correspondence is kept when the backward flow brings it home:

    |f(x) + b(x + f(x))| < alpha (|f(x)| + |b(x + f(x))|) + beta          (alpha = beta = 0.5 by default)

and ``x + f(x)`` lies inside frame j.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from worldtree.priors.config import FlowConfig

_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


@dataclass
class FlowPair:
    """Flow from frame ``i`` to frame ``j``: ``flow`` [H,W,2] float32 pixels, ``valid`` [H,W] bool."""

    flow: np.ndarray
    valid: np.ndarray


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """RGB float [H,W,3] in [0,1] or uint8 -> grey uint8 [H,W]."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img


def dis_flow(gray0: np.ndarray, gray1: np.ndarray, preset: str = "medium") -> np.ndarray:
    """DIS optical flow from grey uint8 image 0 to image 1: ``[H, W, 2]`` float32 pixels."""
    dis = cv2.DISOpticalFlow_create(_PRESETS[preset])
    flow = dis.calc(gray0, gray1, None)
    # DIS can emit non-finite values on flat borders; a zero vector is then flagged by the FB check.
    return np.nan_to_num(flow, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)


def sample_flow(flow: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Bilinearly sample ``flow`` [H,W,2] at positions ``at`` [...,2] (x, y); outside -> replicated border."""
    mx = np.ascontiguousarray(at[..., 0], dtype=np.float32)
    my = np.ascontiguousarray(at[..., 1], dtype=np.float32)
    return cv2.remap(flow, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def fb_consistency(fwd: np.ndarray, bwd: np.ndarray, alpha: float = 0.5, beta: float = 0.5) -> np.ndarray:
    """Forward-backward check of ``fwd`` (i->j) against ``bwd`` (j->i): bool ``[H, W]`` (see module doc)."""
    H, W = fwd.shape[:2]
    py, px = np.mgrid[0:H, 0:W].astype(np.float32)
    tx, ty = px + fwd[..., 0], py + fwd[..., 1]
    b = sample_flow(bwd, np.stack([tx, ty], -1))
    err = np.linalg.norm(fwd + b, axis=-1)
    bound = alpha * (np.linalg.norm(fwd, axis=-1) + np.linalg.norm(b, axis=-1)) + beta
    inside = (tx >= 0) & (tx <= W - 1) & (ty >= 0) & (ty <= H - 1)
    return (err < bound) & inside


def lands_inside(fwd: np.ndarray) -> np.ndarray:
    """Bool ``[H, W]``: ``x + f(x)`` falls inside the image."""
    H, W = fwd.shape[:2]
    py, px = np.mgrid[0:H, 0:W].astype(np.float32)
    tx, ty = px + fwd[..., 0], py + fwd[..., 1]
    return (tx >= 0) & (tx <= W - 1) & (ty >= 0) & (ty <= H - 1)


def flow_pairs(num_frames: int, offsets: Iterable[int]) -> list[tuple[int, int]]:
    """Ordered pairs (i, j), both directions, for every i and gap k in ``offsets`` with j = i + k < T."""
    pairs: list[tuple[int, int]] = []
    for k in sorted({int(k) for k in offsets if int(k) > 0}):
        for i in range(num_frames - k):
            pairs += [(i, i + k), (i + k, i)]
    return pairs


def compute_pair(gray_i: np.ndarray, gray_j: np.ndarray, cfg: FlowConfig) -> tuple[FlowPair, FlowPair]:
    """Forward (i->j) and backward (j->i) flow with their consistency masks."""
    f = dis_flow(gray_i, gray_j, cfg.preset)
    b = dis_flow(gray_j, gray_i, cfg.preset)
    return (
        FlowPair(f, fb_consistency(f, b, cfg.fb_alpha, cfg.fb_beta)),
        FlowPair(b, fb_consistency(b, f, cfg.fb_alpha, cfg.fb_beta)),
    )


def compute_flows(
    images: np.ndarray,
    cfg: FlowConfig,
    on_pair: Callable[[int, int], None] | None = None,
) -> dict[tuple[int, int], FlowPair]:
    """Flow for every pair of :func:`flow_pairs` over ``images`` [T,H,W,3]; ``on_pair(i, j)`` after each."""
    grays = [to_gray_u8(im) for im in images]
    out: dict[tuple[int, int], FlowPair] = {}
    for i, j in flow_pairs(len(grays), cfg.offsets):
        if (i, j) in out:
            continue
        out[(i, j)], out[(j, i)] = compute_pair(grays[i], grays[j], cfg)
        if on_pair is not None:
            on_pair(i, j)
    return out


def endpoint_error(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean end-point error ``|pred - gt|`` in pixels over ``mask`` (all pixels when None); NaN if empty."""
    e = np.linalg.norm(pred - gt, axis=-1)
    if mask is not None:
        e = e[mask]
    return float(e.mean()) if e.size else float("nan")
