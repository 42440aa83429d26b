"""Dynamic Gaussians: a :class:`~worldtree.gaussians.GaussianSet` whose members each live at a canonical
(reference) frame and are carried to any frame by the motion scaffold.

Extra per-Gaussian entries in ``params`` (so density control grows and shrinks them with the rest):

    t_ref     [N]    long, frozen (requires_grad False): the reference frame of each Gaussian
    skin_corr [N, K] optional learned additive correction of the K skinning weights (MoSca)
    t_logstd  [N]    optional learned log of a temporal standard deviation (frames): the opacity at frame t
                     is ``opacity * exp(-(t - t_ref)^2 / (2 std^2))`` (:meth:`DynamicGaussians.opacities_at`)

The mean and rotation stored are those at ``t_ref``; :meth:`DynamicGaussians.at` returns them at frame ``t``
by dual-quaternion blending of the scaffold nodes' motion ``T_k(t) T_k(t_ref)^-1``
(:meth:`worldtree.motion.scaffold.Scaffold.deform`). Scale and colour do not change with time; the opacity
does only with ``t_logstd`` (off by default, the paper's model). With it, a Gaussian lifted at one frame fades
out at frames its carried position does not fit (where the scaffold's motion is wrong, e.g. a surface that
turns away between frames), instead of leaving a blur there; its neighbours in time still see it.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from worldtree.gaussians import GaussianSet
from worldtree.motion.scaffold import Scaffold, SkinCache

TIME_STD = "t_logstd"
"""Name of the optional per-Gaussian log temporal standard deviation (frames) in ``params``."""


class DynamicGaussians(GaussianSet):
    """Gaussians with a reference frame each; see the module docstring."""

    def __init__(self, params):
        # Integer entries (t_ref) cannot require gradients: wrap them as frozen parameters first.
        fixed = {
            k: v
            if isinstance(v, nn.Parameter) or v.is_floating_point()
            else nn.Parameter(v.detach().clone(), requires_grad=False)
            for k, v in params.items()
        }
        if "t_ref" not in fixed:
            raise ValueError("DynamicGaussians needs a 't_ref' entry (reference frame per Gaussian)")
        super().__init__(fixed)

    @classmethod
    def from_points_at(
        cls,
        points: torch.Tensor,
        colors: torch.Tensor,
        t_ref: torch.Tensor,
        init_opacity: float = 0.1,
        skin_k: int = 0,
        time_std: float = 0.0,
    ) -> DynamicGaussians:
        """Isotropic Gaussians at ``points`` [N, 3] (their positions at frames ``t_ref`` [N] long) with RGB
        ``colors`` [N, 3]; ``skin_k > 0`` adds a zero skinning correction [N, skin_k]; ``time_std > 0`` (frames)
        adds the temporal opacity ``t_logstd`` starting at ``log(time_std)``."""
        base = GaussianSet.from_points(points, colors, init_opacity=init_opacity)
        params: dict[str, torch.Tensor] = dict(base.params.items())
        params["t_ref"] = nn.Parameter(t_ref.to(points.device).long().clone(), requires_grad=False)
        if skin_k > 0:
            params["skin_corr"] = torch.zeros(points.shape[0], skin_k, device=points.device)
        if time_std > 0:
            params[TIME_STD] = torch.full((points.shape[0],), math.log(time_std), device=points.device)
        return cls(params)

    @classmethod
    def empty(cls, device: torch.device | str = "cpu", skin_k: int = 0) -> DynamicGaussians:
        """A set with no Gaussian (a static scene)."""
        z = torch.zeros
        params = {
            "means": z(0, 3, device=device),
            "quats": z(0, 4, device=device),
            "log_scales": z(0, 3, device=device),
            "opacity_logits": z(0, device=device),
            "sh0": z(0, 3, device=device),
            "t_ref": nn.Parameter(z(0, dtype=torch.long, device=device), requires_grad=False),
        }
        if skin_k > 0:
            params["skin_corr"] = z(0, skin_k, device=device)
        return cls(params)

    @property
    def t_ref(self) -> torch.Tensor:
        """[N] long reference frame of each Gaussian."""
        return self.params["t_ref"]

    @property
    def skin_correction(self) -> torch.Tensor | None:
        """[N, K] skinning-weight correction, or None."""
        return self.params["skin_corr"] if "skin_corr" in self.params else None

    def opacities_at(self, t: float) -> torch.Tensor:
        """``[N]`` opacities at (possibly fractional) frame ``t``: the stored ones, times the temporal falloff
        ``exp(-(t - t_ref)^2 / (2 std^2))`` when the set has ``t_logstd`` (std clamped to [0.05, 1e4] frames
        so the exponent stays finite)."""
        if TIME_STD not in self.params:
            return self.opacities
        std = self.params[TIME_STD].clamp(math.log(0.05), math.log(1e4)).exp()
        dt = float(t) - self.t_ref.to(std.dtype)
        return self.opacities * torch.exp(-0.5 * (dt / std) ** 2)

    def attach(self, scaffold: Scaffold) -> SkinCache:
        """Skinning neighbourhoods of the current means at their reference frames (no gradient)."""
        return scaffold.attach(self.means.detach(), self.t_ref)

    def at(
        self, scaffold: Scaffold, t: int, cache: SkinCache | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(means [N, 3], quats [N, 4] unit)`` at frame ``t``, differentiable in the Gaussians, the node
        poses, radii and the skinning correction. With no node (M = 0) the stored values come back."""
        if len(self) == 0 or scaffold.M == 0:
            return self.means, self.quats
        corr = self.skin_correction
        if corr is not None and cache is not None and corr.shape[1] != cache.idx.shape[1]:
            corr = None  # the graph's K changed (e.g. fewer nodes than K): the correction no longer lines up
        m, q = scaffold.deform(self.means, self.quats, self.t_ref, t, cache, corr)
        return m, q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    @classmethod
    def load(cls, path, device: torch.device | str = "cpu") -> DynamicGaussians:
        from worldtree.infra.errors import UserError

        data = cls.read_params(path, device)
        if "t_ref" not in data:
            raise UserError(f"{path}: a static Gaussian file (no t_ref); expected dynamic Gaussians")
        return cls(data)


RenderList = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]
"""``(means [N, 3], quats [N, 4], log_scales [N, 3], opacities [N], colours [N, 3])`` for
:func:`worldtree.render.rasterize`."""


def gaussians_at(
    static: GaussianSet,
    dynamic: DynamicGaussians,
    scaffold: Scaffold,
    t: int,
    cache: SkinCache | None = None,
    extra: RenderList | None = None,
) -> RenderList:
    """The one place that assembles what a frame renders: the static Gaussians, then the dynamic ones deformed
    by ``scaffold`` to its frame ``t`` (``cache``: their skinning cache, computed when None), then ``extra``
    (a tree node's ancestors, :func:`worldtree.tree.sac.chain_gaussians_at`), concatenated in that order.
    Differentiable in every input's parameters."""
    dm, dq = dynamic.at(scaffold, t, cache)
    parts = [
        (static.means, static.quats, static.log_scales, static.opacities, static.colors),
        (dm, dq, dynamic.log_scales, dynamic.opacities_at(t), dynamic.colors),
    ]
    if extra is not None:
        parts.append(extra)
    return tuple(torch.cat(xs) for xs in zip(*parts, strict=True))  # type: ignore[return-value]


def between(ga: RenderList, gb: RenderList, opacities: torch.Tensor, frac: float) -> RenderList:
    """The render list ``frac`` of the way from ``ga`` to ``gb``, two render lists of the same Gaussians (e.g.
    one model at frames ``t`` and ``t + 1``): means interpolated linearly, rotations nlerped (``gb``'s flipped
    into ``ga``'s hemisphere first, so antipodal quaternions do not cancel), the given ``opacities`` ``[N]``
    (the caller's, at that time), log-scales and colours of ``ga``."""
    ma, qa, ls, _, c = ga
    mb, qb, _, _, _ = gb
    qb = torch.where((qa * qb).sum(-1, keepdim=True) < 0, -qb, qb)
    q = (1.0 - frac) * qa + frac * qb
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return (1.0 - frac) * ma + frac * mb, q, ls, opacities, c


def path_weights(knots: tuple[int, ...], frac: float) -> tuple[float, ...]:
    """Weights ``w_i`` of the polynomial through values at the integer ``knots`` (frame offsets from frame
    ``a``, distinct, e.g. ``(-1, 0, 1, 2)``), evaluated at offset ``frac``: ``p(frac) = sum_i w_i y_i``
    (Lagrange; they sum to 1, so a point that does not move stays put). Two knots ``(0, 1)`` give the straight
    line ``(1 - frac, frac)``; four give the cubic, exact for a path of degree 3 in time."""
    if len(set(knots)) != len(knots) or not knots:
        raise ValueError(f"path_weights: distinct knots needed, got {knots}")
    out = []
    for i, ki in enumerate(knots):
        w = 1.0
        for j, kj in enumerate(knots):
            if j != i:
                w *= (frac - kj) / (ki - kj)  # knots are distinct integers: no zero division
        out.append(w)
    return tuple(out)


def between_path(lists: dict[int, RenderList], opacities: torch.Tensor, frac: float) -> RenderList:
    """The render list ``frac`` of the way from frame ``a`` to ``a + 1`` along the path through every frame
    given: ``lists`` maps frame offsets (``0`` and ``1`` required, ``-1`` and ``2`` where the model has those
    frames) to render lists of the same Gaussians. Means follow the polynomial through all of them
    (:func:`path_weights`: the cubic through four frames, a parabola through three, the straight line of
    :func:`between` through two), so a path that curves between the frames is followed rather than cut;
    rotations are nlerped between frames ``a`` and ``a + 1`` as in :func:`between`; the given ``opacities``
    ``[N]``; log-scales and colours of frame ``a``."""
    if 0 not in lists or 1 not in lists:
        raise ValueError(f"between_path: frames 0 and 1 are needed, got offsets {sorted(lists)}")
    knots = tuple(sorted(lists))
    m, q, ls, o, c = between(lists[0], lists[1], opacities, frac)
    if len(knots) == 2:
        return m, q, ls, o, c
    weights = path_weights(knots, frac)
    m = sum(w * lists[k][0] for w, k in zip(weights, knots, strict=True))
    return m, q, ls, o, c


def halfway(ga: RenderList, gb: RenderList, opacities: torch.Tensor) -> RenderList:
    """:func:`between` at ``frac = 0.5``: means averaged, rotations nlerped, the caller's ``opacities`` at the
    middle time (e.g. one model at frames ``t - 1`` and ``t + 1`` predicting frame ``t``). Halving is exact in
    floating point, so this is bit for bit ``(ma + mb) / 2`` and the nlerp of ``qa + qb``."""
    return between(ga, gb, opacities, 0.5)
