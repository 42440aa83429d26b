"""A moving object's depth from its outline: image size and one smooth path (issue #28).

Rule: where a mask outlines each moving object (an imported segmentation: the classical masks cut objects
into parts, docs/base_method.md), a piece of the mask that stays one object from frame to frame gives

- **size constancy**: its area falls as its depth squared, so ``q_t = 1 / sqrt(area_t)`` is the depth of its
  centre up to one factor;
- **one smooth path**: the factor ``s`` that makes the centre path ``c_t + s q_t r_t`` smoothest
  (:func:`worldtree.motion.track_depth.trajectory_scale`), which the cameras' own acceleration measures.

An object is placed only where its path fit (the share of the cameras' acceleration the scaled rays cancel)
is at least ``min_fit``; the cue fails, with a low fit, where the object turns faster than the cameras.
Elsewhere the depth prior is left as it was. Frames where the piece touches the border or has merged with another are not used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from worldtree.motion.track_depth import trajectory_scale

__all__ = ["ObjectChain", "ObjectDepthConfig", "link_pieces", "mask_pieces", "object_depths"]


@dataclass
class ObjectDepthConfig:
    """Settings of :func:`object_depths` (used by Base with imported masks and the classical depth)."""

    enabled: bool = True
    """Place outlined moving objects by their size and path (only with imported masks; see the module)."""
    min_frames: int = 5
    """Frames an object must be one whole piece in before its path is solved."""
    min_fit: float = 0.9
    """The path fit an object needs to be placed (1: a smooth path exists). On generated scenes the fit was
    0.99 or more for every object placed within 2 % of its depth with exact cameras, 0.96 for the same
    objects with the bundle-adjusted ones (their depth still within 1.5 %), 0.95 for an object placed 13 % too
    near (a turning box, whose outline changes) and 0.84 or less for every object off by 16 % or more."""
    min_area: int = 6
    """Pieces under this many pixels are noise, not an object."""
    max_jump: float = 0.15
    """Largest centroid move between linked pieces, as a fraction of the image diagonal."""
    max_area_ratio: float = 1.5
    """Largest area change per frame between linked pieces (a larger one is a merge or a split)."""
    max_gap: int = 8
    """Frames a chain may miss (merged with another object, out of view) and still be continued."""

    def __post_init__(self) -> None:
        if self.min_frames < 3:
            raise ValueError(f"ObjectDepthConfig: min_frames must be >= 3 (a path needs 3), got {self.min_frames}")
        if not 0.0 <= self.min_fit <= 1.0:
            raise ValueError(f"ObjectDepthConfig: min_fit must be in [0, 1], got {self.min_fit}")
        if not self.max_area_ratio >= 1.0 or not self.max_jump > 0.0 or self.max_gap < 1:
            raise ValueError("ObjectDepthConfig: max_area_ratio must be >= 1, max_jump > 0 and max_gap >= 1")


@dataclass
class Piece:
    """One connected piece of one frame's mask."""

    label: int
    centroid: np.ndarray  # [2] px (u, v)
    area: float  # px
    border: bool  # touches the image border


@dataclass
class ObjectChain:
    """One object followed through frames: its pieces, frame by frame (``frames`` strictly increasing)."""

    frames: list[int] = field(default_factory=list)
    pieces: list[Piece] = field(default_factory=list)


def mask_pieces(mask: np.ndarray, min_area: int) -> tuple[np.ndarray, list[Piece]]:
    """The 8-connected pieces of ``mask`` ``[H, W]`` bool with at least ``min_area`` pixels: the label image
    ``[H, W]`` int32 and one :class:`Piece` per kept label."""
    H, W = mask.shape
    n, lab, st, cen = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    out = []
    for k in range(1, n):
        x, y, w, h, area = (int(a) for a in st[k])
        if area < min_area:
            continue
        out.append(Piece(k, cen[k].astype(np.float64), float(area), x == 0 or y == 0 or x + w == W or y + h == H))
    return lab.astype(np.int32), out


def link_pieces(pieces: list[list[Piece]], diag: float, cfg: ObjectDepthConfig) -> list[ObjectChain]:
    """Chains of pieces over frames (``pieces[t]``: frame ``t``'s pieces; ``diag`` the image diagonal, px).

    A chain last seen ``g`` frames back (``g <= max_gap``) may take a piece within ``g * max_jump * diag``
    pixels whose area is within ``max_area_ratio ** g`` of its last one; pairs are taken cheapest first (cost:
    the distance over that reach plus ``|log|`` of the area ratio), one piece per chain and one chain per piece.
    A merge (two objects drawn as one outline) is a piece that is the nearest piece of two chains seen in the
    frame before, or the nearest piece of the frame before's merge while no second piece is near that merge
    (then it has parted): no chain takes it and it starts none, so
    the objects' chains resume when they part. Any other unmatched piece starts a chain.
    """
    chains: list[ObjectChain] = []
    reach = cfg.max_jump * diag
    merged_before: list[Piece] = []
    for t, frame in enumerate(pieces):
        live = [c for c in chains if t - c.frames[-1] <= cfg.max_gap]
        merged: set[int] = set()
        if frame:
            claims: dict[int, int] = {}
            sources = [(c.pieces[-1], False) for c in live if c.frames[-1] == t - 1]
            sources += [(p, True) for p in merged_before]
            for last, was_merged in sources:
                d = [float(np.linalg.norm(p.centroid - last.centroid)) for p in frame]
                i = int(np.argmin(d))
                if was_merged and sum(x <= reach for x in d) > 1:
                    continue  # the merge has parted into pieces near it
                if d[i] <= reach:
                    claims[i] = claims.get(i, 0) + (2 if was_merged else 1)
            merged = {i for i, n in claims.items() if n > 1}
        pairs = []
        for i, p in enumerate(frame):
            if i in merged:
                continue
            for j, c in enumerate(live):
                last, gap = c.pieces[-1], t - c.frames[-1]
                d = float(np.linalg.norm(p.centroid - last.centroid))
                ratio = max(p.area, last.area) / max(min(p.area, last.area), 1.0)
                if d <= reach * gap and ratio <= cfg.max_area_ratio**gap:
                    pairs.append((d / (reach * gap) + math.log(ratio), i, j))
        used_p, used_c = set(), set()
        for _, i, j in sorted(pairs):
            if i in used_p or j in used_c:
                continue
            used_p.add(i)
            used_c.add(j)
            live[j].frames.append(t)
            live[j].pieces.append(frame[i])
        for i, p in enumerate(frame):
            if i not in used_p and i not in merged:
                chains.append(ObjectChain([t], [p]))
        merged_before = [frame[i] for i in sorted(merged)]
    return chains


def _sphere_front(
    lab: np.ndarray, piece: Piece, z_centre: float, f: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels ``(rows, cols)`` of ``piece`` and their depth on the front of a ball of the piece's area whose
    centre is at camera depth ``z_centre`` (``f`` the focal length in pixels): ``z_c - sqrt(R^2 - rho^2)``."""
    rows, cols = np.nonzero(lab == piece.label)
    radius_px = math.sqrt(piece.area / math.pi)
    rho2 = (cols - piece.centroid[0]) ** 2 + (rows - piece.centroid[1]) ** 2
    cap = np.sqrt(np.maximum(radius_px * radius_px - rho2, 0.0))
    return rows, cols, z_centre - cap * z_centre / f


def object_depths(
    masks: torch.Tensor, Ks: torch.Tensor, w2cs: torch.Tensor, cfg: ObjectDepthConfig
) -> tuple[torch.Tensor, list[dict]]:
    """Depth of the outlined moving objects that size and path place (module docstring).

    Args:
        masks: ``[T, H, W]`` bool, the moving objects' outlines per training frame.
        Ks: ``[T, 3, 3]`` intrinsics at the masks' size (pixels). w2cs: ``[T, 4, 4]`` OpenCV world-to-camera.

    Returns:
        ``(depth, objects)``: ``depth`` ``[T, H, W]`` float32 on the masks' device, camera z in the cameras'
        units on the pixels of placed objects' whole pieces and 0 elsewhere; ``objects`` one record per chain
        with at least ``min_frames`` whole pieces (``frames``, ``fit``, ``scale``, ``placed``).
    """
    T, H, W = masks.shape
    m = masks.detach().bool().cpu().numpy()
    labs, pieces = [], []
    for t in range(T):
        lab, ps = mask_pieces(m[t], cfg.min_area)
        labs.append(lab)
        pieces.append(ps)
    chains = link_pieces(pieces, math.hypot(H, W), cfg)
    depth = np.zeros((T, H, W), np.float32)
    Kd, Wd = Ks.detach().double().cpu(), w2cs.detach().double().cpu()
    records = []
    for ch in chains:
        keep = [(t, p) for t, p in zip(ch.frames, ch.pieces, strict=True) if not p.border]
        if len(keep) < cfg.min_frames:
            continue
        frames = torch.tensor([t for t, _ in keep])
        px = torch.tensor(np.stack([p.centroid for _, p in keep]))
        q = torch.tensor([1.0 / math.sqrt(max(p.area, 1.0)) for _, p in keep], dtype=torch.float64)
        s, fit = trajectory_scale(frames, px, q, Kd, Wd)
        placed = bool(math.isfinite(s) and s > 0 and fit >= cfg.min_fit)
        records.append({"frames": len(keep), "fit": float(fit), "scale": float(s), "placed": placed})
        if not placed:
            continue
        for (t, p), qt in zip(keep, q.tolist(), strict=True):
            f = float(Kd[t, 0, 0] + Kd[t, 1, 1]) / 2.0
            rows, cols, z = _sphere_front(labs[t], p, s * qt, f)
            depth[t, rows, cols] = np.maximum(z, 1e-6)
    return torch.from_numpy(depth).to(masks.device), records
