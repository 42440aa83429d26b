"""Photometric coupling of neighbouring training frames through the scaffold's motion.

With temporal opacity (:mod:`worldtree.dynamic`, ``t_logstd``) each frame is drawn mostly by its own dynamic
Gaussians, so the RGB loss of frame ``i`` says little about where the scaffold carries them between frames:
a wrong motion is simply faded out. At a time between two training frames (a held-out frame) both frames'
Gaussians are visible, and a wrong motion shows as a double image. This term asks the motion to explain the
next image: frame ``i``'s picture -- its dynamic Gaussians with their opacities at time ``i`` -- carried by
the scaffold to a neighbouring training frame ``j`` and rendered from camera ``j`` over the (fixed) static
Gaussians must look like image ``j``:

    L_couple = L1(render_j(static, dyn_i carried to j), image_j) + lambda_dssim (1 - SSIM)

- Only the motion learns from it: the scaffold (node poses and radii) and the skinning correction. The
  Gaussians' means at their reference frames, rotations, scales, colours and opacities are detached, so the
  term cannot fit image ``j`` by repainting frame ``i``'s Gaussians or fading them out.
- Frame ``j``'s own Gaussians (``t_ref == j``) are left out: the scaffold does not move them at ``j``
  (``T_k(j) T_k(j)^-1`` is the identity), they would fit image ``j`` whatever the motion. Gaussians whose
  opacity at time ``i`` is negligible (< ``min_opacity``) are left out too (they would not be seen).
- Static Gaussians are rendered detached: they occlude and fill the background, so the error is where the
  carried dynamic picture differs from image ``j`` (the dynamic region and where it lands wrongly).
"""

from __future__ import annotations

import torch

from worldtree.dynamic import DynamicGaussians, RenderList
from worldtree.gaussians import GaussianSet
from worldtree.motion.scaffold import Scaffold, SkinCache


def neighbour(i: int, T: int, k: int) -> int:
    """The training frame next to ``i`` used at the ``k``-th coupling: ``i + 1`` for even ``k``, ``i - 1`` for
    odd ``k``, the only neighbour at either end (``T >= 2``)."""
    if i == 0:
        return 1
    if i == T - 1:
        return T - 2
    return i + 1 if k % 2 == 0 else i - 1


def carried_frame(
    static: GaussianSet,
    dynamic: DynamicGaussians,
    scaffold: Scaffold,
    i: int,
    j: int,
    cache: SkinCache,
    min_opacity: float = 1.0 / 255.0,
    extra: RenderList | None = None,
) -> RenderList | None:
    """Frame ``i``'s picture carried to frame ``j``: the static Gaussians (detached), then the dynamic ones with
    ``t_ref != j`` and opacity at time ``i`` >= ``min_opacity``, deformed to frame ``j``, then ``extra``
    (detached: e.g. a tree node's ancestors as they draw frame ``j``, background like the static set).

    Returns ``(means [N, 3], quats [N, 4], log_scales [N, 3], opacities [N], colours [N, 3])`` for
    :func:`worldtree.render.rasterize`, differentiable only in the scaffold's node poses and radii and in
    the dynamic set's skinning correction; None when no dynamic Gaussian qualifies or the scaffold has no node.
    """
    if len(dynamic) == 0 or scaffold.M == 0:
        return None
    with torch.no_grad():
        op = dynamic.opacities_at(float(i))
        sel = ((op >= min_opacity) & (dynamic.t_ref != j)).nonzero().squeeze(1)
    if sel.numel() == 0:
        return None
    sub = SkinCache(cache.attach[sel], cache.idx[sel], cache.valid[sel])
    corr = dynamic.skin_correction
    if corr is not None and corr.shape[1] != sub.idx.shape[1]:
        corr = None  # the graph's K changed since the correction was made (as DynamicGaussians.at)
    m, q = scaffold.deform(
        dynamic.means.detach()[sel],
        dynamic.quats.detach()[sel],
        dynamic.t_ref[sel],
        j,
        sub,
        None if corr is None else corr[sel],
    )
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    fixed = (static.means, static.quats, static.log_scales, static.opacities, static.colors)
    carried = (m, q, dynamic.log_scales[sel].detach(), op[sel], dynamic.colors[sel].detach())
    after = tuple(x.detach() for x in extra) if extra is not None else None
    return tuple(  # type: ignore[return-value]
        torch.cat([fixed[n].detach(), carried[n]] + ([after[n]] if after is not None else [])) for n in range(5)
    )
