"""Unit dual quaternions and dual-quaternion blending (DQB) of rigid transforms.

A dual quaternion is a pair ``(real, dual)`` of [..., 4] (w, x, y, z) tensors. The rigid transform
``x -> R(q) x + t`` is ``real = q``, ``dual = 0.5 (0, t) q``; ``t = 2 vec(dual conj(real))``. Leading shapes
broadcast; the device and dtype of the inputs are kept. See ``docs/motion.md`` for the formulas and guards.
"""

from __future__ import annotations

import torch

from worldtree.motion import quaternion as quat

__all__ = [
    "apply_points",
    "apply_rotations",
    "blend",
    "blend_dual",
    "conjugate",
    "dual_conjugate",
    "from_quat_trans",
    "multiply",
    "normalize",
    "to_quat_trans",
]

DualQuat = tuple[torch.Tensor, torch.Tensor]


def _pure(v: torch.Tensor) -> torch.Tensor:
    """The pure quaternion ``(0, v)`` [..., 4] of vectors ``v`` [..., 3]."""
    return torch.cat((torch.zeros_like(v[..., :1]), v), dim=-1)


def from_quat_trans(q: torch.Tensor, t: torch.Tensor) -> DualQuat:
    """Unit dual quaternion of the transform ``(q, t)`` (``q`` [..., 4] any norm, ``t`` [..., 3])."""
    shape = torch.broadcast_shapes(q.shape[:-1], t.shape[:-1])
    real = quat.normalize(q).expand(*shape, 4)
    return real, 0.5 * quat.multiply(_pure(t.expand(*shape, 3)), real)


def normalize(real: torch.Tensor, dual: torch.Tensor, eps: float = 1e-12) -> DualQuat:
    """Nearest unit dual quaternion: ``real / |real|`` and ``dual / |real|`` made orthogonal to ``real``.

    A real part with ``|real| <= eps`` becomes the identity (and the dual part zero).
    """
    n2 = (real * real).sum(-1, keepdim=True)
    ok = n2 > eps * eps
    real_s = torch.where(ok, real, quat.identity((), real.dtype, real.device))
    dual_s = torch.where(ok, dual, torch.zeros_like(dual))
    n = torch.sqrt((real_s * real_s).sum(-1, keepdim=True))
    r, d = real_s / n, dual_s / n
    return r, d - (r * d).sum(-1, keepdim=True) * r


def to_quat_trans(
    real: torch.Tensor, dual: torch.Tensor, eps: float = 1e-12
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(q, t)`` ([..., 4] unit, [..., 3]) of a (possibly unnormalised) dual quaternion.

    ``q = real / |real|`` and ``t = 2 vec(dual conj(real)) / |real|^2``; the vector part ignores the
    component of ``dual`` along ``real``, which is exactly what normalisation would remove. ``|real| <= eps``
    gives the identity.
    """
    r, d = normalize(real, dual, eps)
    return r, 2.0 * quat.multiply(d, quat.conjugate(r))[..., 1:]


def multiply(
    a_real: torch.Tensor, a_dual: torch.Tensor, b_real: torch.Tensor, b_dual: torch.Tensor
) -> DualQuat:
    """Product ``a b`` (transform ``b`` applied first): ``(a_r b_r, a_r b_d + a_d b_r)``."""
    return quat.multiply(a_real, b_real), quat.multiply(a_real, b_dual) + quat.multiply(a_dual, b_real)


def conjugate(real: torch.Tensor, dual: torch.Tensor) -> DualQuat:
    """Quaternion conjugate ``(real*, dual*)``: the inverse transform for a unit dual quaternion."""
    return quat.conjugate(real), quat.conjugate(dual)


def dual_conjugate(real: torch.Tensor, dual: torch.Tensor) -> DualQuat:
    """Dual-number conjugate ``(real, -dual)``."""
    return real, -dual


def apply_points(q: torch.Tensor, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Move points ``x`` [..., 3] by the rigid transform ``(q, t)`` (e.g. a :func:`blend` result)."""
    return quat.rotate(q, x) + t


def apply_rotations(q: torch.Tensor, rot: torch.Tensor) -> torch.Tensor:
    """Rotate orientations ``rot`` [..., 4] (any norm, kept) by ``q`` [..., 4] unit: ``q rot``."""
    return quat.multiply(q, rot)


def blend(
    q: torch.Tensor,
    t: torch.Tensor,
    weights: torch.Tensor,
    mix_identity: bool = True,
    align: bool = True,
    eps: float = 1e-12,
    degenerate_tol: float = 1e-6,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Dual-quaternion linear blending of K rigid transforms per item -> one rigid transform per item.

    Args:
        q: [..., K, 4] rotations of the transforms (any norm; either sign).
        t: [..., K, 3] translations.
        weights: [..., K] raw (unnormalised) weights, e.g. skinning weights with masked entries at 0.
        mix_identity: blend ``alpha sum_k w_k/W dq_k + (1 - alpha) dq_identity`` with ``W = sum_k w_k`` and
            ``alpha = clamp(W, 0, 1)`` (MoSca): items far from every node (``W -> 0``) stay put. Otherwise
            the normalised weights alone are used.
        align: move every ``q_k`` to the hemisphere of the pivot (the neighbour with the largest weight,
            itself taken with ``w >= 0`` so the identity term agrees with it) before blending. Turning this
            off is only useful to test the guard below.
        eps: floor of ``W`` in the division ``w_k / W``.
        degenerate_tol: if the blended real part has norm below this (possible only with negative weights
            or ``align=False``, e.g. antipodal inputs), the pivot's own transform is returned instead.

    Returns:
        ``(q, t)``: [..., 4] unit rotation and [..., 3] translation. With all K transforms equal (and
        ``W >= 1`` or ``mix_identity=False``) the result is that transform exactly; the result does not depend
        on the sign of any input ``q_k``. Gradients are finite everywhere, including the guarded cases.
    """
    real, dual = from_quat_trans(q, t)  # [..., K, 4] each
    return blend_dual(real, dual, weights, mix_identity, align, eps, degenerate_tol)


def blend_dual(
    real: torch.Tensor,
    dual: torch.Tensor,
    weights: torch.Tensor,
    mix_identity: bool = True,
    align: bool = True,
    eps: float = 1e-12,
    degenerate_tol: float = 1e-6,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`blend` for transforms already given as unit dual quaternions ``real, dual`` [..., K, 4].

    Lets a caller convert each scaffold node once and gather the results per Gaussian, instead of converting
    every (Gaussian, neighbour) pair. Same arguments, guarantees and return value as :func:`blend`.
    """
    k = real.shape[-2]
    if k == 0:
        ident = quat.identity(real.shape[:-2], real.dtype, real.device)
        return ident, torch.zeros((*real.shape[:-2], 3), dtype=real.dtype, device=real.device)
    weights = weights.to(real.dtype).expand(real.shape[:-1])

    pivot_idx = weights.argmax(dim=-1)[..., None, None].expand(*real.shape[:-2], 1, 4)
    piv_real = torch.gather(real, -2, pivot_idx)  # [..., 1, 4]
    piv_dual = torch.gather(dual, -2, pivot_idx)
    piv_sign = torch.where(piv_real[..., :1] < 0, -1.0, 1.0).to(real.dtype)
    piv_real, piv_dual = piv_real * piv_sign, piv_dual * piv_sign
    if align:
        # q and -q are one rotation; the dual part must flip with the real part to stay the same transform.
        sign = torch.where((real * piv_real).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(real.dtype)
        real, dual = real * sign, dual * sign

    w_sum = weights.sum(dim=-1, keepdim=True)  # [..., 1]
    coef = weights / w_sum.clamp(min=eps)  # normalised weights; the clamp keeps W -> 0 finite
    b_real = (coef[..., None] * real).sum(dim=-2)
    b_dual = (coef[..., None] * dual).sum(dim=-2)
    if mix_identity:
        alpha = w_sum.clamp(0.0, 1.0)
        b_real = alpha * b_real + (1.0 - alpha) * quat.identity((), real.dtype, real.device)
        b_dual = alpha * b_dual

    degenerate = (b_real * b_real).sum(-1, keepdim=True) < degenerate_tol**2
    b_real = torch.where(degenerate, piv_real[..., 0, :], b_real)
    b_dual = torch.where(degenerate, piv_dual[..., 0, :], b_dual)
    return to_quat_trans(b_real, b_dual, eps)
