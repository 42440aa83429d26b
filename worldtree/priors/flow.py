"""Dense optical flow between frame pairs (OpenCV DIS) with a forward-backward consistency mask.

Flow ``f`` from frame i to frame j maps pixel ``x`` of i to ``x + f(x)`` in j, in pixels, shape ``[H, W, 2]``
(``[..., 0]`` horizontal). A correspondence is kept when the backward flow brings it home:

    |f(x) + b(x + f(x))| < alpha (|f(x)| + |b(x + f(x))|) + beta          (alpha = beta = 0.5 by default)

and ``x + f(x)`` lies inside frame j and, with ``FlowConfig.photo_max``, the colours agree: flow that is
FB-consistent but wrong (typically smoothed across an occlusion edge) lands on another surface.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from worldtree.imageio import as_uint8_array
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
    img = as_uint8_array(img)
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img


def dis_flow(
    gray0: np.ndarray, gray1: np.ndarray, preset: str = "medium", init: np.ndarray | None = None
) -> np.ndarray:
    """DIS optical flow from grey uint8 image 0 to image 1: ``[H, W, 2]`` float32 pixels.

    ``init`` [H,W,2] is an initial flow DIS refines (it starts its coarse-to-fine search from it).
    """
    dis = cv2.DISOpticalFlow_create(_PRESETS[preset])
    start = None if init is None else np.ascontiguousarray(init, dtype=np.float32).copy()
    flow = dis.calc(gray0, gray1, start)
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


def bilinear(img: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Bilinear samples ``[N]`` of a single-channel ``img`` [H,W] at ``pts`` [N,2] (x, y), clamped to the border.

    Plain numpy: cv2.remap limits its maps to 32767 entries per side.
    """
    H, W = img.shape
    x = np.clip(pts[:, 0].astype(np.float64), 0, W - 1)
    y = np.clip(pts[:, 1].astype(np.float64), 0, H - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), W - 2) if W > 1 else np.zeros(len(x), np.int64)
    y0 = np.minimum(np.floor(y).astype(np.int64), H - 2) if H > 1 else np.zeros(len(y), np.int64)
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    fx, fy = x - x0, y - y0
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bot = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def rigid_transfer(
    depth: np.ndarray,
    K_i: np.ndarray,
    w2c_i: np.ndarray,
    K_j: np.ndarray,
    w2c_j: np.ndarray,
    pts: np.ndarray,
    z: np.ndarray | None = None,
) -> np.ndarray:
    """Where static points at pixel positions ``pts`` [N,2] of frame i (depth map ``depth`` [H,W] of frame i,
    sampled bilinearly) project in frame j: ``[N, 2]``. Points that land behind camera j stay in place.
    ``z``, when given, is the depth already sampled at ``pts`` ``[N]``."""
    pts = np.asarray(pts, np.float32).reshape(-1, 2)
    z = bilinear(depth.astype(np.float64), pts) if z is None else np.asarray(z, np.float64)
    Ki, Kj = np.asarray(K_i, np.float64), np.asarray(K_j, np.float64)
    wi, wj = np.asarray(w2c_i, np.float64), np.asarray(w2c_j, np.float64)
    cam = np.stack([(pts[:, 0] - Ki[0, 2]) / Ki[0, 0] * z, (pts[:, 1] - Ki[1, 2]) / Ki[1, 1] * z, z], -1)
    X = (cam - wi[:3, 3]) @ wi[:3, :3]
    Xc = X @ wj[:3, :3].T + wj[:3, 3]
    ok = Xc[:, 2] > 1e-9
    uv = Xc[:, :2] / np.where(ok, Xc[:, 2], 1.0)[:, None] * [Kj[0, 0], Kj[1, 1]] + [Kj[0, 2], Kj[1, 2]]
    return np.where(ok[:, None], uv, pts).astype(np.float32)


def rigid_flow(
    depth: np.ndarray, K_i: np.ndarray, w2c_i: np.ndarray, K_j: np.ndarray, w2c_j: np.ndarray
) -> np.ndarray:
    """Flow ``[H, W, 2]`` from frame i to j if the world were static, given frame i's depth ``[H, W]``."""
    H, W = depth.shape
    py, px = np.mgrid[0:H, 0:W].astype(np.float32)
    pts = np.stack([px.ravel(), py.ravel()], -1)
    # At pixel centres the bilinear sample is the depth itself (weights exactly 1 and 0): skip it.
    z = depth.astype(np.float64).ravel()
    return (rigid_transfer(depth, K_i, w2c_i, K_j, w2c_j, pts, z) - pts).reshape(H, W, 2)


def _normalised_gray(gray: np.ndarray) -> np.ndarray:
    g = cv2.GaussianBlur(gray.astype(np.float32), (5, 5), 1.0)
    return (g - g.mean()) / max(float(g.std()), 1e-6)


def photometric_residual(gray_i: np.ndarray, gray_j: np.ndarray, fwd: np.ndarray) -> np.ndarray:
    """``|I_i(x) - I_j(x + f(x))|`` ``[H, W]`` of the lightly blurred grey images, each normalised to zero mean
    and unit standard deviation over the frame (so a global gain or offset between cameras cancels)."""
    H, W = gray_i.shape
    py, px = np.mgrid[0:H, 0:W].astype(np.float32)
    warped = cv2.remap(
        _normalised_gray(gray_j), px + fwd[..., 0], py + fwd[..., 1], cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )  # fmt: skip
    return np.abs(warped - _normalised_gray(gray_i))


def pair_validity(
    gray_i: np.ndarray, gray_j: np.ndarray, fwd: np.ndarray, bwd: np.ndarray | None, cfg: FlowConfig
):
    """Validity ``[H, W]`` of flow i->j: the FB check (or landing inside when ``bwd`` is None) and, unless
    ``cfg.photo_max`` is None, a photometric residual below ``cfg.photo_max``."""
    valid = fb_consistency(fwd, bwd, cfg.fb_alpha, cfg.fb_beta) if bwd is not None else lands_inside(fwd)
    if cfg.photo_max is not None:
        valid &= photometric_residual(gray_i, gray_j, fwd) < cfg.photo_max
    return valid


def compute_pair(
    gray_i: np.ndarray,
    gray_j: np.ndarray,
    cfg: FlowConfig,
    init_ij: np.ndarray | None = None,
    init_ji: np.ndarray | None = None,
) -> tuple[FlowPair, FlowPair]:
    """Forward (i->j) and backward (j->i) flow with their consistency masks; optional initial flows."""
    f = dis_flow(gray_i, gray_j, cfg.preset, init_ij)
    b = dis_flow(gray_j, gray_i, cfg.preset, init_ji)
    return FlowPair(f, pair_validity(gray_i, gray_j, f, b, cfg)), FlowPair(
        b, pair_validity(gray_j, gray_i, b, f, cfg)
    )


def compute_flows(
    images: np.ndarray,
    cfg: FlowConfig,
    on_pair: Callable[[int, int], None] | None = None,
    depth: np.ndarray | None = None,
    Ks: np.ndarray | None = None,
    w2cs: np.ndarray | None = None,
) -> dict[tuple[int, int], FlowPair]:
    """Flow for every pair of :func:`flow_pairs` over ``images`` [T,H,W,3]; ``on_pair(i, j)`` after each.

    With ``depth`` [T,H,W], ``Ks`` and ``w2cs`` (and ``cfg.init_from_depth``) DIS starts from the rigid flow
    of the static scene, which keeps it on track across wide camera jumps.
    """
    grays = [to_gray_u8(im) for im in images]
    out: dict[tuple[int, int], FlowPair] = {}
    use_init = cfg.init_from_depth and depth is not None and Ks is not None and w2cs is not None
    for i, j in flow_pairs(len(grays), cfg.offsets):
        if (i, j) in out:
            continue
        init_ij = init_ji = None
        if use_init:
            init_ij = rigid_flow(depth[i], Ks[i], w2cs[i], Ks[j], w2cs[j])
            init_ji = rigid_flow(depth[j], Ks[j], w2cs[j], Ks[i], w2cs[i])
        out[(i, j)], out[(j, i)] = compute_pair(grays[i], grays[j], cfg, init_ij, init_ji)
        if on_pair is not None:
            on_pair(i, j)
    return out


def endpoint_error(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean end-point error ``|pred - gt|`` in pixels over ``mask`` (all pixels when None); NaN if empty."""
    e = np.linalg.norm(pred - gt, axis=-1)
    if mask is not None:
        e = e[mask]
    return float(e.mean()) if e.size else float("nan")
