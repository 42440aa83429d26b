"""The stored world frame of a scene: a similarity ``world = s R source + t`` applied to the cameras.

``nvls build`` (SfM) and ``nvls import`` (LLFF files) both put a scene into the *rig* frame when asked: origin
at the mean camera centre, axes of the mean camera, and the median scene depth 1. Every absolute constant of
the methods (motion-regulariser weights against the data terms, node spacing, learning rates) is then used
at the scale the generated scenes have, whatever units the source used (LLFF captures come in arbitrary ones;
Balloon1's median depth is about 50).
"""

from __future__ import annotations

import numpy as np


def rig_similarity(w2cs: np.ndarray, depths: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, R [3, 3], t [3])`` of ``world = s R source + t`` putting the mean camera at the origin with
    identity axes and the median of ``depths`` (source units, any shape; non-finite/non-positive ignored)
    at 1. ``w2cs`` [N, 4, 4] world-to-camera poses in the source frame."""
    M = np.mean(w2cs[:, :3, :3], axis=0)
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    centres = np.stack([-w[:3, :3].T @ w[:3, 3] for w in w2cs])
    d = np.asarray(depths, np.float64).ravel()
    d = d[np.isfinite(d) & (d > 0)]
    med = float(np.median(d)) if d.size else 1.0
    s = 1.0 / med if np.isfinite(med) and med > 1e-12 else 1.0
    t = -s * R @ centres.mean(axis=0)
    return s, R, t


def apply_similarity(w2cs: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World-to-camera poses ``[N, 4, 4]`` after ``x' = s R x + t`` (camera frames scale with the world:
    a point's camera coordinates are multiplied by ``s``)."""
    out = np.tile(np.eye(4), (len(w2cs), 1, 1))
    for i, w in enumerate(w2cs):
        Ri = w[:3, :3] @ R.T
        out[i, :3, :3] = Ri
        out[i, :3, 3] = s * w[:3, 3] - Ri @ t
    return out
