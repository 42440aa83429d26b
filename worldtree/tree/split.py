"""Where a TPT node is split: ``binary`` (default), ``gradient`` and ``flow`` (paper appendix).

All strategies return the global frame ``P`` that starts the right child (children ``[L, P-1]`` and ``[P, R]``)
and keep it in the allowed range ``[L + c, R + 1 - c]``, ``c = min_child_len(min_len)`` (5 frames for the
default ``min_len = 12``; :mod:`worldtree.tree.tpt` explains the rule). They are called only for nodes with
``>= min_len`` frames.

- ``binary``: ``P = (L + R) // 2`` (the paper's rule; always inside the allowed range).
- ``gradient`` / ``flow``: *balanced* split of a non-negative per-frame profile ``w`` over the node's frames
  (``w[k]`` belongs to global frame ``L + k``): ``P`` minimises ``|S(P) - (W - S(P))|`` with ``S(P)`` the sum of
  ``w`` over ``[L, P-1]`` and ``W`` the total, i.e. the point where the cumulative profile reaches half its
  total, rounded to the nearer frame boundary; ties go to the point nearest the binary one, then the smaller.
  ``gradient`` uses the position gradients accumulated per frame while the node trained
  (:class:`ProfileAccumulator`); ``flow`` the mean optical-flow magnitude of the dynamic pixels
  (:func:`flow_profile`).

Degenerate profiles fall back to ``binary`` (the reason is returned in :class:`SplitChoice`):
a non-finite or negative entry; an all-zero profile; a profile where every split point is equally unbalanced
(all the mass in one frame, e.g. one spike at an end); or a balance point outside the allowed range (the mass
sits so close to one end that no split respecting the minimum child length can balance it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from worldtree.tree.tpt import (
    DEFAULT_MIN_LEN,
    Interval,
    TemporalPartitionTree,
    binary_point,
    can_split,
    split_range,
)

__all__ = [
    "SPLIT_STRATEGIES",
    "ProfileAccumulator",
    "SplitChoice",
    "balanced_split",
    "binary_split",
    "choose_split",
    "flow_profile",
]

SPLIT_STRATEGIES = ("binary", "gradient", "flow")


@dataclass(frozen=True)
class SplitChoice:
    """A split decision: ``point`` P (global frame), the strategy used and why it fell back, if it did."""

    point: int
    """Global frame that starts the right child."""
    strategy: str
    """Strategy asked for."""
    fallback: str | None = None
    """None when the strategy's own point was used; otherwise why ``binary`` was used instead."""


def _allowed(iv: Interval, min_len: int) -> tuple[int, int]:
    if not can_split(iv.length, min_len):
        raise ValueError(f"interval {iv} has {iv.length} frames; nodes under {max(min_len, 2)} are not split")
    return split_range(iv.start, iv.end, min_len)


def binary_split(iv: Interval, min_len: int = DEFAULT_MIN_LEN) -> int:
    """``(L + R) // 2`` for an interval of ``>= min_len`` frames (children of ``floor((n-1)/2)`` and
    ``ceil((n+1)/2)`` frames, both ``>= min_child_len``; the clamp into the allowed range only guards)."""
    lo, hi = _allowed(iv, min_len)
    return int(min(max(binary_point(iv.start, iv.end), lo), hi))


def _as_profile(profile: np.ndarray | torch.Tensor, n: int) -> np.ndarray:
    if isinstance(profile, torch.Tensor):
        profile = profile.detach().cpu().double().numpy()
    w = np.asarray(profile, dtype=np.float64)
    if w.shape != (n,):
        raise ValueError(
            f"split profile must be 1-D with one value per frame of the node ({n}), got {w.shape}"
        )
    return w


def balanced_split(
    iv: Interval,
    profile: np.ndarray | torch.Tensor,
    min_len: int = DEFAULT_MIN_LEN,
    strategy: str = "balanced",
) -> SplitChoice:
    """Balanced split of ``profile`` ``[iv.length]`` (see the module docstring), with binary fallback."""
    lo, hi = _allowed(iv, min_len)
    w = _as_profile(profile, iv.length)
    binary = binary_split(iv, min_len)

    def fall(reason: str) -> SplitChoice:
        return SplitChoice(binary, strategy, reason)

    if not np.isfinite(w).all():
        return fall("non-finite profile")
    if (w < 0).any():
        return fall("negative profile entry")
    total = float(w.sum())
    if total <= 0.0:  # entries are >= 0 here, so only an all-zero profile sums to 0
        return fall("all-zero profile")
    # S(P) for every P in L+1 .. R: the sum of the first P - L entries.
    cum = np.cumsum(w)[:-1]
    points = np.arange(iv.start + 1, iv.end + 1)
    imbalance = np.abs(2.0 * cum - total)
    if float(imbalance.max() - imbalance.min()) <= 1e-9 * total:
        return fall("no split point balances better than another (a single spike)")
    # Free optimum (ties: nearest the binary point, then the smaller P).
    order = np.lexsort((points, np.abs(points - binary), imbalance))
    best = int(points[order[0]])
    if not lo <= best <= hi:
        return fall(f"balance point {best} outside the allowed range [{lo}, {hi}]")
    return SplitChoice(best, strategy, None)


def choose_split(
    strategy: str,
    iv: Interval,
    profile: np.ndarray | torch.Tensor | None = None,
    min_len: int = DEFAULT_MIN_LEN,
) -> SplitChoice:
    """Split point of node interval ``iv`` with ``strategy`` (``binary``, ``gradient`` or ``flow``).

    ``profile`` ``[iv.length]`` is the node's per-frame profile (needed by ``gradient`` and ``flow``; when it
    is None they fall back to binary with the reason "no profile").
    """
    if strategy not in SPLIT_STRATEGIES:
        raise ValueError(f"split strategy {strategy!r}: choose one of {', '.join(SPLIT_STRATEGIES)}")
    if strategy == "binary":
        return SplitChoice(binary_split(iv, min_len), strategy, None)
    if profile is None:
        return SplitChoice(binary_split(iv, min_len), strategy, "no profile")
    return balanced_split(iv, profile, min_len, strategy)


class ProfileAccumulator:
    """Per-frame profile gathered while a node trains (the ``gradient`` split's input).

    Call :meth:`add` after each backward with the frame just rendered (node-local index) and a non-negative
    value, e.g. the sum over dynamic Gaussians of the norm of their position gradient. :meth:`profile`
    returns the mean value per visit of each frame (frames are sampled at random, so sums would favour the
    frames visited more often); frames never visited get the mean over visited frames (neutral for the
    balance). Non-finite values are skipped and counted in :attr:`skipped`.
    """

    def __init__(self, num_frames: int):
        if num_frames < 1:
            raise ValueError(f"ProfileAccumulator needs >= 1 frame, got {num_frames}")
        self.total = np.zeros(num_frames, dtype=np.float64)
        self.count = np.zeros(num_frames, dtype=np.int64)
        self.skipped = 0

    def add(self, frame: int, value: float | torch.Tensor) -> None:
        v = float(value.detach()) if isinstance(value, torch.Tensor) else float(value)
        if not np.isfinite(v):
            self.skipped += 1
            return
        self.total[frame] += abs(v)
        self.count[frame] += 1

    def profile(self) -> np.ndarray:
        """``[T_node]`` mean value per visit (see the class docstring); all zero when nothing was added."""
        seen = self.count > 0
        out = np.zeros_like(self.total)
        if not seen.any():
            return out
        out[seen] = self.total[seen] / self.count[seen]
        out[~seen] = out[seen].mean()
        return out

    def state_dict(self) -> dict:
        return {"total": torch.from_numpy(self.total.copy()), "count": torch.from_numpy(self.count.copy()),
                "skipped": self.skipped}  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        self.total = state["total"].numpy().astype(np.float64).copy()
        self.count = state["count"].numpy().astype(np.int64).copy()
        self.skipped = int(state["skipped"])


def flow_profile(
    flows: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] | dict,
    dynamic_mask: np.ndarray,
) -> np.ndarray:
    """``[T]`` per-frame motion of the dynamic regions (the ``flow`` split's input), pixels per frame.

    Args:
        flows: ``{(i, j): pair}`` flow from frame i to j, where ``pair`` is a
            :class:`worldtree.priors.flow.FlowPair` (``.flow`` [H, W, 2], ``.valid`` [H, W]) or a tuple
            ``(flow, valid)``.
        dynamic_mask: ``[T, H, W]`` bool dynamic pixels.

    Frame i's value is the mean over its pairs of ``|flow| / |j - i|`` averaged over pixels that are dynamic
    in frame i and valid; frames with no such pixel get 0 (no visible motion).
    """
    mask = np.asarray(dynamic_mask).astype(bool)
    T = mask.shape[0]
    sums = np.zeros(T, dtype=np.float64)
    counts = np.zeros(T, dtype=np.int64)
    for (i, j), pair in flows.items():
        f, valid = (pair.flow, pair.valid) if hasattr(pair, "flow") else pair
        if i == j or not 0 <= i < T:
            continue
        m = mask[i] & np.asarray(valid).astype(bool)
        if not m.any():
            continue
        mag = np.linalg.norm(np.asarray(f, dtype=np.float64)[m], axis=-1)
        mag = mag[np.isfinite(mag)]
        if mag.size == 0:
            continue
        sums[i] += float(mag.mean()) / abs(j - i)
        counts[i] += 1
    out = np.zeros(T, dtype=np.float64)
    ok = counts > 0
    out[ok] = sums[ok] / counts[ok]
    return out


def build_intervals(
    num_frames: int,
    depth: int,
    min_len: int = DEFAULT_MIN_LEN,
    split: str = "binary",
    profile: np.ndarray | torch.Tensor | None = None,
) -> TemporalPartitionTree:
    """Build the tree's intervals layer by layer down to ``depth`` (0 = root only).

    Args:
        num_frames: T training frames.
        depth: deepest layer (the paper: 2, i.e. 3 layers and up to 7 nodes).
        min_len: nodes shorter than this are leaves.
        split: ``binary``, ``gradient`` or ``flow`` (this module).
        profile: for ``gradient``/``flow``, a global per-frame profile ``[T]`` (e.g. flow magnitude of the
            dynamic regions); each node balances its own slice. Unused by ``binary``. When the profile is
            only known after training a node (the gradient split), grow the tree with
            :meth:`TemporalPartitionTree.grow_layer` and a per-node profile instead.
    """
    if depth < 0:
        raise ValueError(f"depth must be >= 0, got {depth}")
    tree = TemporalPartitionTree(num_frames, min_len)
    prof = None
    if profile is not None:
        prof = profile.detach().cpu().double().numpy() if isinstance(profile, torch.Tensor) else profile
        prof = np.asarray(prof, dtype=np.float64)
        if prof.shape != (num_frames,):
            raise ValueError(f"profile must have shape [{num_frames}], got {prof.shape}")

    def fn(j: int, iv: Interval) -> int:
        local = None if prof is None else prof[iv.start : iv.end + 1]
        return choose_split(split, iv, local, min_len).point

    for d in range(depth):
        if not tree.grow_layer(d, fn):
            break
    return tree
