"""Unit quaternions for rotations, in the (w, x, y, z) order used by the rasterizer.

All functions take tensors with any leading batch shape ``[..., 4]`` (or ``[..., 3]`` vectors,
``[..., 3, 3]`` matrices) and keep the input's device and dtype. Angles are in radians. A quaternion and its
negative are the same rotation; functions that return a quaternion say which sign they pick.

Every function is finite in value and gradient at its singular points (zero quaternion, zero angle, 180
degrees); the guards are listed in ``docs/motion.md``.
"""

from __future__ import annotations

import torch

from worldtree.motion._safe import any_perpendicular, safe_norm, safe_unit, series, sinc, taylor_threshold

__all__ = [
    "align_sign",
    "angle",
    "angle_between",
    "angle_between_components",
    "angle_between_unit",
    "conjugate",
    "exp",
    "from_axis_angle",
    "from_matrix",
    "from_two_vectors",
    "identity",
    "inverse",
    "log",
    "matrix_from_6d",
    "matrix_to_6d",
    "multiply",
    "multiply_components",
    "normalize",
    "rotate",
    "slerp",
    "standardize",
    "to_matrix",
]


def identity(
    shape: tuple[int, ...] = (), dtype: torch.dtype | None = None, device: torch.device | str | None = None
) -> torch.Tensor:
    """Identity rotations ``(1, 0, 0, 0)`` of shape ``[*shape, 4]``."""
    q = torch.zeros((*shape, 4), dtype=dtype, device=device)
    q[..., 0] = 1.0
    return q


def _identity_like(q: torch.Tensor) -> torch.Tensor:
    return identity((), dtype=q.dtype, device=q.device)


def normalize(q: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Unit quaternion ``q / |q|`` [..., 4]; a quaternion with ``|q| <= eps`` becomes the identity.

    The gradient is finite everywhere (zero for the rows replaced by the identity).
    """
    return safe_unit(q, _identity_like(q), eps)


def standardize(q: torch.Tensor) -> torch.Tensor:
    """Pick the sign with ``w >= 0`` [..., 4] (canonical representative; rotation unchanged)."""
    return torch.where(q[..., :1] < 0, -q, q)


def align_sign(q: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Flip ``q`` [..., 4] where ``dot(q, ref) < 0`` so it lies in ``ref``'s hemisphere (``ref`` broadcasts).

    Same rotations; needed before any linear blend, where ``q`` and ``-q`` would otherwise cancel.
    """
    dot = (q * ref).sum(dim=-1, keepdim=True)
    return torch.where(dot < 0, -q, q)


def multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a * b`` [..., 4] (rotation ``b`` first, then ``a``); shapes broadcast."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def conjugate(q: torch.Tensor) -> torch.Tensor:
    """``(w, -x, -y, -z)`` [..., 4]: the inverse rotation for a unit quaternion."""
    return torch.cat((q[..., :1], -q[..., 1:]), dim=-1)


def inverse(q: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Multiplicative inverse ``conj(q) / |q|^2`` [..., 4]; ``|q| <= eps`` gives the identity."""
    n = normalize(q, eps)
    norm = safe_norm(q, keepdim=True).clamp(min=eps)
    return conjugate(n) / norm


def rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors ``v`` [..., 3] by ``q`` [..., 4] (any norm; normalised here). Shapes broadcast."""
    shape = torch.broadcast_shapes(q.shape[:-1], v.shape[:-1])
    q = normalize(q).expand(*shape, 4)
    v = v.expand(*shape, 3)
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * torch.linalg.cross(u, v, dim=-1)
    return v + w * t + torch.linalg.cross(u, t, dim=-1)


def to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix [..., 3, 3] of ``q`` [..., 4] (any norm; normalised here; zero -> identity)."""
    w, x, y, z = normalize(q).unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = (
        torch.stack((1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)), dim=-1),
        torch.stack((2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)), dim=-1),
        torch.stack((2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)), dim=-1),
    )
    return torch.stack(rows, dim=-2)


def from_matrix(R: torch.Tensor) -> torch.Tensor:
    """Quaternion [..., 4] with ``w >= 0`` of rotation matrices ``R`` [..., 3, 3] (Shepperd's method).

    Of the four algebraically equal formulas, each row uses the one dividing by the largest of
    ``4w^2, 4x^2, 4y^2, 4z^2`` (always >= 1 for a rotation), so no division is ill-conditioned, including at
    180 degrees where ``w = 0``. Slightly non-orthonormal input is tolerated (the result is normalised).
    """
    r00, r01, r02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    r10, r11, r12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    four_sq = torch.stack(
        (1 + r00 + r11 + r22, 1 + r00 - r11 - r22, 1 - r00 + r11 - r22, 1 - r00 - r11 + r22), dim=-1
    )
    # The clamp keeps unselected branches finite (value and gradient); the selected one is >= 1.
    two_c = 2.0 * torch.sqrt(four_sq.clamp(min=0.1))  # 4 * component
    s_w, s_x, s_y, s_z = two_c.unbind(-1)
    cand = torch.stack(
        (
            torch.stack((s_w * s_w / 4, r21 - r12, r02 - r20, r10 - r01), dim=-1) / s_w[..., None],
            torch.stack((r21 - r12, s_x * s_x / 4, r01 + r10, r02 + r20), dim=-1) / s_x[..., None],
            torch.stack((r02 - r20, r01 + r10, s_y * s_y / 4, r12 + r21), dim=-1) / s_y[..., None],
            torch.stack((r10 - r01, r02 + r20, r12 + r21, s_z * s_z / 4), dim=-1) / s_z[..., None],
        ),
        dim=-2,
    )  # [..., 4 branches, 4]; branch c is +-(w, x, y, z) computed by dividing by 4|c|
    pick = four_sq.argmax(dim=-1)[..., None, None].expand(*four_sq.shape[:-1], 1, 4)
    q = torch.gather(cand, -2, pick).squeeze(-2)
    return standardize(normalize(q))


def from_axis_angle(axis: torch.Tensor, angle: torch.Tensor | float) -> torch.Tensor:
    """Quaternion [..., 4] of a rotation by ``angle`` (radians, [...]) about ``axis`` [..., 3] (any norm).

    A zero axis gives the identity.
    """
    angle = torch.as_tensor(angle, dtype=axis.dtype, device=axis.device)
    shape = torch.broadcast_shapes(axis.shape[:-1], angle.shape)
    axis, angle = axis.expand(*shape, 3), angle.expand(shape)[..., None]
    ex = torch.zeros(3, dtype=axis.dtype, device=axis.device)
    ex[0] = 1.0
    n = safe_unit(axis, ex)
    zero = (axis * axis).sum(-1, keepdim=True) <= 1e-24
    half = 0.5 * torch.where(zero, torch.zeros_like(angle), angle)
    return torch.cat((torch.cos(half), torch.sin(half) * n), dim=-1)


def exp(omega: torch.Tensor) -> torch.Tensor:
    """Quaternion [..., 4] of the rotation vector ``omega`` [..., 3] (axis * angle, radians): so(3) exp.

    ``(cos(|w|/2), sin(|w|/2)/|w| * w)`` with ``sin(x)/x`` from a series near 0, so ``omega = 0`` gives the
    identity with a finite gradient (0.5 * I). The sign follows continuously from ``omega`` (``w`` may be < 0
    for angles over pi).
    """
    half = 0.5 * safe_norm(omega, keepdim=True)
    return torch.cat((torch.cos(half), 0.5 * sinc(half) * omega), dim=-1)


def log(q: torch.Tensor) -> torch.Tensor:
    """Rotation vector [..., 3] (axis * angle, angle in [0, pi]) of ``q`` [..., 4] (any norm): so(3) log.

    Uses ``2 atan2(|v|, w) / |v| * v`` on the ``w >= 0`` representative; below a small ``|v|`` the factor
    comes from its series in ``|v| / w``. At exactly 180 degrees either of the two equal answers may come back.
    """
    q = standardize(normalize(q))
    w, v = q[..., :1], q[..., 1:]
    s = safe_norm(v, keepdim=True)
    small = s < taylor_threshold(q.dtype)
    s_big = torch.where(small, torch.ones_like(s), s)
    w_small = torch.where(small, w, torch.ones_like(w))  # w ~ 1 on the small branch; never 0 there
    r2 = (s / w_small) ** 2
    factor_small = 2.0 / w_small * series(r2, (1.0, -1 / 3, 1 / 5, -1 / 7, 1 / 9))
    factor_big = 2.0 * torch.atan2(s_big, w) / s_big
    return torch.where(small, factor_small, factor_big) * v


def angle(q: torch.Tensor) -> torch.Tensor:
    """Rotation angle [...] in [0, pi] of ``q`` [..., 4] (any norm), accurate near 0 and pi."""
    q = normalize(q)
    return 2.0 * torch.atan2(safe_norm(q[..., 1:]), q[..., 0].abs())


def angle_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Geodesic angle [...] in [0, pi] between the rotations ``a`` and ``b`` [..., 4] (any norm;
    sign-independent)."""
    return angle_between_unit(normalize(a), normalize(b))


def angle_between_unit(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """:func:`angle_between` of unit quaternions ``a``, ``b`` [..., 4] (not normalised here; same shape)."""
    return angle_between_components(a.movedim(-1, 0).contiguous(), b.movedim(-1, 0).contiguous())


def angle_between_components(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """:func:`angle_between` of unit quaternions stored component-major, ``a``, ``b`` [4, ...] (w, x, y, z
    first; not normalised here) -> [...].

    The angle of ``r = conj(a) b``, written out: ``r_w = a . b`` and ``r_v = a_w b_v - b_w a_v - a_v x b_v``,
    then ``2 atan2(|r_v|, |r_w|)``, which needs no unit ``r`` (atan2 ignores a common positive factor) and
    stays accurate near 0 and pi. The motion regularisers evaluate it on every node and frame of a scaffold:
    on contiguous components each product is one pass over memory, where :func:`multiply` on the last axis
    works on strided views and stacks the result."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    rw = aw * bw + ax * bx + ay * by + az * bz
    rx = aw * bx - bw * ax - (ay * bz - az * by)
    ry = aw * by - bw * ay - (az * bx - ax * bz)
    rz = aw * bz - bw * az - (ax * by - ay * bx)
    sq = rx * rx + ry * ry + rz * rz
    rv = torch.sqrt(torch.clamp(sq, min=torch.finfo(sq.dtype).tiny))  # safe_norm's guard at r_v = 0
    return 2.0 * torch.atan2(rv, rw.abs())


def multiply_components(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """:func:`multiply` of quaternions stored component-major, ``a``, ``b`` [4, ...] -> [4, ...]."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        )
    )


def slerp(q0: torch.Tensor, q1: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:
    """Spherical linear interpolation [..., 4] from ``q0`` (t=0) to ``q1`` (t=1) along the shorter arc.

    ``q0``, ``q1`` [..., 4] (any norm, normalised here) and ``t`` [...] broadcast. ``q1`` is first moved to
    ``q0``'s hemisphere, so the arc is <= 90 degrees on the sphere (<= 180 degrees of rotation). The weights
    ``sin((1-t) W) / sin W`` are written as ``(1-t) sinc((1-t) W) / sinc W``, finite at ``W = 0`` (identical
    endpoints) without a branch; ``W = 2 atan2(|q0 - q1|, |q0 + q1|)`` stays accurate for tiny arcs where
    ``acos(dot)`` would lose half the digits.
    """
    q0 = normalize(q0)
    q1 = align_sign(normalize(q1), q0)
    t = torch.as_tensor(t, dtype=q0.dtype, device=q0.device)[..., None]
    half_arc = torch.atan2(safe_norm(q0 - q1, keepdim=True), safe_norm(q0 + q1, keepdim=True))
    arc = 2.0 * half_arc  # in [0, pi/2] after sign alignment, so sinc(arc) >= 2/pi
    w0 = (1.0 - t) * sinc((1.0 - t) * arc) / sinc(arc)
    w1 = t * sinc(t * arc) / sinc(arc)
    return normalize(w0 * q0 + w1 * q1)


def from_two_vectors(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Smallest rotation [..., 4] taking the direction of ``a`` to that of ``b`` (both [..., 3], any norm).

    Opposite directions give a 180-degree turn about a deterministic axis perpendicular to ``a``; a zero
    vector gives the identity.
    """
    ex = torch.zeros(3, dtype=a.dtype, device=a.device)
    ex[0] = 1.0
    zero = ((a * a).sum(-1) <= 1e-24) | ((b * b).sum(-1) <= 1e-24)
    ua, ub = safe_unit(a, ex), safe_unit(b, ex)
    cross = torch.linalg.cross(ua, ub, dim=-1)
    # Near-opposite vectors leave a cross product of pure rounding noise; removing its component along ``a``
    # keeps the axis perpendicular to ``a``, which is all a half turn from ``a`` to ``-a`` needs.
    axis = cross - (cross * ua).sum(-1, keepdim=True) * ua
    axis = safe_unit(axis, any_perpendicular(ua), eps=1e-30)
    theta = torch.atan2(safe_norm(cross), (ua * ub).sum(-1))
    theta = torch.where(zero, torch.zeros_like(theta), theta)
    return from_axis_angle(axis, theta)


def matrix_from_6d(d6: torch.Tensor) -> torch.Tensor:
    """Rotation matrix [..., 3, 3] from the continuous 6D representation ``d6`` [..., 6].

    ``d6`` holds the first two COLUMNS of the matrix (Zhou et al. 2019), orthonormalised by Gram-Schmidt.
    Degenerate input (zero or parallel columns) still yields a rotation: missing directions are replaced by
    the x axis or a deterministic perpendicular.
    """
    ex = torch.zeros(3, dtype=d6.dtype, device=d6.device)
    ex[0] = 1.0
    b1 = safe_unit(d6[..., :3], ex)
    a2 = d6[..., 3:]
    b2 = safe_unit(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, any_perpendicular(b1), eps=1e-9)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack((b1, b2, b3), dim=-1)


def matrix_to_6d(R: torch.Tensor) -> torch.Tensor:
    """The 6D representation [..., 6] (first two columns) of rotation matrices ``R`` [..., 3, 3]."""
    return torch.cat((R[..., :, 0], R[..., :, 1]), dim=-1)
