"""Guarded elementwise maths shared by the motion modules (private).

Every helper here is finite in value AND gradient at its singular point, so that a NaN never reaches an
optimiser through ``torch.where`` (which back-propagates into both branches: the branch that is not selected
must still be computed from safe inputs).
"""

from __future__ import annotations

import torch


def taylor_threshold(dtype: torch.dtype) -> float:
    """Argument below which the series (kept through the x^8 term) replace the closed forms.

    ``2 eps^(1/10)`` balances the series truncation error (~x^10 / 4e7) against the cancellation error of the
    closed forms (~eps / x^2): about 0.4 in float32 and 0.055 in float64, both leaving < 1e-6 relative error.
    """
    eps = torch.finfo(dtype).eps if dtype.is_floating_point else torch.finfo(torch.float32).eps
    return 2.0 * eps**0.1


def series(x2: torch.Tensor, coeffs: tuple[float, ...]) -> torch.Tensor:
    """Evaluate ``sum_i coeffs[i] * x2**i`` by Horner's rule (``x2`` is the squared argument)."""
    out = torch.full_like(x2, coeffs[-1])
    for c in reversed(coeffs[:-1]):
        out = out * x2 + c
    return out


def safe_norm(v: torch.Tensor, dim: int = -1, keepdim: bool = False) -> torch.Tensor:
    """Euclidean norm whose gradient is 0 (not NaN) at ``v = 0``.

    The squared norm is clamped below by the smallest normal number, so the result differs from the true norm
    by at most ~1e-19 (float32) and the clamp stops the infinite derivative of ``sqrt`` at 0.
    """
    sq = (v * v).sum(dim=dim, keepdim=keepdim)
    return torch.sqrt(torch.clamp(sq, min=torch.finfo(v.dtype).tiny))


def sinc(x: torch.Tensor) -> torch.Tensor:
    """Unnormalised ``sin(x) / x`` (1 at 0), accurate and with a finite gradient for every ``x``."""
    small = x.abs() < taylor_threshold(x.dtype)
    x_big = torch.where(small, torch.ones_like(x), x)  # keeps the unselected branch finite at x = 0
    x2 = x * x
    return torch.where(
        small, series(x2, (1.0, -1 / 6, 1 / 120, -1 / 5040, 1 / 362880)), torch.sin(x_big) / x_big
    )


def safe_unit(v: torch.Tensor, fallback: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """``v / |v|`` along the last axis; where ``|v| <= eps`` return ``fallback`` (which must be unit length).

    ``fallback`` broadcasts against ``v``. Gradients are finite everywhere (zero through the fallback rows).
    """
    fallback = fallback.expand_as(v)
    ok = (v * v).sum(dim=-1, keepdim=True) > eps * eps
    v_safe = torch.where(ok, v, fallback)
    return v_safe / torch.sqrt((v_safe * v_safe).sum(dim=-1, keepdim=True))


def any_perpendicular(a: torch.Tensor) -> torch.Tensor:
    """A unit vector perpendicular to ``a`` [..., 3] (crosses ``a`` with its least-aligned basis axis).

    Where ``a`` is zero the result is the x axis. Deterministic, not differentiable in a meaningful way.
    """
    idx = a.abs().argmin(dim=-1, keepdim=True)
    basis = torch.zeros_like(a).scatter_(-1, idx, 1.0)
    ex = torch.zeros_like(a)
    ex[..., 0] = 1.0
    return safe_unit(torch.linalg.cross(a, basis, dim=-1), ex)
