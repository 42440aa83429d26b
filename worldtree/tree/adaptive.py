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
   scaffold and canonical space whatever its residual;
4. ``dynamic_depth_conf >= min_depth_conf`` (default 0.5) when the depth prior's confidence was given: the
   mean confidence of the depth prior over the node's dynamic pixels, i.e. whether the moving content's depth
   is measured (imported or exact depth, objects placed by their outlines) or only filled from its static
   surroundings (the classical depth, confidence 0 there). A child sees each time from one camera; where
   nothing measures the moving content's depth it cannot place it better than its parent did, and measured
   on generated 12- and 40-frame videos and the real Balloon1 its children of 5-20 frames did not beat the
   root (docs/worldtree_method.md, "The tree against its root"). Children of ``depth_test_below`` (40) frames
   or more are exempt: at 160 frames, children of 40-80 frames gained without a measured depth;
5. ``excess >= max(min(min_excess, min_excess_rel * static_error), min_excess_floor)`` (defaults 0.01, i.e.
   2.6 grey levels of 255 on average over the moving pixels; half the static pixels' own error; never under
   0.002, half a grey level): the moving regions are fit clearly worse than the static ones. The relative
   part keeps scenes of smooth texture, whose static pixels fit to well under 0.01, from being judged by a bar
   set for fine texture.

Intervals where the model already follows the motion stay leaves, so branches of one tree differ. Every
quantity is recorded with the decision (``SplitDecision.to_dict``) for ``timing.json``.

Which children a split trains (one-sided split, :func:`decide_child`). Before a child is trained, tests 2-5
are applied to the *parent's* fit restricted to the child's frames: the parent's residual on those frames
(from its per-frame sums, :func:`residual_sums`, and the depth confidence's, :func:`depth_conf_sums`) and the motion of the parent's scaffold over those frames
(same measure and threshold as above). A child whose frames the parent already holds (near-static, or moving
less than the threshold, or fit as well as the static pixels) is not trained: the parent goes on rendering its
frames (:meth:`worldtree.tree.tpt.TemporalPartitionTree.own_frames`). When neither child needs training, the
node stays a leaf. The test on a child has no minimum length (that test is about whether a node may have
children).

The thresholds' measurements (the generated scenes' motion against ground truth, the demo's halves, the
smooth-texture scene) are in docs/worldtree_method.md, "Modelling only what a scene needs".
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import asdict, dataclass

import torch

from worldtree.tree.tpt import can_split

__all__ = ["AutoSplitConfig", "ChildDecision", "FitAssessment", "SplitDecision", "assess_fit", "decide_child",
           "decide_fit_split", "decide_split", "depth_conf_sums", "moving_depth_conf", "residual_stats",
           "residual_sums", "scaffold_motion_px", "stats_of_sums"]  # fmt: skip


@dataclass(frozen=True)
class AutoSplitConfig:
    """Thresholds of the ``--depth auto`` criterion (see the module docstring)."""

    min_excess: float = 0.01
    """Split when the dynamic pixels' mean L1 residual exceeds the static pixels' by at least this
    (colour units in [0, 1])."""
    min_excess_rel: float = 0.5
    """... or by at least this fraction of the static pixels' own mean residual, whichever bar is lower ..."""
    min_excess_floor: float = 0.002
    """... but never by less than this (half a grey level: a model that fits its static pixels exactly must
    not split on noise)."""
    min_dynamic_fraction: float = 0.002
    """Split only when at least this share of the node's pixels is dynamic."""
    min_motion_frac: float = 0.10
    """Split only when the scaffold's motion over the interval (``motion_px``) reaches this fraction of the
    image's larger side (when the motion was measured)."""
    min_depth_conf: float = 0.5
    """Split only when the depth prior's mean confidence over the node's dynamic pixels reaches this (when the
    confidence was given; 0: no such test): short children need the moving content's depth measured."""
    depth_test_below: int = 40
    """The depth test applies to children of fewer frames than this (a node's halves; a would-be child's own
    length); longer children are exempt."""
    max_depth: int = 6
    """Safety bound on the depth ``auto`` may reach (the minimum interval usually stops it first)."""

    def __post_init__(self) -> None:
        if not 0 <= self.min_depth_conf <= 1:
            raise ValueError(
                f"AutoSplitConfig.min_depth_conf {self.min_depth_conf}: choose a value in [0, 1]"
            )
        if self.depth_test_below < 0:
            raise ValueError(f"AutoSplitConfig.depth_test_below {self.depth_test_below}: choose a count >= 0")
        if (
            not self.min_excess >= 0
            or not self.min_excess_rel >= 0
            or not self.min_excess_floor >= 0
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
    dynamic_depth_conf: float | None = None
    """Mean depth-prior confidence over the dynamic pixels (test 4); None when not given."""
    test_cpu_s: float | None = None
    """CPU seconds (this process, all threads) the test itself took on a trained fit (its renders of the node's
    frames and the motion measure; :func:`decide_fit_split`); None when the residual was given."""

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class ChildDecision:
    """Whether a would-be child of a split is trained, measured on its parent's fit over the child's frames
    (:func:`decide_child`)."""

    train: bool
    reason: str
    """Why (e.g. ``"not trained: near-static: scaffold motion 15.5 px < 16 px on the parent's fit"``)."""
    frames: list[int]
    """The child's global frames ``[start, end]``."""
    dynamic_error: float
    static_error: float
    excess: float
    dynamic_fraction: float
    motion_px: float
    """The parent's scaffold motion over the child's frames (pixels)."""
    motion_min_px: float
    dynamic_depth_conf: float | None = None
    """Mean depth-prior confidence over the child's dynamic pixels; None when the parent did not record it."""

    def to_dict(self) -> dict:
        return asdict(self)


@torch.no_grad()
def residual_sums(residual: torch.Tensor, dynamic: torch.Tensor) -> torch.Tensor:
    """Per-frame sums of the residual over the dynamic and the static pixels and their counts.

    Args:
        residual: ``[T, H, W]`` per-pixel L1 residual (colour units); non-finite entries are ignored.
        dynamic: ``[T, H, W]`` bool dynamic mask.

    Returns ``[T, 4]`` float64: ``(dynamic sum, dynamic pixels, static sum, static pixels)`` per frame; the
    statistics of any run of frames follow from its rows (:func:`stats_of_sums`).
    """
    if residual.shape != dynamic.shape or residual.dim() != 3:
        raise ValueError(
            f"residual {tuple(residual.shape)} and mask {tuple(dynamic.shape)} must both be [T, H, W]"
        )
    ok = torch.isfinite(residual)
    r = torch.where(ok, residual, torch.zeros_like(residual)).double()
    dyn, sta = dynamic.bool() & ok, ~dynamic.bool() & ok
    return torch.stack(
        [(r * dyn).sum((1, 2)), dyn.sum((1, 2)).double(), (r * sta).sum((1, 2)), sta.sum((1, 2)).double()], -1
    )


@torch.no_grad()
def depth_conf_sums(conf: torch.Tensor, dynamic: torch.Tensor) -> torch.Tensor:
    """``[T]`` float64 per-frame sums of the depth prior's confidence ``conf`` ``[T, H, W]`` (in [0, 1];
    non-finite entries count 0) over the ``dynamic`` ``[T, H, W]`` pixels; divided by the dynamic pixel
    counts of :func:`residual_sums` they give the mean confidence of any run of frames."""
    if conf.shape != dynamic.shape or conf.dim() != 3:
        raise ValueError(
            f"confidence {tuple(conf.shape)} and mask {tuple(dynamic.shape)} must both be [T, H, W]"
        )
    c = torch.nan_to_num(conf.double(), nan=0.0, posinf=0.0, neginf=0.0).clamp(0.0, 1.0)
    return (c * dynamic.bool().to(c.device)).sum((1, 2))


def moving_depth_conf(conf: torch.Tensor, dynamic: torch.Tensor) -> float | None:
    """Mean of the depth prior's confidence ``conf`` ``[T, H, W]`` (in [0, 1]) over the ``dynamic`` ``[T, H, W]``
    pixels of a whole video: how much of the moving objects' depth the prior measures (None: nothing moves)."""
    n = int(dynamic.bool().sum())
    return float(depth_conf_sums(conf, dynamic).sum()) / n if n else None


def _mean_conf(conf_sums: torch.Tensor | None, sums: torch.Tensor) -> float | None:
    """Mean confidence over the dynamic pixels of the frames of ``sums`` ``[T, 4]`` (None without sums; 0
    without dynamic pixels)."""
    if conf_sums is None:
        return None
    n = float(sums.double().reshape(-1, 4)[:, 1].sum())
    return float(conf_sums.double().sum()) / n if n > 0 else 0.0


def stats_of_sums(sums: torch.Tensor) -> dict[str, float]:
    """:func:`residual_stats` from the per-frame rows ``[T, 4]`` of :func:`residual_sums` (all rows pooled)."""
    d_sum, n_dyn, s_sum, n_sta = (float(x) for x in sums.double().reshape(-1, 4).sum(0))
    d_err = d_sum / n_dyn if n_dyn > 0 else 0.0
    s_err = s_sum / n_sta if n_sta > 0 else 0.0
    return {
        "dynamic_error": d_err,
        "static_error": s_err,
        "excess": d_err - s_err if n_dyn > 0 else 0.0,
        "dynamic_fraction": n_dyn / max(n_dyn + n_sta, 1.0),
    }


@torch.no_grad()
def residual_stats(residual: torch.Tensor, dynamic: torch.Tensor) -> dict[str, float]:
    """Mean residual over dynamic / static pixels and the dynamic share.

    Args:
        residual: ``[T, H, W]`` per-pixel L1 residual (colour units); non-finite entries are ignored.
        dynamic: ``[T, H, W]`` bool dynamic mask.

    Returns ``{"dynamic_error", "static_error", "excess", "dynamic_fraction"}`` (errors are 0 over an empty
    region, so an all-static node has ``excess = 0``).
    """
    return stats_of_sums(residual_sums(residual, dynamic))


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


def _needs_model(st: dict[str, float], motion_px: float | None, min_motion: float, cfg: AutoSplitConfig,
                 depth_conf: float | None = None, child_frames: int = 0) -> tuple[bool, str]:  # fmt: skip
    """Tests 2-5 of the criterion (module docstring) on pooled residual statistics, a motion and the mean depth
    confidence over the dynamic pixels (None: not tested) of a would-be child of ``child_frames`` frames."""
    if st["dynamic_fraction"] < cfg.min_dynamic_fraction:
        return (
            False,
            f"near-static: dynamic fraction {st['dynamic_fraction']:.4g} < {cfg.min_dynamic_fraction:g}",
        )
    if motion_px is not None and not motion_px >= min_motion:
        return False, f"near-static: scaffold motion {motion_px:.3g} px < {min_motion:.3g} px"
    tested = depth_conf is not None and cfg.min_depth_conf > 0 and child_frames < cfg.depth_test_below
    if tested and not depth_conf >= cfg.min_depth_conf:
        return False, (
            f"depth unmeasured: mean depth confidence {depth_conf:.3g} on the moving pixels < "
            f"{cfg.min_depth_conf:g}"
        )
    need = max(min(cfg.min_excess, cfg.min_excess_rel * st["static_error"]), cfg.min_excess_floor)
    if not st["excess"] >= need:
        return False, f"motion fit: excess {st['excess']:.4g} < {need:.4g}"
    return True, f"excess {st['excess']:.4g} >= {need:.4g}"


def decide_split(
    residual: torch.Tensor,
    dynamic: torch.Tensor,
    min_len: int,
    cfg: AutoSplitConfig = AutoSplitConfig(),
    motion_px: float | None = None,
    depth_conf: torch.Tensor | None = None,
) -> SplitDecision:
    """Apply the criterion to a trained node's residual ``[T, H, W]``, dynamic mask ``[T, H, W]`` and, when
    given, its scaffold motion ``motion_px`` (:func:`scaffold_motion_px`) and the depth prior's confidence
    ``depth_conf`` ``[T, H, W]`` in [0, 1] (None skips that test)."""
    conf_sums = depth_conf_sums(depth_conf, dynamic) if depth_conf is not None else None
    size = (int(residual.shape[1]), int(residual.shape[2]))
    return _decide_sums(residual_sums(residual, dynamic), conf_sums, size, min_len, cfg, motion_px)


def _decide_sums(sums: torch.Tensor, conf_sums: torch.Tensor | None, image_size: tuple[int, int], min_len: int,
                 cfg: AutoSplitConfig, motion_px: float | None) -> SplitDecision:  # fmt: skip
    """:func:`decide_split` from the node's per-frame sums ``[T, 4]`` (:func:`residual_sums`) and ``[T]``
    (:func:`depth_conf_sums`, or None) at image size ``(H, W)``."""
    st = stats_of_sums(sums)
    conf = _mean_conf(conf_sums, sums)
    frames = int(sums.shape[0])
    min_motion = cfg.min_motion_frac * max(image_size)
    if not can_split(frames, min_len):
        split, reason = False, f"interval: {frames} frames < min_len {min_len}"
    else:
        split, reason = _needs_model(st, motion_px, min_motion, cfg, conf, child_frames=frames // 2)
    return SplitDecision(split, reason, frames, st["dynamic_error"], st["static_error"], st["excess"],
                         st["dynamic_fraction"], motion_px, None if motion_px is None else min_motion,
                         conf)  # fmt: skip


@dataclass
class FitAssessment:
    """A trained fit measured once on its own frames: its split decision and what its children's decisions
    need (:func:`decide_child`)."""

    decision: SplitDecision
    sums: torch.Tensor
    """``[T, 4]`` per-frame residual sums (:func:`residual_sums`) of the fit's frames."""
    Ks: torch.Tensor
    """``[T, 3, 3]`` the fit's intrinsics (the motion of a run of frames is measured through them)."""
    image_size: tuple[int, int]
    """``(H, W)`` of the residual (the motion threshold is a fraction of the larger side)."""
    conf_sums: torch.Tensor | None = None
    """``[T]`` per-frame depth-confidence sums over the dynamic pixels (:func:`depth_conf_sums`); None when
    the confidence was not given."""

    def to_payload(self) -> dict:
        """Plain tensors and numbers (a tree node's output file)."""
        out = {"sums": self.sums.detach().cpu().double(), "Ks": self.Ks.detach().cpu().float(),
               "image_size": [int(self.image_size[0]), int(self.image_size[1])]}  # fmt: skip
        if self.conf_sums is not None:
            out["conf_sums"] = self.conf_sums.detach().cpu().double()
        return out


def assess_fit(fit, dynamic: torch.Tensor, min_len: int, cfg: AutoSplitConfig,
               depth_conf: torch.Tensor | None = None) -> FitAssessment:  # fmt: skip
    """:func:`decide_fit_split` plus the per-frame sums its children's decisions use (one render of each of
    the fit's frames serves both)."""
    cpu0 = time.process_time()
    motion = scaffold_motion_px(fit.scaffold.pos, fit.Ks, fit.cameras())
    residual = fit.residuals()
    sums = residual_sums(residual, dynamic)
    conf_sums = depth_conf_sums(depth_conf, dynamic) if depth_conf is not None else None
    size = (int(residual.shape[1]), int(residual.shape[2]))
    decision = _decide_sums(sums, conf_sums, size, min_len, cfg, motion)
    decision = dataclasses.replace(decision, test_cpu_s=time.process_time() - cpu0)
    return FitAssessment(decision, sums, fit.Ks, size, conf_sums)


def decide_fit_split(fit, dynamic: torch.Tensor, min_len: int, cfg: AutoSplitConfig,
                     depth_conf: torch.Tensor | None = None) -> SplitDecision:  # fmt: skip
    """:func:`decide_split` for a trained photometric fit (``worldtree.stages.photometric.PhotometricFit`` or a
    tree node's fit): its residuals on its own frames, ``dynamic`` ``[T, H, W]`` masks of those frames, the
    motion of its own scaffold seen by its own cameras and, when given, the depth prior's confidence ``[T, H,
    W]`` on those frames. Records the test's own CPU time (``test_cpu_s``)."""
    return assess_fit(fit, dynamic, min_len, cfg, depth_conf).decision


def decide_child(
    parent_pos: torch.Tensor,
    parent_w2cs: torch.Tensor,
    parent_start: int,
    measured: dict,
    child: tuple[int, int],
    cfg: AutoSplitConfig,
) -> ChildDecision:
    """Whether a would-be child needs its own training, from its parent's fit on the child's frames.

    Args:
        parent_pos: ``[T_p, M, 3]`` the trained parent's scaffold positions over its frames (node-local).
        parent_w2cs: ``[T_p, 4, 4]`` the parent's cameras.
        parent_start: the parent's first global frame.
        measured: the parent's :meth:`FitAssessment.to_payload` (``sums`` ``[T_p, 4]``, ``Ks`` ``[T_p, 3, 3]``,
            ``image_size``, and ``conf_sums`` ``[T_p]`` when the depth confidence was measured).
        child: the child's global frames ``(start, end)`` inclusive, inside the parent's.

    Tests 2-5 of the criterion on those frames (module docstring): the parent's residual sums pooled over them,
    its scaffold's motion over them (:func:`scaffold_motion_px`, the same threshold) and the depth confidence
    over their dynamic pixels.
    """
    a, b = int(child[0]) - int(parent_start), int(child[1]) - int(parent_start)
    T = int(parent_pos.shape[0])
    if not 0 <= a <= b < T or measured["sums"].shape[0] != T:
        raise ValueError(f"child frames {child} are not inside the parent's {T} frames from {parent_start}")
    sl = slice(a, b + 1)
    motion = scaffold_motion_px(parent_pos[sl], measured["Ks"][sl], parent_w2cs[sl])
    st = stats_of_sums(measured["sums"][sl])
    cs = measured.get("conf_sums")
    conf = _mean_conf(cs[sl] if cs is not None else None, measured["sums"][sl])
    min_motion = cfg.min_motion_frac * max(int(x) for x in measured["image_size"])
    train, why = _needs_model(st, motion, min_motion, cfg, conf, child_frames=b - a + 1)
    reason = ("trained: " if train else "not trained: ") + why + " on the parent's fit"
    return ChildDecision(train, reason, [int(child[0]), int(child[1])], st["dynamic_error"], st["static_error"],
                         st["excess"], st["dynamic_fraction"], motion, min_motion, conf)  # fmt: skip
