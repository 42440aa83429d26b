"""Complete short 3D trajectories beyond their ends with the motion of their neighbours.

Classical dynamic tracks on a rig whose consecutive frames come from different cameras last a few frames each
(median 6 of 40 on the generated demo). Held constant outside that window (:func:`worldtree.motion.lift.fill_gaps`),
a scaffold node built from such a track stands still for most of the video and its Gaussians blur. The object
is usually tracked *somewhere* at every frame, though, by other short tracks: a track's trajectory continues
with the displacement of the nearby tracks that are measured across that step, frame by frame, forward after
its last measured frame and backward before its first (MoSca completes its tracks from the neighbours' motion
too). Gaps inside the measured span are interpolated linearly as before.

For a track ``n`` known at ``t - 1`` and not at ``t`` the donors are the tracks ``m`` whose measured span
(first to last valid frame) holds both ``t - 1`` and ``t``, within ``radius`` of ``x_n(t - 1)`` at ``t - 1``;
``x_n(t) = x_n(t - 1) + sum_m w_m (x_m(t) - x_m(t - 1)) / sum_m w_m`` over the ``k`` nearest, with
``w_m = exp(-d_m^2 / (2 (radius / 2)^2))``. With no donor the point is held for that step (the old
behaviour; a displacement is never borrowed from far away) and the next step tries again.
"""

from __future__ import annotations

import torch

from worldtree.motion.lift import fill_gaps

__all__ = ["complete_trajectories"]


@torch.no_grad()
def _extend(
    x: torch.Tensor, known: torch.Tensor, span: torch.Tensor, frames: range, step: int, radius: float, k: int
) -> None:
    """In place: carry every track known at ``t - step`` and unknown at ``t`` to ``t`` for ``t`` in ``frames``."""
    for t in frames:
        p = t - step
        cand = torch.nonzero(known[p] & ~known[t]).flatten()
        if cand.numel() == 0:
            continue
        donors = torch.nonzero(span[p] & span[t]).flatten()
        disp = torch.zeros(cand.numel(), x.shape[-1], dtype=x.dtype, device=x.device)
        if donors.numel() > 0:
            d = torch.cdist(x[p, cand], x[p, donors])  # [C, D]
            kk = min(k, donors.numel())
            dist, idx = d.topk(kk, dim=1, largest=False)
            sigma = max(radius, 1e-12) / 2.0
            w = torch.exp(-(dist**2) / (2.0 * sigma * sigma)) * (dist <= radius)
            step_d = (x[t, donors] - x[p, donors])[idx]  # [C, kk, 3]
            tot = w.sum(1, keepdim=True)
            disp = torch.where(tot > 0, (w[..., None] * step_d).sum(1) / tot.clamp_min(1e-12), disp)
        x[t, cand] = x[p, cand] + disp
        known[t, cand] = True


@torch.no_grad()
def complete_trajectories(
    points: torch.Tensor, valid: torch.Tensor, radius: float, k: int = 8
) -> tuple[torch.Tensor, torch.Tensor]:
    """Fill every frame of every trajectory (see the module docstring).

    Args:
        points: [T, N, C] measured positions (world units), anything where ``valid`` is False.
        valid: [T, N] bool, measured frames.
        radius: donors farther than this (world units, at the frame before the step) are not used; <= 0 gives
            :func:`worldtree.motion.lift.fill_gaps` (held ends).
        k: most donors per step.

    Returns:
        ``(filled [T, N, C], observed [T, N] bool)``: measured frames exactly as given; ``observed`` is a copy of
        ``valid``. Tracks with no valid frame stay 0. No gradient flows (a preprocessing step).
    """
    filled, observed = fill_gaps(points.detach(), valid)
    T, N = valid.shape
    if radius <= 0 or T < 2 or N == 0:
        return filled, observed
    v = valid.bool()
    frames = torch.arange(T, device=v.device)[:, None]
    first = torch.where(v, frames, torch.full_like(frames, T)).amin(0)
    last = torch.where(v, frames, torch.full_like(frames, -1)).amax(0)
    span = (frames >= first[None]) & (frames <= last[None])  # [T, N] inside the measured span
    x = filled.clone()
    known = span.clone()
    _extend(x, known, span, range(1, T), 1, float(radius), int(k))
    _extend(x, known, span, range(T - 2, -1, -1), -1, float(radius), int(k))
    return x, observed
