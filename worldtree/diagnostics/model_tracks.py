"""2D tracks read off a fitted dynamic model: where the scaffold carries each dynamic Gaussian in every frame.

A fitted Base / WorldTree-root model implies a track for every dynamic Gaussian: its centre deformed to frame
``t`` by the scaffold and projected by training camera ``t``. Compared with the exact motion of a generated
scene (``benchmarks.speed.motion_proof``), these tracks say how far the model's motion is right, which the
test-view PSNR alone does not: with temporal opacity a frame is drawn mostly by its own Gaussians, so a wrong
long-range motion can still render well.

A track point is visible at frame ``t`` when it projects inside the image in front of the camera and is not
hidden: its camera depth is at most ``(1 + depth_tol)`` times the model's rendered depth there (where the
rendered opacity is below 0.5 nothing hides it). ``window`` (in temporal standard deviations) also keeps
only the frames where the Gaussian's temporal opacity still draws it (sets without one are unaffected).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from worldtree.dynamic import TIME_STD, DynamicGaussians, gaussians_at
from worldtree.gaussians import GaussianSet
from worldtree.motion.lift import project_points
from worldtree.motion.scaffold import Scaffold
from worldtree.render import rasterize


@dataclass
class ModelTracks:
    """``xy`` [T, N, 2] pixels (OpenCV, pixel centres at integers), ``visible`` [T, N] bool, ``index`` [N]
    long: which dynamic Gaussian each track follows."""

    xy: torch.Tensor
    visible: torch.Tensor
    index: torch.Tensor


def pick_gaussians(
    dynamic: DynamicGaussians, max_tracks: int, min_opacity: float = 0.3, seed: int = 0
) -> torch.Tensor:
    """``[N]`` indices of at most ``max_tracks`` dynamic Gaussians with opacity >= ``min_opacity``, drawn
    uniformly at random (``seed``) and sorted; faint Gaussians draw little and follow nothing measurable."""
    cand = torch.nonzero(dynamic.opacities.detach() >= min_opacity).flatten().cpu()
    if len(cand) > max_tracks:
        g = torch.Generator().manual_seed(seed)
        cand = cand[torch.randperm(len(cand), generator=g)[:max_tracks]].sort().values
    return cand.to(dynamic.means.device)


@torch.no_grad()
def model_tracks(
    static: GaussianSet,
    dynamic: DynamicGaussians,
    scaffold: Scaffold,
    Ks: torch.Tensor,
    w2cs: torch.Tensor,
    width: int,
    height: int,
    index: torch.Tensor,
    depth_tol: float = 0.03,
    window: float | None = None,
) -> ModelTracks:
    """Tracks of the dynamic Gaussians ``index`` [N] over the scaffold's T frames (see the module docstring).

    ``Ks`` [T, 3, 3] and ``w2cs`` [T, 4, 4] are the model's own training cameras (pixels at ``width`` x
    ``height``); ``depth_tol`` is relative; ``window`` in temporal standard deviations, or None."""
    T = scaffold.T
    dev = dynamic.means.device
    index = index.to(dev).long()
    N = len(index)
    xy = torch.zeros(T, N, 2, device=dev)
    vis = torch.zeros(T, N, dtype=torch.bool, device=dev)
    if N == 0:
        return ModelTracks(xy, vis, index)
    cache = dynamic.attach(scaffold)
    t_ref = dynamic.t_ref[index].to(torch.float32)
    std = None
    if window is not None and TIME_STD in dynamic.params:
        std = dynamic.params[TIME_STD][index].clamp(math.log(0.05), math.log(1e4)).exp()  # as opacities_at
    for t in range(T):
        K = Ks[t].to(dev, torch.float32)
        w2c = w2cs[t].to(dev, torch.float32)
        frame = gaussians_at(static, dynamic, scaffold, t, cache)
        means = frame[0][len(static) :]  # gaussians_at puts the static set first
        uv, z = project_points(means[index], K, w2c)  # behind the camera: refused below, finite here
        u, v = uv[:, 0], uv[:, 1]
        xy[t, :, 0], xy[t, :, 1] = u, v
        iu, iv = u.round().long(), v.round().long()
        ok = (z > 1e-6) & (iu >= 0) & (iu < width) & (iv >= 0) & (iv < height)
        out = rasterize(*frame, K, w2c, width, height)
        alpha = out.alpha[iv.clamp(0, height - 1), iu.clamp(0, width - 1)]
        depth = out.depth[iv.clamp(0, height - 1), iu.clamp(0, width - 1)] / alpha.clamp_min(1e-6)
        ok &= (alpha < 0.5) | (z <= depth * (1.0 + depth_tol))
        if std is not None:
            ok &= (t - t_ref).abs() <= window * std
        vis[t] = ok
    return ModelTracks(xy, vis, index)
