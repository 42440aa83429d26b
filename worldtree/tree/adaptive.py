"""``--depth auto``: whether a trained node's frames need children, by a measured criterion.

After a node is trained, it is rendered on each of its own training frames and the per-pixel photometric
residual ``r = mean_c |render - image|`` (colours in [0, 1]) is split by the node's dynamic mask (the priors'
per-frame motion mask, ``[T, H, W]`` bool):

- ``dynamic_error``: mean of ``r`` over the dynamic pixels of every frame of the node;
- ``static_error``: mean of ``r`` over the other pixels, the level one canonical space reaches where nothing
  moves (noise, blur, limited Gaussians), which children cannot lower by splitting time;
- ``excess = dynamic_error - static_error``: the part of the moving regions' error that one canonical space
  with one set of scaffold trajectories over the node's interval leaves unexplained;
- ``dynamic_fraction``: share of the node's pixels that are dynamic.

The node is split when all of these hold (otherwise ``reason`` names the first that failed):

1. it has ``>= min_len`` frames (the tree's minimum interval; shorter nodes are leaves anyway);
2. ``dynamic_fraction >= min_dynamic_fraction`` (a near-static interval has nothing for children to add);
3. ``excess >= min_excess`` (default 0.01, i.e. 2.6 grey levels of 255 on average over the moving pixels):
   the moving regions are fit clearly worse than the static ones.

Intervals where the model already follows the motion stay leaves, so branches of one tree differ. Every
quantity is recorded with the decision (``SplitDecision.to_dict``) for ``timing.json``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch

from worldtree.tree.tpt import can_split

__all__ = ["AutoSplitConfig", "SplitDecision", "decide_split", "residual_stats"]


@dataclass(frozen=True)
class AutoSplitConfig:
    """Thresholds of the ``--depth auto`` criterion (see the module docstring)."""

    min_excess: float = 0.01
    """Split when the dynamic pixels' mean L1 residual exceeds the static pixels' by at least this
    (colour units in [0, 1])."""
    min_dynamic_fraction: float = 0.002
    """Split only when at least this share of the node's pixels is dynamic."""
    max_depth: int = 6
    """Safety bound on the depth ``auto`` may reach (the minimum interval usually stops it first)."""

    def __post_init__(self) -> None:
        if not self.min_excess >= 0 or not 0 <= self.min_dynamic_fraction <= 1 or self.max_depth < 0:
            raise ValueError(
                f"AutoSplitConfig needs min_excess >= 0, 0 <= min_dynamic_fraction <= 1 and max_depth >= 0; "
                f"got {self.min_excess}, {self.min_dynamic_fraction}, {self.max_depth}"
            )


@dataclass(frozen=True)
class SplitDecision:
    """Whether a node is split and the measurements behind it."""

    split: bool
    reason: str
    """Why (e.g. ``"excess 0.031 >= 0.01"`` or ``"near-static: dynamic fraction 0.0001 < 0.002"``)."""
    frames: int
    dynamic_error: float
    static_error: float
    excess: float
    dynamic_fraction: float

    def to_dict(self) -> dict:
        return asdict(self)


@torch.no_grad()
def residual_stats(residual: torch.Tensor, dynamic: torch.Tensor) -> dict[str, float]:
    """Mean residual over dynamic / static pixels and the dynamic share.

    Args:
        residual: ``[T, H, W]`` per-pixel L1 residual (colour units); non-finite entries are ignored.
        dynamic: ``[T, H, W]`` bool dynamic mask.

    Returns ``{"dynamic_error", "static_error", "excess", "dynamic_fraction"}`` (errors are 0 over an empty
    region, so an all-static node has ``excess = 0``).
    """
    if residual.shape != dynamic.shape or residual.dim() != 3:
        raise ValueError(
            f"residual {tuple(residual.shape)} and mask {tuple(dynamic.shape)} must both be [T, H, W]"
        )
    ok = torch.isfinite(residual)
    r = torch.where(ok, residual, torch.zeros_like(residual)).double()
    dyn, sta = dynamic.bool() & ok, ~dynamic.bool() & ok
    n_dyn, n_sta = int(dyn.sum()), int(sta.sum())
    d_err = float(r[dyn].mean()) if n_dyn else 0.0
    s_err = float(r[sta].mean()) if n_sta else 0.0
    total = max(n_dyn + n_sta, 1)
    return {
        "dynamic_error": d_err,
        "static_error": s_err,
        "excess": d_err - s_err if n_dyn else 0.0,
        "dynamic_fraction": n_dyn / total,
    }


def decide_split(
    residual: torch.Tensor, dynamic: torch.Tensor, min_len: int, cfg: AutoSplitConfig = AutoSplitConfig()
) -> SplitDecision:
    """Apply the criterion to a trained node's residual ``[T, H, W]`` and dynamic mask ``[T, H, W]``."""
    st = residual_stats(residual, dynamic)
    frames = int(residual.shape[0])
    if not can_split(frames, min_len):
        split, reason = False, f"interval: {frames} frames < min_len {min_len}"
    elif st["dynamic_fraction"] < cfg.min_dynamic_fraction:
        split = False
        reason = f"near-static: dynamic fraction {st['dynamic_fraction']:.4g} < {cfg.min_dynamic_fraction:g}"
    elif st["excess"] < cfg.min_excess:
        split, reason = False, f"motion fit: excess {st['excess']:.4g} < {cfg.min_excess:g}"
    else:
        split, reason = True, f"excess {st['excess']:.4g} >= {cfg.min_excess:g}"
    return SplitDecision(split, reason, frames, st["dynamic_error"], st["static_error"], st["excess"],
                         st["dynamic_fraction"])  # fmt: skip
