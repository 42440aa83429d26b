"""The motion scaffold: M nodes with a rigid pose per frame and a radius, a curve-distance KNN graph over them,
and the deformation of Gaussians by dual-quaternion blending of their neighbours' motion.

Built from complete 3D trajectories of the dynamic tracks (:mod:`worldtree.motion.lift`) by
:func:`build_scaffold`; nodes are added where content is far from every node (:func:`densify`) and thinned by
:func:`resample_nodes`. Distances are in scene units; the config speaks in *units* of
``unit_ratio * scene_scale`` (0.01 of the scene scale by default). Formulas and choices: ``docs/motion.md``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass

import torch
from torch import nn

from worldtree.motion import quaternion as Q
from worldtree.motion import se3, skinning

__all__ = [
    "ArapGraph",
    "Scaffold",
    "ScaffoldConfig",
    "SkinCache",
    "build_scaffold",
    "curve_distance",
    "densify",
    "greedy_select",
    "resample_nodes",
    "subsample_frames",
]


@dataclass
class ScaffoldConfig:
    """Scaffold construction and topology settings (REFERENCE section 2 unless said)."""

    unit_ratio: float = 0.01
    """One *unit* is ``unit_ratio * scene_scale`` scene units; every ``*_units`` field below is in units."""
    node_spacing_units: float = 2.0
    """Minimum curve distance between the nodes picked from the tracks (greedy, see :func:`greedy_select`).
    Not given by the paper or REFERENCE: chosen well under the 5-unit edge threshold and the 7-unit radius, so
    a node has ~15 valid neighbours on a surface and every Gaussian several nodes in reach."""
    max_nodes: int = 4096
    """Cap on the nodes picked at build time (the best-observed tracks are picked first)."""
    knn_k: int = 16
    """Graph neighbours per node, the node itself included (column 0)."""
    edge_max_dist_units: float = 5.0
    """A graph edge is valid when the curve distance is below this (the self edge is always valid)."""
    curve_top_k: int = 3
    """Curve distance = the k-th largest per-frame distance (robust maximum), see :func:`curve_distance`."""
    curve_max_frames: int = 100
    """Per-frame distances are taken on at most this many evenly spaced frames."""
    sigma_init_units: float = 7.0
    """Initial node radius."""
    sigma_max_units: float = 20.0
    """Largest node radius: ``sigma = sigma_max * sigmoid(sigma_logit)``."""
    rotation_mode: str = "reference"
    """Node rotation initialisation: ``"reference"`` (Procrustes of each frame against the reference frame, no
    drift) or ``"accumulated"`` (frame-to-frame Procrustes chained from the reference frame, as MoSca)."""
    rotation_ref_frame: int = -1
    """Reference frame of the rotations (identity there); -1 picks the frame where most nodes are observed."""
    rotation_neighbours: int = 16
    """Tracks in each node's Procrustes neighbourhood (the node's own track included): the nearest by curve
    distance, counted only below ``edge_max_dist_units``."""
    unobserved_weight: float = 0.1
    """Procrustes weight of a neighbour whose position is filled (not observed) in either frame of a fit."""
    arap_level_units: tuple[float, ...] = (1.0, 4.0)
    """Multi-level ARAP: node subsets resampled at these curve spacings."""
    arap_level_k: tuple[int, ...] = (8, 8)
    """Multi-level ARAP: neighbours per node in each level's subset."""
    arap_level_weights: tuple[float, ...] = (0.4, 0.3)
    """Multi-level ARAP: weight of each level relative to the base graph (weight 1)."""
    complete_radius_units: float = 12.0
    """Track ends are continued with the motion of measured tracks within this distance
    (:mod:`worldtree.motion.track_completion`; 0 = held constant). Not from the paper: a little under the
    size of the generated scenes' moving objects (20-30 units across), so one body's motion is not lent to
    another."""
    complete_k: int = 8
    """Most neighbouring tracks averaged per completion step."""
    trajectory_depth: bool = True
    """Re-estimate the depth of the dynamic tracks (and of the dynamic pixels near them) from the smoothness
    of their 3D trajectories before lifting (:mod:`worldtree.motion.track_depth`): the depth prior on moving
    objects is a static-world estimate. Classical depth only: imported depth (a network's, or exact) is a
    measurement on the moving objects and is kept (with exact priors the re-estimate cost 3.4 dB mPSNR in
    tests/methods/test_base_beats_static.py)."""
    trajectory_depth_imported: bool = False
    """Also re-estimate imported depth that was fitted to the classical one (``priors.depth_import.fit_scale_shift``):
    a network's relative depth, scaled per frame by the static world around the moving objects, is not a
    measurement of their depth either. Off: the fitted import is kept on moving pixels (on, it scored lower on
    Balloon1's leave-one-out and did not gain on generated scenes: docs/priors.md)."""
    trajectory_depth_prior: float = 3e-3
    """Weight of the depth prior against the trajectory's smoothness (``w`` of
    :func:`worldtree.motion.track_depth.smooth_trajectory_depths`). Not from the paper: on the demo scene's
    classical priors 1e-3..1e-2 gave the lowest depth error on the moving objects (3e-3: median 9 % / 13 % in
    the slow / fast half against 13 % / 28 % for the prior); much smaller lets the cameras' ambiguity through."""
    densify_dist_units: float = 5.0
    """:func:`densify` adds nodes for points farther than this from every node at their frame."""
    densify_max_new: int = 32
    """At most this many nodes per :func:`densify` call (paper appendix: 32)."""
    mix_identity: bool = True
    """Deformation blends with the identity by ``clamp(sum of raw skinning weights, 0, 1)`` (MoSca)."""

    def __post_init__(self) -> None:
        if self.rotation_mode not in ("reference", "accumulated"):
            raise ValueError(
                f"ScaffoldConfig.rotation_mode must be 'reference' or 'accumulated', got {self.rotation_mode!r}"
            )
        if not len(self.arap_level_units) == len(self.arap_level_k) == len(self.arap_level_weights):
            raise ValueError(
                "ScaffoldConfig: arap_level_units, arap_level_k and arap_level_weights need equal lengths"
            )
        if min(self.knn_k, self.curve_top_k, self.curve_max_frames, self.rotation_neighbours) < 1:
            raise ValueError(
                "ScaffoldConfig: knn_k, curve_top_k, curve_max_frames and rotation_neighbours must be >= 1"
            )
        if not 0 < self.sigma_init_units < self.sigma_max_units:
            raise ValueError("ScaffoldConfig: need 0 < sigma_init_units < sigma_max_units")
        # Tuples survive a JSON round trip as lists; keep them tuples (frozen, hashable defaults).
        self.arap_level_units = tuple(float(x) for x in self.arap_level_units)
        self.arap_level_k = tuple(int(x) for x in self.arap_level_k)
        self.arap_level_weights = tuple(float(x) for x in self.arap_level_weights)


@dataclass
class ArapGraph:
    """Neighbourhoods for the ARAP term: node i is compared with the nodes ``idx[i]``.

    ``idx`` [M, K] long, ``valid`` [M, K] bool, ``weight`` the level weight, ``detach_neighbours`` whether the
    neighbours' positions are treated as constants (MoSca does so for the coarse levels).
    """

    idx: torch.Tensor
    valid: torch.Tensor
    weight: float = 1.0
    detach_neighbours: bool = False


@dataclass
class SkinCache:
    """Per-Gaussian skinning neighbourhood: ``attach`` [N] nearest node at the reference time, ``idx`` [N, K]
    that node's graph neighbours (itself first), ``valid`` [N, K] their edge validity."""

    attach: torch.Tensor
    idx: torch.Tensor
    valid: torch.Tensor

    def to_state(self) -> dict[str, torch.Tensor]:
        """CPU copies of the three tensors (a checkpoint carries the cache: recomputing it on resume from the
        checkpoint's node positions would differ from the one the uninterrupted run still uses)."""
        return {k: getattr(self, k).detach().cpu().clone() for k in ("attach", "idx", "valid")}

    @classmethod
    def from_state(cls, state: dict[str, torch.Tensor], device: torch.device | str | None = None) -> SkinCache:
        """Inverse of :meth:`to_state` (optionally onto ``device``)."""
        return cls(*(state[k].to(device) if device is not None else state[k] for k in ("attach", "idx", "valid")))


def subsample_frames(T: int, max_frames: int, device: torch.device | str | None = None) -> torch.Tensor:
    """At most ``max_frames`` evenly spaced frame indices of ``0..T-1`` (all of them when T <= max_frames).

    Deterministic (rounded ``linspace``, duplicates removed), so graphs are reproducible without a seed.
    """
    if T <= max_frames:
        return torch.arange(T, device=device)
    return torch.unique(torch.linspace(0, T - 1, max_frames, device=device).round().long())


class _Curves:
    """Trajectories prepared once for many :func:`curve_distance` queries: on the evenly spaced frames,
    curve-major (one curve's frames contiguous, so gathering curves reads whole rows).

    ``traj`` [T, N, 3], ``obs`` [T, N] bool or None (all observed)."""

    def __init__(self, traj: torch.Tensor, obs: torch.Tensor | None, max_frames: int):
        frames = subsample_frames(traj.shape[0], max_frames, traj.device)
        self.frames = int(frames.numel())
        self.xyz = traj[frames].permute(1, 0, 2).contiguous()  # [N, T', 3]
        if obs is None:
            self.obs = torch.ones(self.xyz.shape[:2], dtype=torch.bool, device=traj.device)
        else:
            self.obs = obs[frames].bool().T.contiguous()  # [N, T']
        self.obs_f = self.obs.to(traj.dtype)

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


@torch.no_grad()
def curve_distance(
    a: torch.Tensor,
    b: torch.Tensor,
    a_obs: torch.Tensor | None = None,
    b_obs: torch.Tensor | None = None,
    top_k: int = 3,
    max_frames: int = 100,
    max_chunk: int = 1 << 23,
) -> torch.Tensor:
    """Robust maximum over time of the distance between curves: [P, Q].

    Args:
        a: [T, P, 3], b: [T, Q, 3] trajectories.
        a_obs, b_obs: [T, P], [T, Q] bool observed frames (None: all observed).
        top_k: robustness; the ``k_eff``-th largest co-observed distance is returned with
            ``k_eff = clamp(ceil(top_k * n / T'), 1, min(top_k, n))``, ``n`` the number of frames where both are
            observed among the ``T'`` used frames (fewer co-observed frames -> closer to the plain maximum).
        max_frames: per-frame distances on at most this many evenly spaced frames (:func:`subsample_frames`).
        max_chunk: bound on ``T' * rows * Q`` per block (memory).

    Returns:
        [P, Q] distances (scene units); ``inf`` where two curves are never observed in the same frame.

    Pairs never observed in the same frame are not computed: dynamic tracks live a few frames each, so at 160
    frames most pairs share none and the cost follows the co-observed pairs, not ``P x Q``.
    """
    if a.shape[0] == 0 or a.shape[1] == 0 or b.shape[1] == 0:
        return torch.full((a.shape[1], b.shape[1]), math.inf, dtype=a.dtype, device=a.device)
    return _curve_distance(
        _Curves(a, a_obs, max_frames), _Curves(b, b_obs, max_frames), top_k, max_chunk
    )


def _curve_distance(
    A: _Curves, B: _Curves, top_k: int, max_chunk: int, rows: torch.Tensor | None = None
) -> torch.Tensor:
    """:func:`curve_distance` of the prepared curves ``A`` (or its ``rows``) against all of ``B``: [P, Q]."""
    xa, oa, fa = (A.xyz, A.obs, A.obs_f) if rows is None else (A.xyz[rows], A.obs[rows], A.obs_f[rows])
    P, Qn, Tp = int(xa.shape[0]), len(B), A.frames
    out = torch.full((P, Qn), math.inf, dtype=xa.dtype, device=xa.device)
    if P == 0 or Qn == 0 or Tp == 0:
        return out
    k = min(top_k, Tp)
    block = max(1, max_chunk // max(1, Tp * Qn))
    for s in range(0, P, block):
        e = min(P, s + block)
        # Co-observed frame counts of the block's pairs: sums of 0/1 products, exact in floating point.
        n = (fa[s:e] @ B.obs_f.T).round().long()  # [r, Q]
        pairs = torch.nonzero(n > 0)
        if pairs.shape[0] > n.numel() // 2:
            # Exact differences rather than cdist's matrix-product form, which loses digits on close curves.
            d = torch.linalg.vector_norm(xa[s:e, None] - B.xyz[None], dim=-1)  # [r, Q, T']
            d = d.masked_fill(~(oa[s:e, None] & B.obs[None]), -1.0)  # below every real distance
            out[s:e] = _kth_largest(d, n, k, top_k, Tp)
            continue
        # Short tracks share few frames: most pairs are never co-observed (inf) and cost nothing here.
        per = max(1, max_chunk // max(1, 3 * Tp))
        for c in range(0, pairs.shape[0], per):
            i, j = pairs[c : c + per].unbind(1)
            d = torch.linalg.vector_norm(xa[s + i] - B.xyz[j], dim=-1)  # [S, T']
            d = d.masked_fill(~(oa[s + i] & B.obs[j]), -1.0)
            out[s + i, j] = _kth_largest(d, n[i, j], k, top_k, Tp)
    return out


def _kth_largest(d: torch.Tensor, n: torch.Tensor, k: int, top_k: int, Tp: int) -> torch.Tensor:
    """The ``k_eff``-th largest of ``d`` [..., T'] over frames (unobserved frames hold -1) given ``n`` [...]
    co-observed frames; ``inf`` where ``n`` is 0 (:func:`curve_distance`'s rule)."""
    top = torch.topk(d, k, dim=-1, largest=True, sorted=True).values  # [..., k] descending
    k_eff = torch.ceil(top_k * n.to(d.dtype) / Tp).long()
    k_eff = torch.minimum(torch.minimum(k_eff, n), torch.full_like(n, k)).clamp(min=1)
    val = torch.gather(top, -1, (k_eff - 1)[..., None]).squeeze(-1)
    return torch.where(n > 0, val, torch.full_like(val, math.inf))


@torch.no_grad()
def greedy_select(
    count: int,
    dist_to: Callable[[int], torch.Tensor],
    spacing: float,
    priority: torch.Tensor | None = None,
    max_count: int | None = None,
) -> torch.Tensor:
    """Greedy Poisson-disk subsampling in any metric: [S] long indices, sorted ascending.

    Items are visited in ``priority`` order (descending; ties by index); an item is kept when its distance to
    every kept item is > ``spacing``. ``dist_to(i)`` returns the [count] distances from item i to all items.
    Every item ends within ``spacing`` of a kept one unless ``max_count`` stopped the selection first; kept
    items are pairwise farther than ``spacing``. Cost: one ``dist_to`` call per kept item.
    """
    if count == 0:
        return torch.zeros(0, dtype=torch.long)
    if priority is None:
        order = torch.arange(count)
    else:
        order = torch.sort(priority.detach().cpu().double(), descending=True, stable=True).indices
    rank = torch.empty(count, dtype=torch.long)
    rank[order] = torch.arange(count)
    min_d = torch.full((count,), math.inf, dtype=torch.float64)
    kept: list[int] = []
    limit = count if max_count is None else max(0, max_count)
    while len(kept) < limit:
        uncovered = min_d > spacing
        if not bool(uncovered.any()):
            break
        # The uncovered item that comes first in priority order.
        i = int(torch.where(uncovered, rank, torch.full_like(rank, count)).argmin())
        kept.append(i)
        d = dist_to(i).detach().to("cpu", torch.float64, copy=True)  # never write into the caller's tensor
        d[i] = 0.0
        min_d = torch.minimum(min_d, d)
    return torch.sort(torch.tensor(kept, dtype=torch.long)).values


def _sigma_logit(sigma: float, sigma_max: float, m: int, dtype, device) -> torch.Tensor:
    p = min(max(sigma / sigma_max, 1e-6), 1 - 1e-6)
    return torch.full((m,), math.log(p / (1 - p)), dtype=dtype, device=device)


def _continuous_signs(quat: torch.Tensor) -> torch.Tensor:
    """Flip signs along time [T, M, 4] so consecutive quaternions have a non-negative dot product."""
    if quat.shape[0] < 2:
        return quat
    flip = torch.where((quat[1:] * quat[:-1]).sum(-1) < 0, -1.0, 1.0).to(quat.dtype)
    sign = torch.cat((torch.ones_like(flip[:1]), torch.cumprod(flip, dim=0)), dim=0)
    return quat * sign[..., None]


class Scaffold(nn.Module):
    """Motion scaffold of M nodes over T frames (an :class:`torch.nn.Module`, device-agnostic).

    Parameters (optimisable): ``pos`` [T, M, 3] node positions (scene units), ``quat`` [T, M, 4] node
    rotations (w, x, y, z; any norm, normalised where used; only each node's rotation *relative to another of
    its frames* matters), ``sigma_logit`` [M] with ``sigma = sigma_max * sigmoid(sigma_logit)``.
    Buffers: ``observed`` [T, M] bool (frames where the node's source track was measured), ``knn_idx`` [M, K]
    (column 0 is the node itself), ``edge_valid`` [M, K] bool, and per multi-level ARAP level ``l``
    ``level{l}_idx`` / ``level{l}_valid`` [M, K_l]. ``unit`` (scene units per unit) and ``cfg`` are plain
    attributes. M = 0 (a static scene) is a valid scaffold: every method accepts it and deforms nothing.
    """

    def __init__(
        self,
        pos: torch.Tensor,
        quat: torch.Tensor,
        sigma_logit: torch.Tensor,
        observed: torch.Tensor,
        unit: float,
        cfg: ScaffoldConfig,
        knn_idx: torch.Tensor | None = None,
        edge_valid: torch.Tensor | None = None,
        levels: list[tuple[torch.Tensor, torch.Tensor]] | None = None,
    ) -> None:
        super().__init__()
        T, M = pos.shape[:2]
        if (
            pos.shape != (T, M, 3)
            or quat.shape != (T, M, 4)
            or sigma_logit.shape != (M,)
            or observed.shape != (T, M)
        ):
            raise ValueError(
                f"Scaffold: expected pos [T,M,3], quat [T,M,4], sigma_logit [M], observed [T,M]; got {tuple(pos.shape)}, "
                f"{tuple(quat.shape)}, {tuple(sigma_logit.shape)}, {tuple(observed.shape)}"
            )
        if not unit > 0:
            raise ValueError(f"Scaffold: unit must be > 0, got {unit}")
        self.cfg = cfg
        self.unit = float(unit)
        self.pos = nn.Parameter(pos.detach().clone())
        self.quat = nn.Parameter(quat.detach().clone())
        self.sigma_logit = nn.Parameter(sigma_logit.detach().clone())
        self.register_buffer("observed", observed.detach().bool().clone())
        if knn_idx is None or edge_valid is None or levels is None:
            self.register_buffer("knn_idx", torch.zeros((M, 0), dtype=torch.long, device=pos.device))
            self.register_buffer("edge_valid", torch.zeros((M, 0), dtype=torch.bool, device=pos.device))
            for lv in range(len(cfg.arap_level_units)):
                self.register_buffer(
                    f"level{lv}_idx", torch.zeros((M, 0), dtype=torch.long, device=pos.device)
                )
                self.register_buffer(
                    f"level{lv}_valid", torch.zeros((M, 0), dtype=torch.bool, device=pos.device)
                )
            self.update_topology()
        else:
            self.register_buffer("knn_idx", knn_idx.detach().long().clone())
            self.register_buffer("edge_valid", edge_valid.detach().bool().clone())
            for lv, (li, lval) in enumerate(levels):
                self.register_buffer(f"level{lv}_idx", li.detach().long().clone())
                self.register_buffer(f"level{lv}_valid", lval.detach().bool().clone())

    # ----------------------------------------------------------------- sizes and activations
    @property
    def T(self) -> int:
        return int(self.pos.shape[0])

    @property
    def M(self) -> int:
        return int(self.pos.shape[1])

    @property
    def K(self) -> int:
        return int(self.knn_idx.shape[1])

    @property
    def sigma_max(self) -> float:
        """Largest node radius (scene units)."""
        return self.cfg.sigma_max_units * self.unit

    @property
    def sigma(self) -> torch.Tensor:
        """[M] node radii (scene units), in ``(0, sigma_max)``."""
        return self.sigma_max * torch.sigmoid(self.sigma_logit)

    @classmethod
    def empty(
        cls, T: int, unit: float, cfg: ScaffoldConfig, dtype=torch.float32, device: torch.device | str = "cpu"
    ) -> Scaffold:
        """A scaffold with no node (M = 0) over T frames."""
        return cls(
            torch.zeros((T, 0, 3), dtype=dtype, device=device),
            torch.zeros((T, 0, 4), dtype=dtype, device=device),
            torch.zeros((0,), dtype=dtype, device=device),
            torch.zeros((T, 0), dtype=torch.bool, device=device),
            unit,
            cfg,
        )

    # ----------------------------------------------------------------- topology
    def _obs_for_distance(self, use_observed: bool) -> torch.Tensor | None:
        if not use_observed:
            return None
        # A node never observed (added by densify) has a fully estimated trajectory: trust all its frames.
        obs = self.observed.clone()
        obs[:, ~obs.any(dim=0)] = True
        return obs

    @torch.no_grad()
    def curve_distances(self, use_observed: bool = True) -> torch.Tensor:
        """[M, M] node-to-node curve distances (:func:`curve_distance`), ``inf`` on the diagonal."""
        obs = self._obs_for_distance(use_observed)
        D = curve_distance(
            self.pos.detach(), self.pos.detach(), obs, obs, self.cfg.curve_top_k, self.cfg.curve_max_frames
        )
        D.fill_diagonal_(math.inf)
        return D

    @torch.no_grad()
    def update_topology(self, use_observed: bool = True) -> None:
        """Recompute the KNN graph and the multi-level ARAP graphs from the current trajectories.

        Row i of ``knn_idx`` is ``[i, K-1 nearest other nodes by curve distance]`` (K clamped to M); an edge is
        valid when its distance is below ``edge_max_dist_units``. Level l keeps the node subset resampled at
        ``arap_level_units[l]`` (:func:`greedy_select`, best-observed first) and links every node to its
        ``arap_level_k[l]`` nearest subset nodes other than itself, valid below ``edge_max_dist_units *
        arap_level_units[l]`` (MoSca's level threshold).
        """
        M, dev, cfg = self.M, self.pos.device, self.cfg
        D = self.curve_distances(use_observed)
        k = min(cfg.knn_k, M)  # 0 for an empty scaffold: no column at all
        nn_d, nn_i = torch.topk(D, max(k - 1, 0), dim=1, largest=False, sorted=True)
        self_i = torch.arange(M, device=dev)[:, None][:, : min(k, 1)]
        self.knn_idx = torch.cat((self_i, nn_i), dim=1)
        thr = cfg.edge_max_dist_units * self.unit
        self.edge_valid = torch.cat((torch.ones_like(self_i, dtype=torch.bool), nn_d < thr), dim=1)
        priority = self.observed.sum(dim=0)
        for lv, (units, kl) in enumerate(zip(cfg.arap_level_units, cfg.arap_level_k, strict=True)):
            sub = greedy_select(M, lambda i: D[i], units * self.unit, priority).to(dev)
            kk = min(kl, int(sub.numel()))
            if kk == 0:
                idx = torch.zeros((M, 0), dtype=torch.long, device=dev)
                dist = torch.zeros((M, 0), dtype=D.dtype, device=dev)
            else:
                dist, col = torch.topk(D[:, sub], kk, dim=1, largest=False, sorted=True)
                idx = sub[col]
            setattr(self, f"level{lv}_idx", idx)
            setattr(self, f"level{lv}_valid", dist < thr * units)

    def arap_graphs(self) -> list[ArapGraph]:
        """The base graph (self column dropped, weight 1) followed by the multi-level graphs (their weights,
        neighbours detached), for :func:`worldtree.motion.regularizers.arap_loss`."""
        graphs = [ArapGraph(self.knn_idx[:, 1:], self.edge_valid[:, 1:], 1.0, False)]
        for lv, w in enumerate(self.cfg.arap_level_weights):
            graphs.append(
                ArapGraph(getattr(self, f"level{lv}_idx"), getattr(self, f"level{lv}_valid"), w, True)
            )
        return graphs

    def _levels(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        return [
            (getattr(self, f"level{lv}_idx"), getattr(self, f"level{lv}_valid"))
            for lv in range(len(self.cfg.arap_level_units))
        ]

    # ----------------------------------------------------------------- copies
    def slice_time(self, start: int, end: int) -> Scaffold:
        """A copy with the trajectories of frames ``[start, end)`` (frame ``start`` becomes 0); same nodes,
        radii and graphs (the tree's split keeps every node). Detached from this scaffold's autograd graph."""
        if not 0 <= start < end <= self.T:
            raise ValueError(f"slice_time: need 0 <= start < end <= T={self.T}, got [{start}, {end})")
        return Scaffold(
            self.pos[start:end],
            self.quat[start:end],
            self.sigma_logit,
            self.observed[start:end],
            self.unit,
            self.cfg,
            self.knn_idx,
            self.edge_valid,
            self._levels(),
        )

    def select(self, idx: torch.Tensor) -> Scaffold:
        """A copy keeping the nodes ``idx`` [S] (in that order); the graphs are recomputed."""
        idx = idx.to(self.pos.device).long()
        return Scaffold(
            self.pos[:, idx],
            self.quat[:, idx],
            self.sigma_logit[idx],
            self.observed[:, idx],
            self.unit,
            self.cfg,
        )

    def to_state(self) -> dict:
        """Everything needed to rebuild this scaffold (tensors on their device, config as a plain dict)."""
        state = {k: v.detach().clone() for k, v in self.state_dict().items()}
        return {"tensors": state, "unit": self.unit, "config": asdict(self.cfg)}

    @classmethod
    def from_state(cls, state: dict, device: torch.device | str | None = None) -> Scaffold:
        """Inverse of :meth:`to_state` (optionally onto ``device``)."""
        cfg = ScaffoldConfig(**state["config"])
        t = {k: (v.to(device) if device is not None else v) for k, v in state["tensors"].items()}
        levels = [(t[f"level{lv}_idx"], t[f"level{lv}_valid"]) for lv in range(len(cfg.arap_level_units))]
        return cls(
            t["pos"],
            t["quat"],
            t["sigma_logit"],
            t["observed"],
            state["unit"],
            cfg,
            t["knn_idx"],
            t["edge_valid"],
            levels,
        )

    # ----------------------------------------------------------------- skinning and deformation
    @torch.no_grad()
    def attach(self, points: torch.Tensor, t_ref: torch.Tensor) -> SkinCache:
        """Skinning neighbourhoods of points [N, 3] at their reference frames ``t_ref`` [N] long.

        Each point attaches to its nearest node at its own reference frame (Euclidean), and is skinned by that
        node's graph row (itself and its K-1 graph neighbours, masked by edge validity), as MoSca.
        With M = 0 the neighbourhoods are empty ([N, 0]).
        """
        n = points.shape[0]
        t_ref = t_ref.to(points.device).long().expand(n)
        attach = torch.zeros(n, dtype=torch.long, device=points.device)
        if self.M == 0:
            empty = torch.zeros((n, 0), dtype=torch.long, device=points.device)
            return SkinCache(attach, empty, empty.bool())
        for t in torch.unique(t_ref).tolist():
            m = t_ref == t
            idx, _ = skinning.knn(points[m].detach(), self.pos[t].detach(), 1)
            attach[m] = idx[:, 0]
        return SkinCache(attach, self.knn_idx[attach], self.edge_valid[attach])

    def deform(
        self,
        points: torch.Tensor,
        quats: torch.Tensor,
        t_ref: torch.Tensor,
        t: torch.Tensor | int,
        cache: SkinCache | None = None,
        correction: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Move Gaussians from their reference frames to frame(s) ``t`` by DQB of their nodes' motion.

        Args:
            points: [N, 3] means at their reference frames; quats: [N, 4] rotations (w, x, y, z), norm kept.
            t_ref: [N] long reference frame of each Gaussian; t: int, scalar or [N] long target frame(s).
            cache: :meth:`attach` result for (points, t_ref); computed here when None (no gradient flows
                through the neighbour choice either way).
            correction: [N, K] learned additive skinning-weight correction, or None.

        Returns:
            ``(points_t [N, 3], quats_t [N, 4])``: each neighbour k contributes ``T_k(t) T_k(t_ref)^-1``
            (:func:`worldtree.motion.se3.relative`), blended with the weights of
            :func:`worldtree.motion.skinning.skinning_weights` (``sigma_k``, masked by the graph edges).
            Differentiable in points, quats, node poses, sigma and the correction.
        """
        n = points.shape[0]
        t_ref = t_ref.to(points.device).long().expand(n)
        t_vec = torch.as_tensor(t, device=points.device).long().expand(n)
        if cache is None:
            cache = self.attach(points, t_ref)
        idx = cache.idx
        if torch.as_tensor(t).dim() == 0 and idx.numel() > 0:
            # One target frame: build a table of node motions from their reference frames to t once, as dual
            # quaternions, then gather, instead of composing and converting a transform per (Gaussian,
            # neighbour); the same per-entry arithmetic, and one compiled skinning pass. The table covers every
            # (frame, node) when that is the smaller set, else only the pairs the Gaussians use (a long video
            # with many nodes: 160 x 3,459 entries against 30,000 x 16 pairs). Neighbour values are gathered
            # component-major ([C, N, K]).
            ti = int(t)
            pos, quat, frame, table_idx = self.pos, self.quat, t_ref, idx
            if self.T * self.M > idx.numel():
                pairs, inverse = torch.unique(t_ref[:, None] * self.M + idx, return_inverse=True)
                node = pairs % self.M
                pos = self.pos.reshape(-1, 3).index_select(0, pairs)[None]  # [1, U, 3]
                quat = self.quat.reshape(-1, 4).index_select(0, pairs)[None]
                q_t, p_t = self.quat[ti].index_select(0, node)[None], self.pos[ti].index_select(0, node)[None]
                frame, table_idx = torch.zeros_like(t_ref), inverse.view(idx.shape)
            else:
                q_t, p_t = self.quat[ti][None], self.pos[ti][None]
            real, dual = skinning.relative_dual(q_t, p_t, quat, pos)  # [T, M, 4] or [1, U, 4] each
            return skinning.deform_dual_planes(
                points,
                quats,
                skinning.gather_planes(pos, frame, table_idx),
                self.sigma.index_select(0, idx.reshape(-1)).view(idx.shape),
                skinning.gather_planes(real, frame, table_idx),
                skinning.gather_planes(dual, frame, table_idx),
                cache.valid,
                correction,
                self.cfg.mix_identity,
            )
        else:
            p_ref = skinning.gather_frames(self.pos, t_ref, idx)
            q_ref = skinning.gather_frames(self.quat, t_ref, idx)
            p_t = skinning.gather_frames(self.pos, t_vec, idx)
            q_t = skinning.gather_frames(self.quat, t_vec, idx)
            q_rel, t_rel = se3.relative(q_t, p_t, q_ref, p_ref)
        return skinning.deform_neighbours(
            points,
            quats,
            p_ref,
            self.sigma.index_select(0, idx.reshape(-1)).view(idx.shape),
            q_rel,
            t_rel,
            cache.valid,
            correction,
            self.cfg.mix_identity,
        )


@torch.no_grad()
def _node_rotations(
    pos: torch.Tensor,
    observed: torch.Tensor,
    knn_idx: torch.Tensor,
    edge_valid: torch.Tensor,
    cfg: ScaffoldConfig,
) -> torch.Tensor:
    """[T, M, 4] node rotations by weighted Procrustes of neighbourhoods.

    ``pos`` [T, P, 3] / ``observed`` [T, P]: the points the neighbourhoods index (the tracks); ``knn_idx``,
    ``edge_valid`` [M, K]: node m's neighbourhood (itself included) and which members count.
    """
    T, M = observed.shape[0], knn_idx.shape[0]
    if M == 0:
        return torch.zeros((T, 0, 4), dtype=pos.dtype, device=pos.device)
    t_ref = cfg.rotation_ref_frame
    if t_ref < 0:
        t_ref = int(torch.argmax(observed.sum(dim=1)))
    t_ref = min(t_ref, T - 1)
    nb = pos[:, knn_idx]  # [T, M, K, 3]
    nb_obs = observed[:, knn_idx]  # [T, M, K]
    edge = edge_valid.to(pos.dtype)[None]

    def weights(obs_a: torch.Tensor, obs_b: torch.Tensor) -> torch.Tensor:
        both = obs_a & obs_b
        return edge * torch.where(both, torch.ones_like(edge), torch.full_like(edge, cfg.unobserved_weight))

    if cfg.rotation_mode == "reference":
        fit = se3.procrustes(
            nb[t_ref : t_ref + 1].expand_as(nb), nb, weights(nb_obs[t_ref : t_ref + 1], nb_obs)
        )
        R = fit.rotation
        R[t_ref] = torch.eye(3, dtype=pos.dtype, device=pos.device)
    else:
        R = torch.eye(3, dtype=pos.dtype, device=pos.device).expand(T, M, 3, 3).clone()
        if T > 1:
            # step[t] maps frame t's neighbourhood to frame t+1's; chained outward from the reference frame.
            step = se3.procrustes(nb[:-1], nb[1:], weights(nb_obs[:-1], nb_obs[1:])).rotation
            for t in range(t_ref + 1, T):
                R[t] = step[t - 1] @ R[t - 1]
            for t in range(t_ref - 1, -1, -1):
                R[t] = step[t].transpose(-1, -2) @ R[t + 1]
    return _continuous_signs(Q.from_matrix(R))


@torch.no_grad()
def build_scaffold(
    traj: torch.Tensor, observed: torch.Tensor, scene_scale: float, cfg: ScaffoldConfig | None = None
) -> Scaffold:
    """Build a scaffold from complete 3D trajectories of dynamic tracks.

    Args:
        traj: [T, N, 3] world trajectories with no gap (:func:`worldtree.motion.lift.fill_gaps`).
        observed: [T, N] bool, frames where each track was measured; tracks never observed are ignored.
        scene_scale: scene size in scene units (a unit is ``cfg.unit_ratio * scene_scale``).
        cfg: settings (defaults: :class:`ScaffoldConfig`).

    Steps: nodes = :func:`greedy_select` of the tracks in the curve metric (:func:`curve_distance` on observed
    frames) at ``node_spacing_units``, best-observed tracks first, at most ``max_nodes``; node trajectories =
    those tracks'; KNN graph by curve distance (:meth:`Scaffold.update_topology`); rotations by weighted
    Procrustes of each node's ``rotation_neighbours`` nearest tracks in the curve metric (within
    ``edge_max_dist_units``; ``rotation_mode``); radii ``sigma_init_units``. No dynamic track
    gives an empty scaffold (M = 0).
    """
    cfg = cfg or ScaffoldConfig()
    if traj.dim() != 3 or traj.shape[-1] != 3 or observed.shape != traj.shape[:2]:
        raise ValueError(
            f"build_scaffold: expected traj [T,N,3] and observed [T,N], got {tuple(traj.shape)}, {tuple(observed.shape)}"
        )
    if not (math.isfinite(scene_scale) and scene_scale > 0):
        raise ValueError(f"build_scaffold: scene_scale must be a positive number, got {scene_scale}")
    T = traj.shape[0]
    unit = cfg.unit_ratio * scene_scale
    observed = observed.bool()
    keep = observed.any(dim=0) & torch.isfinite(traj).all(dim=2).all(dim=0)
    cand = torch.nonzero(keep).flatten()
    if cand.numel() == 0 or T == 0:
        return Scaffold.empty(T, unit, cfg, traj.dtype, traj.device)
    c_traj, c_obs = traj[:, cand], observed[:, cand]
    curves = _Curves(c_traj, c_obs, cfg.curve_max_frames)  # prepared once for the one-row queries below

    n_cand = int(cand.numel())
    n_rot = min(cfg.rotation_neighbours, n_cand)
    nearest: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}  # node -> its n_rot nearest tracks

    def dist_to(i: int) -> torch.Tensor:
        row = _curve_distance(curves, curves, cfg.curve_top_k, 1 << 23, torch.tensor([i], device=traj.device))[0]
        d, j = torch.topk(row, n_rot, largest=False, sorted=True)
        nearest[i] = (j, d)
        return row

    sel = greedy_select(n_cand, dist_to, cfg.node_spacing_units * unit, c_obs.sum(dim=0), cfg.max_nodes)
    pos, obs = c_traj[:, sel.to(traj.device)], c_obs[:, sel.to(traj.device)]
    M = pos.shape[1]
    sigma_logit = _sigma_logit(cfg.sigma_init_units, cfg.sigma_max_units, M, traj.dtype, traj.device)
    quat = Q.identity((T, M), dtype=traj.dtype, device=traj.device)
    scf = Scaffold(pos, quat, sigma_logit, obs, unit, cfg)
    # Rotations from each node's nearest *tracks* (denser than the nodes, so neighbourhoods are rarely
    # collinear), within the edge threshold.
    nb_idx = torch.stack([nearest[int(i)][0] for i in sel]).to(traj.device)
    nb_d = torch.stack([nearest[int(i)][1] for i in sel]).to(traj.device)
    nb_valid = nb_d < cfg.edge_max_dist_units * unit
    scf.quat.data = _node_rotations(c_traj, c_obs, nb_idx, nb_valid, cfg)
    return scf


@torch.no_grad()
def resample_nodes(scaffold: Scaffold, spacing_units: float | None = None) -> Scaffold:
    """Thin the nodes to a curve spacing (default ``node_spacing_units``), best-observed first; new graphs.

    Keeps each kept node's trajectory, rotation and radius (a copy; rebuild the optimiser).
    """
    cfg = scaffold.cfg
    spacing = (cfg.node_spacing_units if spacing_units is None else spacing_units) * scaffold.unit
    D = scaffold.curve_distances()
    sel = greedy_select(scaffold.M, lambda i: D[i], spacing, scaffold.observed.sum(dim=0))
    return scaffold.select(sel)


@torch.no_grad()
def densify(scaffold: Scaffold, points: torch.Tensor, t: torch.Tensor) -> tuple[Scaffold, int]:
    """Add nodes where content is far from every node; returns ``(new scaffold, nodes added)``.

    Args:
        points: [P, 3] positions (e.g. Gaussian means at their reference frames, or lifted track points).
        t: [P] long frame of each point.

    A point is *far* when its distance to the nearest node at its frame exceeds ``densify_dist_units``. Far
    points are taken farthest first, skipping those within ``node_spacing_units`` (Euclidean) of one already
    taken, up to ``densify_max_new``. A new node's trajectory is its point carried from its frame to every
    frame by the current scaffold (:meth:`Scaffold.deform` with the identity mix, so a point far from every
    node barely moves); its rotation is the blended rotation (identity at its own frame); its radius the
    initial one; it is never *observed*. With no node at all the new nodes stay still. The graphs are
    recomputed (a never-observed node uses all its frames in curve distances). The result is a new module:
    rebuild the optimiser.
    """
    cfg, unit, T = scaffold.cfg, scaffold.unit, scaffold.T
    dev, dtype = scaffold.pos.device, scaffold.pos.dtype
    points = points.to(dev, dtype)
    t = t.to(dev).long().expand(points.shape[0])
    near = torch.full((points.shape[0],), math.inf, dtype=dtype, device=dev)
    if scaffold.M > 0:
        for f in torch.unique(t).tolist():
            m = t == f
            _, d2 = skinning.knn(points[m], scaffold.pos[f].detach(), 1)
            near[m] = d2[:, 0].sqrt()
    far = torch.nonzero(near > cfg.densify_dist_units * unit).flatten()
    if far.numel() == 0 or cfg.densify_max_new <= 0:
        return scaffold, 0
    order = far[torch.sort(near[far], descending=True, stable=True).indices]
    cand = points[order]
    spacing = cfg.node_spacing_units * unit
    # Priority = the order above (farthest first); greedy_select gives indices into ``order``.
    sel = greedy_select(
        int(order.numel()),
        lambda i: torch.linalg.vector_norm(cand - cand[i], dim=-1),
        spacing,
        -torch.arange(order.numel(), dtype=torch.float64),
        cfg.densify_max_new,
    ).to(dev)
    new_p, new_t = points[order[sel]], t[order[sel]]
    n_new = int(new_p.shape[0])
    if scaffold.M == 0:
        traj = new_p[None].expand(T, n_new, 3).clone()
        rot = Q.identity((T, n_new), dtype=dtype, device=dev)
    else:
        cache = scaffold.attach(new_p, new_t)
        ident = Q.identity((n_new,), dtype=dtype, device=dev)
        traj_l, rot_l = [], []
        for f in range(T):
            p_f, q_f = scaffold.deform(new_p, ident, new_t, f, cache)
            traj_l.append(p_f)
            rot_l.append(q_f)
        traj, rot = torch.stack(traj_l), _continuous_signs(torch.stack(rot_l))
    pos = torch.cat((scaffold.pos.detach(), traj), dim=1)
    quat = torch.cat((scaffold.quat.detach(), rot), dim=1)
    sig = torch.cat(
        (
            scaffold.sigma_logit.detach(),
            _sigma_logit(cfg.sigma_init_units, cfg.sigma_max_units, n_new, dtype, dev),
        )
    )
    obs = torch.cat((scaffold.observed, torch.zeros((T, n_new), dtype=torch.bool, device=dev)), dim=1)
    return Scaffold(pos, quat, sig, obs, unit, cfg), n_new
