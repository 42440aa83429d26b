"""EWA projection of 3D Gaussians to screen-space ellipses, in differentiable PyTorch.

Used by the reference backend and as the autograd oracle of the C++ projection (csrc/rasterize_cpu.cpp), which
implements the same formulas for the compiled backend.

Pixel convention (OpenCV): pixel (row i, column j) has its centre at (u, v) = (j, i); a camera point (x, y, z)
lands at u = fx x / z + cx, v = fy y / z + cy. The skew term K[0, 1] is ignored.

Culled Gaussians (behind the near plane, non-finite parameters, zero-norm quaternion, degenerate 2D covariance,
bounding square off the image) get radius 0. Their outputs are zeros and, because every quantity is computed
from sanitised stand-in values, their gradients are exactly zero and finite.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

TILE = 16  # tile edge in pixels (classic 3DGS)
RADIUS_CAP = float(2**24)  # pixels; keeps radii representable as int32 and tile maths exact in float32


@dataclass
class Projection:
    """Screen-space Gaussians, one row per input Gaussian."""

    means2d: Tensor  # [N, 2] pixel coordinates (u, v), zeros where culled
    conics: Tensor  # [N, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]], 1/px^2
    depths: Tensor  # [N] camera-space z (world units), zeros where culled
    radii: Tensor  # [N] int32 pixels, ceil(3 sqrt(largest eigenvalue)); 0 = culled


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Unit quaternions [N, 4] (w, x, y, z) -> rotation matrices [N, 3, 3]."""
    w, x, y, z = quats.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, -1).reshape(quats.shape[:-1] + (3, 3))


def _project_cam(p, quats, log_scales, K, R, width, height, eps2d):
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    x, y, z = p.unbind(-1)
    rz = 1.0 / z
    # Clamp the direction used by the Jacobian (as 3DGS and gsplat do) so that Gaussians far outside the
    # frustum do not get enormous screen footprints from the linearisation.
    tan_x = 0.5 * width / fx
    tan_y = 0.5 * height / fy
    lim_x_pos = (width - 0.5 - cx) / fx + 0.3 * tan_x
    lim_x_neg = (cx + 0.5) / fx + 0.3 * tan_x
    lim_y_pos = (height - 0.5 - cy) / fy + 0.3 * tan_y
    lim_y_neg = (cy + 0.5) / fy + 0.3 * tan_y
    tx = z * torch.minimum(torch.maximum(x * rz, -lim_x_neg), lim_x_pos)
    ty = z * torch.minimum(torch.maximum(y * rz, -lim_y_neg), lim_y_pos)
    Rq = quat_to_rotmat(quats / quats.norm(dim=-1, keepdim=True))
    s = torch.exp(log_scales)
    # B = J R Rq with the perspective Jacobian J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]], and
    # A = J R Rq diag(s) = B diag(s); cov2d = A A^T is a Gram matrix, hence symmetric positive semi-definite.
    Bq = R @ Rq
    B0 = (fx * rz)[:, None] * Bq[:, 0] - (fx * tx * rz * rz)[:, None] * Bq[:, 2]  # [N, 3]
    B1 = (fy * rz)[:, None] * Bq[:, 1] - (fy * ty * rz * rz)[:, None] * Bq[:, 2]
    A0, A1 = B0 * s, B1 * s
    sq0, sq1 = (A0 * A0).sum(-1), (A1 * A1).sum(-1)
    a, b, c = sq0 + eps2d, (A0 * A1).sum(-1), sq1 + eps2d
    # det = a c - b^2 without its cancellation (rounding noise of either sign for large thin footprints):
    # det(A A^T) = sum over column pairs of (s_i s_j minor_ij(B))^2 (Cauchy-Binet), plus the positive eps2d
    # terms. The C++ projection computes it the same way.
    minors = torch.stack(
        [
            s[:, 0] * s[:, 1] * (B0[:, 0] * B1[:, 1] - B0[:, 1] * B1[:, 0]),
            s[:, 0] * s[:, 2] * (B0[:, 0] * B1[:, 2] - B0[:, 2] * B1[:, 0]),
            s[:, 1] * s[:, 2] * (B0[:, 1] * B1[:, 2] - B0[:, 2] * B1[:, 1]),
        ],
        -1,
    )
    det = (minors * minors).sum(-1) + eps2d * (sq0 + sq1) + eps2d * eps2d
    means2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], -1)
    return means2d, torch.stack([a, b, c], -1), z, det


def _rotate(v: Tensor, R: Tensor) -> Tensor:
    """v [N, 3] -> v R^T (rotate row vectors)."""
    return v @ R.T


def _radius(cov2d: Tensor, det: Tensor) -> Tensor:
    a, _, c = cov2d.unbind(-1)
    mid = 0.5 * (a + c)
    lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
    return torch.ceil(3.0 * torch.sqrt(lam))


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    K: Tensor,
    w2c: Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    eps2d: float = 0.3,
    keep: Tensor | None = None,
) -> Projection:
    """Project Gaussians with the EWA approximation; differentiable w.r.t. means, quats, log_scales and w2c.

    means [N, 3], quats [N, 4] (w, x, y, z), log_scales [N, 3] (log world-unit std-devs), K [3, 3] pixel
    intrinsics, w2c [4, 4] OpenCV world-to-camera. ``near`` (world units) culls Gaussians with z <= near;
    ``eps2d`` (px^2) is added to the diagonal of every 2D covariance (screen-space dilation). ``keep`` [N] bool
    marks further Gaussians to cull (False), e.g. those with non-finite opacity or colour.
    """
    n = means.shape[0]
    with torch.no_grad():
        # Pass 1, no autograd: decide who survives, on sanitised inputs so that nothing raises or warns.
        ok = (
            torch.isfinite(means).all(-1)
            & torch.isfinite(quats).all(-1)
            & torch.isfinite(log_scales).all(-1)
            & (quats.norm(dim=-1) > 1e-8)
        )
        if keep is not None:
            ok &= keep
        m0, q0, s0 = _sanitise(means, quats, log_scales, ok)
        R = w2c[:3, :3]
        p = _rotate(m0, R) + w2c[:3, 3]
        ok &= torch.isfinite(p).all(-1) & (p[:, 2] > near)
        p = torch.where(ok[:, None], p, _safe_point(p))
        mu, cov, _, det = _project_cam(p, q0, s0, K, R, width, height, eps2d)
        ok &= torch.isfinite(cov).all(-1) & torch.isfinite(mu).all(-1) & (det > 0)
        ok &= torch.isfinite(cov[:, 2] / det) & torch.isfinite(cov[:, 0] / det)
        r = torch.where(ok, _radius(cov, det), torch.zeros_like(det))
        r = torch.clamp(torch.nan_to_num(r, nan=0.0), max=RADIUS_CAP)
        ok &= r > 0
        # Bounding square must touch a tile of the image (same rule the rasterizers use to bin).
        x0, x1, y0, y1 = tile_rect(mu, r, width, height)
        ok &= (x1 > x0) & (y1 > y0)
        radii = torch.where(ok, r, torch.zeros_like(r)).to(torch.int32)

    # Pass 2, differentiable, on the survivors only: culled rows are never touched, so their gradients are
    # exactly zero, and survivors have finite, positive-determinant covariances by construction.
    all_ok = bool(ok.all())
    idx = None if all_ok else torch.nonzero(ok).squeeze(1)

    def gather(t: Tensor) -> Tensor:
        return t if idx is None else t[idx]

    def scatter(values: Tensor, cols: int) -> Tensor:
        if idx is None:
            return values
        shape = (n, cols) if cols else (n,)
        out = torch.zeros(shape, dtype=values.dtype, device=values.device)
        return out.index_put((idx,), values)

    R = w2c[:3, :3]
    p = _rotate(gather(means), R) + w2c[:3, 3]
    mu, cov, z, det = _project_cam(p, gather(quats), gather(log_scales), K, R, width, height, eps2d)
    a, b, c = cov.unbind(-1)
    conics = torch.stack([c / det, -b / det, a / det], -1)

    return Projection(means2d=scatter(mu, 2), conics=scatter(conics, 3), depths=scatter(z, 0), radii=radii)


def _safe_point(p: Tensor) -> Tensor:
    """A point straight ahead of the camera at unit depth (a stand-in for culled Gaussians), shape like p."""
    s = torch.zeros_like(p)
    s[:, 2] = 1.0
    return s


def _sanitise(means, quats, log_scales, ok):
    """Replace the parameters of culled Gaussians by benign values (origin, identity, unit scale)."""
    okc = ok[:, None]
    ident = torch.zeros_like(quats)
    ident[:, 0] = 1.0
    return (
        torch.where(okc, means, torch.zeros_like(means)),
        torch.where(okc, quats, ident),
        torch.where(okc, log_scales, torch.zeros_like(log_scales)),
    )


def tile_rect(
    means2d: Tensor, radii: Tensor, width: int, height: int
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Tiles touched by each Gaussian's bounding square: half-open ranges [x0, x1) x [y0, y1) (int64, [N]).

    Tile tx covers pixel columns 16 tx .. 16 tx + 15, i.e. u in [16 tx - 0.5, 16 tx + 15.5). The C++ kernel
    uses the same formula in the same precision.
    """
    tw = (width + TILE - 1) // TILE
    th = (height + TILE - 1) // TILE
    r = radii.to(means2d.dtype)
    u = means2d[:, 0] + 0.5
    v = means2d[:, 1] + 0.5
    x0 = torch.clamp(torch.floor((u - r) / TILE), 0, tw).long()
    x1 = torch.clamp(torch.ceil((u + r) / TILE), 0, tw).long()
    y0 = torch.clamp(torch.floor((v - r) / TILE), 0, th).long()
    y1 = torch.clamp(torch.ceil((v + r) / TILE), 0, th).long()
    return x0, x1, y0, y1
