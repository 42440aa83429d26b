"""Held-out validation of a tree node: a child is kept only where it renders frames it did not train on better
than its parent, which did train on them.

A child sees each of its times from one camera only, and every time from a different one; what it learns
beyond its parent can be real (motion one canonical space could not hold) or over-fitting (detail that fits
its own views and nothing else). Frames the child never trained on tell the two apart: a child that
over-fits draws them worse. Its parent did train on them, so both models *predict* a held-out frame ``i``
from their states at ``i - 1`` and ``i + 1`` (every Gaussian halfway, :func:`worldtree.dynamic.halfway`),
seen from frame ``i``'s camera: the parent's own fit of frame ``i`` is not used.

Rules:

- the held-out frames of a node of ``n`` frames are ``round(n * frac)`` interior frames spread evenly
  (:func:`holdout_frames`; never the first or last, whose neighbours on one side belong to another node);
- a child is kept when its mean L1 error on them is below its parent's by at least ``margin`` of the parent's
  (:func:`keep_child`); a rejected child is dropped and its parent renders its frames.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch

__all__ = ["HoldoutConfig", "Verdict", "holdout_frames", "keep_child"]


@dataclass(frozen=True)
class HoldoutConfig:
    """Held-out validation of the children (one source of defaults)."""

    enabled: bool = False
    """Hold out frames of every child and keep it only where it beats its parent on them. Off by default:
    measured to reject children that raise the test views' mPSNR (docs/worldtree_method.md, "The tree
    against its root"): a held-out frame is a new time as well as a new camera, and the test views are new
    cameras at trained times."""
    frac: float = 0.2
    """Share of a child's frames held out (at least one when it has three or more frames)."""
    margin: float = 0.0
    """Relative L1 improvement over the parent a child needs on the held-out frames to be kept."""
    refit: bool = True
    """A kept child then trains on its held-out frames too, ``ceil(steps * frac)`` more steps."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.frac < 1.0:
            raise ValueError(f"holdout.frac {self.frac}: choose a share in [0, 1)")
        if not 0.0 <= self.margin < 1.0:
            raise ValueError(f"holdout.margin {self.margin}: choose a relative margin in [0, 1)")


def holdout_frames(n: int, frac: float) -> list[int]:
    """Node-local indices of the held-out frames of a node of ``n`` frames: ``round(n * frac)`` (at least 1
    when ``frac > 0``) interior frames at evenly spaced positions; empty when ``n < 3`` or ``frac == 0``."""
    if n < 3 or frac <= 0:
        return []
    k = min(max(1, round(n * frac)), n - 2)
    # Centres of k equal parts of the interior 1 .. n-2.
    picks = {1 + int((i + 0.5) * (n - 2) / k) for i in range(k)}
    return sorted(min(max(p, 1), n - 2) for p in picks)


@dataclass(frozen=True)
class Verdict:
    """The outcome of one child's validation."""

    keep: bool
    frames: list[int]
    """Held-out node-local frames."""
    child_l1: float
    """Mean L1 error (colour units in [0, 1]) of the child on them."""
    parent_l1: float
    """The same for the parent (as it was when the child was made)."""
    child_psnr: float
    parent_psnr: float
    reason: str

    def to_dict(self) -> dict:
        return asdict(self)


def _psnr(mse: float) -> float:
    return 10.0 * float(torch.log10(torch.tensor(1.0 / max(mse, 1e-12))))


def keep_child(
    child: list[torch.Tensor], parent: list[torch.Tensor], target: list[torch.Tensor], frames: list[int],
    margin: float = 0.0,
) -> Verdict:  # fmt: skip
    """Decide from renders ``[H, W, 3]`` in [0, 1] of the held-out ``frames`` by the child and the parent,
    against the ``target`` images: keep the child when its mean L1 is below ``(1 - margin)`` times the
    parent's. No held-out frame keeps the child (nothing to judge by)."""
    if not frames:
        return Verdict(True, [], float("nan"), float("nan"), float("nan"), float("nan"),
                       "kept: no held-out frame (interval too short)")  # fmt: skip
    if not len(child) == len(parent) == len(target) == len(frames):
        raise ValueError("keep_child: one render per held-out frame for child, parent and target")

    def errors(renders):
        l1 = torch.stack([(r - t).abs().mean() for r, t in zip(renders, target, strict=True)]).mean()
        mse = torch.stack([((r - t) ** 2).mean() for r, t in zip(renders, target, strict=True)]).mean()
        return float(l1), _psnr(float(mse))

    c1, cp = errors(child)
    p1, pp = errors(parent)
    if not (c1 == c1 and p1 == p1):  # NaN renders: never keep what cannot be judged
        return Verdict(False, list(frames), c1, p1, cp, pp, "rejected: non-finite error on the held-out frames")
    keep = c1 < (1.0 - margin) * p1
    verb = "kept" if keep else "rejected"
    reason = (f"{verb}: held-out L1 {c1:.5f} vs parent {p1:.5f} ({cp:.2f} vs {pp:.2f} dB) on "
              f"{len(frames)} frame(s)")  # fmt: skip
    return Verdict(bool(keep), list(frames), c1, p1, cp, pp, reason)
