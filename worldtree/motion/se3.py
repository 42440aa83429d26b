"""Rigid transforms SE(3) as (quaternion, translation) pairs, their Lie algebra, and Procrustes fits.

A transform is ``T = (q, t)`` with ``q`` [..., 4] a (w, x, y, z) rotation (any norm; normalised where used)
and ``t`` [..., 3] a translation in scene units; it maps a point by ``T(x) = R(q) x + t``. Leading shapes
broadcast. Twists ``xi`` [..., 6] are ``(rho, omega)``: translational part first, then the rotation vector
(radians), as in Sophus.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from worldtree.motion import quaternion as quat
from worldtree.motion._safe import safe_norm, series, sinc, taylor_threshold

__all__ = [
    "Procrustes",
    "apply",
    "compose",
    "exp",
    "from_matrix",
    "invert",
    "log",
    "procrustes",
    "relative",
    "to_matrix",
]


def compose(
    q1: torch.Tensor, t1: torch.Tensor, q2: torch.Tensor, t2: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``T1 T2`` (apply ``T2`` first): ``(q1 q2, R1 t2 + t1)`` -> ([..., 4] unit, [..., 3])."""
    q1 = quat.normalize(q1)
    return quat.multiply(q1, quat.normalize(q2)), quat.rotate(q1, t2) + t1


def invert(q: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``T^-1 = (q*, -R^T t)`` -> ([..., 4] unit, [..., 3])."""
    qi = quat.conjugate(quat.normalize(q))
    return qi, -quat.rotate(qi, t)


def apply(q: torch.Tensor, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``R(q) x + t`` for points ``x`` [..., 3] (shapes broadcast)."""
    return quat.rotate(q, x) + t


def relative(
    q_t: torch.Tensor, t_t: torch.Tensor, q_ref: torch.Tensor, t_ref: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``T(t) T(t_ref)^-1``: the motion carrying a point attached to a frame from time t_ref to time t.

    For node poses (rotation ``q`` [..., 4], position ``t`` [..., 3]) at the two times, a point ``x`` at
    t_ref is carried to ``R_rel x + t_rel`` with ``R_rel = R(t) R(t_ref)^T`` and
    ``t_rel = t(t) - R_rel t(t_ref)``. Returns ([..., 4] unit, [..., 3]).
    """
    qi, ti = invert(q_ref, t_ref)
    return compose(q_t, t_t, qi, ti)


def to_matrix(q: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Homogeneous matrices [..., 4, 4] of ``(q, t)``."""
    shape = torch.broadcast_shapes(q.shape[:-1], t.shape[:-1])
    R = quat.to_matrix(q).expand(*shape, 3, 3)
    top = torch.cat((R, t.expand(*shape, 3)[..., None]), dim=-1)
    bottom = torch.zeros((*shape, 1, 4), dtype=top.dtype, device=top.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat((top, bottom), dim=-2)


def from_matrix(T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(q, t)`` ([..., 4] with w >= 0, [..., 3]) of homogeneous matrices ``T`` [..., 4, 4] (or [..., 3, 4])."""
    return quat.from_matrix(T[..., :3, :3]), T[..., :3, 3]


def _coef_b(theta: torch.Tensor) -> torch.Tensor:
    """``(theta - sin theta) / theta^3``, series near 0 where the closed form cancels."""
    small = theta < taylor_threshold(theta.dtype)
    th = torch.where(small, torch.ones_like(theta), theta)
    closed = (th - torch.sin(th)) / th**3
    return torch.where(
        small, series(theta * theta, (1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800)), closed
    )


def _coef_c(theta: torch.Tensor) -> torch.Tensor:
    """``(1 - (theta/2) cot(theta/2)) / theta^2`` for theta in [0, pi], series near 0."""
    small = theta < taylor_threshold(theta.dtype)
    th = torch.where(small, torch.ones_like(theta), theta)
    half = 0.5 * th
    closed = (1.0 - half * torch.cos(half) / torch.sin(half)) / (th * th)
    return torch.where(
        small, series(theta * theta, (1 / 12, 1 / 720, 1 / 30240, 1 / 1209600, 1 / 47900160)), closed
    )


def exp(xi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """se(3) exponential of twists ``xi = (rho, omega)`` [..., 6] -> ``(q, t)`` ([..., 4], [..., 3]).

    ``R = exp(omega)``, ``t = V rho`` with ``V = I + A W + B W^2``, ``W = hat(omega)``,
    ``A = (1 - cos th) / th^2 = sinc(th/2)^2 / 2`` (no cancellation) and ``B = (th - sin th) / th^3``
    (series near 0). Finite with a finite gradient at ``omega = 0``.
    """
    rho, omega = xi[..., :3], xi[..., 3:]
    theta = safe_norm(omega, keepdim=True)
    a = 0.5 * sinc(0.5 * theta) ** 2
    b = _coef_b(theta)
    w_rho = torch.linalg.cross(omega, rho, dim=-1)
    t = rho + a * w_rho + b * torch.linalg.cross(omega, w_rho, dim=-1)
    return quat.exp(omega), t


def log(q: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """se(3) logarithm of ``(q, t)`` -> twist ``(rho, omega)`` [..., 6], rotation angle in [0, pi].

    ``omega = log(q)`` and ``rho = V^-1 t = t - W t / 2 + C W^2 t`` with
    ``C = (1 - (th/2) cot(th/2)) / th^2`` (series near 0). Inverse of :func:`exp` for angles below pi.
    """
    omega = quat.log(q)
    theta = safe_norm(omega, keepdim=True)
    c = _coef_c(theta)
    shape = torch.broadcast_shapes(omega.shape[:-1], t.shape[:-1])
    omega, t = omega.expand(*shape, 3), t.expand(*shape, 3)
    w_t = torch.linalg.cross(omega, t, dim=-1)
    rho = t - 0.5 * w_t + c * torch.linalg.cross(omega, w_t, dim=-1)
    return torch.cat((rho, omega), dim=-1)


class Procrustes(NamedTuple):
    """Result of :func:`procrustes`: ``dst ~ scale * rotation @ src + translation``."""

    rotation: torch.Tensor
    """[..., 3, 3] proper rotation (det +1)."""
    translation: torch.Tensor
    """[..., 3] in the units of ``dst``."""
    scale: torch.Tensor
    """[...] similarity scale (1 unless ``with_scale``)."""
    kind: torch.Tensor
    """[...] int8: 0 well posed, 1 collinear (rotation about the line unobservable), 2 no information (zero
    total weight or coincident points: identity rotation)."""


@torch.no_grad()
def procrustes(
    src: torch.Tensor,
    dst: torch.Tensor,
    weights: torch.Tensor | None = None,
    with_scale: bool = False,
    rtol: float | None = None,
) -> Procrustes:
    """Weighted least-squares rigid (or similarity) fit ``min sum_i w_i |s R src_i + t - dst_i|^2``.

    Args:
        src, dst: [..., P, 3] corresponding points (P >= 1).
        weights: [..., P] non-negative weights (default all 1); zero weights drop points (use them as masks).
        with_scale: also fit a similarity scale (Umeyama); otherwise ``scale = 1``.
        rtol: relative singular-value tolerance for the degenerate cases; default ``sqrt(eps)`` of the dtype.

    Kabsch/Umeyama: weighted centroids, cross-covariance ``H = sum w (src - c_s)(dst - c_d)^T = U S V^T``,
    ``R = V diag(1, 1, d) U^T`` with ``d = sign det(V U^T)`` so reflections are never returned. Degenerate
    inputs give finite answers: zero total weight or coincident points (``S_0`` negligible) -> identity
    rotation (and ``t = c_d - c_s``, or 0 without weight); collinear points (``S_1 <= rtol S_0``) -> the
    smallest rotation taking the source line direction onto the target's (one of the equally good
    minimisers, the one nearest the identity).

    This is for initialisation (scaffold node rotations), so it runs without autograd: the SVD has no useful
    gradient at the degenerate inputs it must accept.
    """
    if src.shape[-1] != 3 or dst.shape[-1] != 3:
        raise ValueError(
            f"procrustes: expected [..., P, 3] points, got {tuple(src.shape)} and {tuple(dst.shape)}"
        )
    shape = torch.broadcast_shapes(src.shape, dst.shape)
    src, dst = src.expand(shape), dst.expand(shape)
    if weights is None:
        weights = torch.ones(shape[:-1], dtype=src.dtype, device=src.device)
    w = weights.to(src.dtype).clamp(min=0).expand(shape[:-1])[..., None]  # [..., P, 1]
    rtol = torch.finfo(src.dtype).eps ** 0.5 if rtol is None else rtol
    tiny = torch.finfo(src.dtype).tiny

    w_sum = w.sum(dim=-2)  # [..., 1]
    has_weight = w_sum[..., 0] > tiny
    w_div = w_sum.clamp(min=tiny)
    c_s = (w * src).sum(dim=-2) / w_div
    c_d = (w * dst).sum(dim=-2) / w_div
    a, b = src - c_s[..., None, :], dst - c_d[..., None, :]
    H = (w * a).transpose(-1, -2) @ b  # [..., 3, 3]
    var_a = (w * a * a).sum(dim=(-2, -1))
    var_b = (w * b * b).sum(dim=(-2, -1))

    U, S, Vh = torch.linalg.svd(H)
    V = Vh.transpose(-1, -2)
    d = torch.sign(torch.linalg.det(V @ U.transpose(-1, -2)))
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.ones_like(S)
    D[..., 2] = d
    R_svd = (V * D[..., None, :]) @ U.transpose(-1, -2)

    # S_0 <= sqrt(var_a var_b) (Cauchy-Schwarz), so this compares it with its largest possible value.
    bound = torch.sqrt(var_a * var_b)
    no_info = (~has_weight) | (S[..., 0] <= rtol * bound) | (bound <= tiny)
    collinear = (~no_info) & (S[..., 1] <= rtol * S[..., 0])
    R_line = quat.to_matrix(quat.from_two_vectors(U[..., :, 0], V[..., :, 0]))
    eye = torch.eye(3, dtype=src.dtype, device=src.device).expand_as(R_svd)
    R = torch.where(no_info[..., None, None], eye, torch.where(collinear[..., None, None], R_line, R_svd))
    kind = torch.zeros(shape[:-2], dtype=torch.int8, device=src.device)
    kind = torch.where(collinear, torch.ones_like(kind), kind)
    kind = torch.where(no_info, torch.full_like(kind, 2), kind)

    if with_scale:
        # trace(R^T H) = sum of singular values with the reflection sign (exact for every branch above).
        tr = (R * H.transpose(-1, -2)).sum(dim=(-2, -1))
        scale = torch.where(var_a > tiny, tr / var_a.clamp(min=tiny), torch.ones_like(var_a))
    else:
        scale = torch.ones_like(var_a)
    t = c_d - scale[..., None] * (R @ c_s[..., None])[..., 0]
    t = torch.where(has_weight[..., None], t, torch.zeros_like(t))
    return Procrustes(R, t, scale, kind)
