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

The residual alone cannot tell an object the node has not reconstructed yet (too few steps or Gaussians:
splitting time does not help) from motion that one canonical space cannot hold. So the criterion also measures
the motion itself, from the node's trained scaffold (:func:`scaffold_motion_px`):

- ``motion_px``: how far the scene's moving parts travel on screen within the node's interval, camera motion
  removed: for each scaffold node (its trajectory averaged over 5 consecutive frames, so that frame-to-frame
  jitter of the optimised nodes does not count) the largest distance, over the interval's frames ``t``,
  between its pixel at ``t`` and the pixel its middle-frame position would have in the same camera ``t``;
  the 90th percentile over the nodes (robust to a few stray nodes).

The node is split when all of these hold (otherwise ``reason`` names the first that failed):

1. it has ``>= min_len`` frames (the tree's minimum interval; shorter nodes are leaves anyway);
2. ``dynamic_fraction >= min_dynamic_fraction`` (a near-static interval has nothing for children to add);
3. ``motion_px >= min_motion_frac * max(H, W)`` (default 10 % of the image's larger side, 16 px at 160x90)
   when the motion was measured: content that moves less than that over the interval is held by one
   scaffold and canonical space whatever its residual. Ground truth of the generated scenes at 160x90 over
   40 frames: ``near_static`` about 5 px, ``slow`` 50 px, ``slow_fast`` 38 px in its first half and 88 px in
   its second, ``fast`` 60-90 px in any half; measured on the root scaffolds of quick-preset runs: ``near_static``
   3.3 px at 80x45 (threshold 8), the demo (``slow_fast``, 160x90) 42.5 px over the clip, 15.5 px in the
   first half and 29.9 px in the second (threshold 16: the calm half stays a leaf, the fast half splits);
4. ``excess >= min_excess`` (default 0.01, i.e. 2.6 grey levels of 255 on average over the moving pixels):
   the moving regions are fit clearly worse than the static ones.

Intervals where the model already follows the motion stay leaves, so branches of one tree differ. Every
quantity is recorded with the decision (``SplitDecision.to_dict``) for ``timing.json``.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import asdict, dataclass

import torch

from worldtree.tree.tpt import can_split

__all__ = ["AutoSplitConfig", "SplitDecision", "decide_fit_split", "decide_split", "residual_stats",
           "scaffold_motion_px"]  # fmt: skip


@dataclass(frozen=True)
class AutoSplitConfig:
    """Thresholds of the ``--depth auto`` criterion (see the module docstring)."""

    min_excess: float = 0.01
    """Split when the dynamic pixels' mean L1 residual exceeds the static pixels' by at least this
    (colour units in [0, 1])."""
    min_dynamic_fraction: float = 0.002
    """Split only when at least this share of the node's pixels is dynamic."""
    min_motion_frac: float = 0.10
    """Split only when the scaffold's motion over the interval (``motion_px``) reaches this fraction of the
    image's larger side (when the motion was measured)."""
    max_depth: int = 6
    """Safety bound on the depth ``auto`` may reach (the minimum interval usually stops it first)."""

    def __post_init__(self) -> None:
        if (
            not self.min_excess >= 0
            or not 0 <= self.min_dynamic_fraction <= 1
            or self.max_depth < 0
            or not self.min_motion_frac >= 0
        ):
            raise ValueError(
                "AutoSplitConfig needs min_excess >= 0, 0 <= min_dynamic_fraction <= 1, max_depth >= 0 and "
                f"min_motion_frac >= 0; got {self.min_excess}, {self.min_dynamic_fraction}, {self.max_depth}, "
                f"{self.min_motion_frac}"
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
    motion_px: float | None = None
    """Scaffold motion over the interval in pixels (:func:`scaffold_motion_px`); None when not measured."""
    motion_min_px: float | None = None
    """The motion threshold applied (``min_motion_frac * max(H, W)``); None when not measured."""
    test_cpu_s: float | None = None
    """CPU seconds (this process, all threads) the test itself took on a trained fit (its renders of the node's
    frames and the motion measure; :func:`decide_fit_split`); None when the residual was given."""

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


@torch.no_grad()
def scaffold_motion_px(
    pos: torch.Tensor, Ks: torch.Tensor, w2cs: torch.Tensor, quantile: float = 0.9, smooth: int = 5
) -> float:
    """On-screen motion of scaffold nodes over an interval, camera motion removed (pixels).

    Args:
        pos: ``[T, M, 3]`` node positions per frame (world units). Ks: ``[T, 3, 3]``. w2cs: ``[T, 4, 4]``.
        quantile: over the nodes, of each node's largest displacement.
        smooth: the trajectories are first averaged over this many consecutive frames (a box filter, kept
            where the whole window lies inside the interval, with the cameras of the windows' centres): frame-
            to-frame jitter of the optimised nodes is not motion (1 = no smoothing; larger than ``T`` is
            clamped to the largest odd window that fits).

    For node ``m`` and frame ``t``: ``|pi_t(pos[t, m]) - pi_t(pos[mid, m])|`` with ``pi_t`` frame ``t``'s
    camera and ``mid`` the middle frame; a node's motion is its largest value over ``t`` (pairs with a point
    within 1e-6 of the camera plane or behind it are skipped). Returns the ``quantile`` over nodes, 0.0 with
    no node or a single frame.
    """
    T, M = int(pos.shape[0]), int(pos.shape[1])
    if M == 0 or T < 2:
        return 0.0
    p = pos.detach().double()
    K, w2c = Ks.detach().double().to(p.device), w2cs.detach().double().to(p.device)
    w = max(1, min(int(smooth), T if T % 2 else T - 1))
    if w > 1:
        p = p.unfold(0, w, 1).mean(-1)  # [T - w + 1, M, 3]: windows of frames, centred at w // 2 ...
        K, w2c = K[w // 2 : T - w // 2], w2c[w // 2 : T - w // 2]  # ... with those centres' cameras
        T = int(p.shape[0])
        if T < 2:
            return 0.0
    R, tr = w2c[:, None, :3, :3], w2c[:, None, :3, 3]

    def pixels(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        cam = (R @ x[..., None])[..., 0] + tr  # [T, M, 3]
        z = cam[..., 2]
        ok = z > 1e-6
        zs = torch.where(ok, z, torch.ones_like(z))
        u = K[:, None, 0, 0] * cam[..., 0] / zs + K[:, None, 0, 2]
        v = K[:, None, 1, 1] * cam[..., 1] / zs + K[:, None, 1, 2]
        return torch.stack([u, v], -1), ok

    now, ok_now = pixels(p)
    still, ok_still = pixels(p[T // 2].expand(T, M, 3))
    d = (now - still).norm(dim=-1)
    d = torch.where(ok_now & ok_still & torch.isfinite(d), d, torch.zeros_like(d))
    per_node = d.amax(dim=0)  # [M]
    return float(torch.quantile(per_node, float(quantile)))


def decide_split(
    residual: torch.Tensor,
    dynamic: torch.Tensor,
    min_len: int,
    cfg: AutoSplitConfig = AutoSplitConfig(),
    motion_px: float | None = None,
) -> SplitDecision:
    """Apply the criterion to a trained node's residual ``[T, H, W]``, dynamic mask ``[T, H, W]`` and, when
    given, its scaffold motion ``motion_px`` (:func:`scaffold_motion_px`; None skips that test)."""
    st = residual_stats(residual, dynamic)
    frames = int(residual.shape[0])
    min_motion = cfg.min_motion_frac * max(int(residual.shape[1]), int(residual.shape[2]))
    if not can_split(frames, min_len):
        split, reason = False, f"interval: {frames} frames < min_len {min_len}"
    elif st["dynamic_fraction"] < cfg.min_dynamic_fraction:
        split = False
        reason = f"near-static: dynamic fraction {st['dynamic_fraction']:.4g} < {cfg.min_dynamic_fraction:g}"
    elif motion_px is not None and not motion_px >= min_motion:
        split, reason = False, f"near-static: scaffold motion {motion_px:.3g} px < {min_motion:.3g} px"
    elif st["excess"] < cfg.min_excess:
        split, reason = False, f"motion fit: excess {st['excess']:.4g} < {cfg.min_excess:g}"
    else:
        split, reason = True, f"excess {st['excess']:.4g} >= {cfg.min_excess:g}"
    return SplitDecision(split, reason, frames, st["dynamic_error"], st["static_error"], st["excess"],
                         st["dynamic_fraction"], motion_px, None if motion_px is None else min_motion)  # fmt: skip


def decide_fit_split(fit, dynamic: torch.Tensor, min_len: int, cfg: AutoSplitConfig) -> SplitDecision:
    """:func:`decide_split` for a trained photometric fit (``worldtree.stages.photometric.PhotometricFit`` or a
    tree node's fit): its residuals on its own frames, ``dynamic`` ``[T, H, W]`` masks of those frames, and
    the motion of its own scaffold seen by its own cameras. Records the test's own CPU time (``test_cpu_s``)."""
    cpu0 = time.process_time()
    motion = scaffold_motion_px(fit.scaffold.pos, fit.Ks, fit.cameras())
    decision = decide_split(fit.residuals(), dynamic, min_len, cfg, motion_px=motion)
    return dataclasses.replace(decision, test_cpu_s=time.process_time() - cpu0)
