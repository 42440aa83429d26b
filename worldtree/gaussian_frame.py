"""The Gaussians a method draws at one time, as plain tensors: what ``Method.gaussians_at(time)`` returns.

A :class:`GaussianFrame` is the time-independent description of one rendered frame: every Gaussian the
method rasterizes at that time (static background, dynamic Gaussians carried to the time, a tree node's
ancestors), in the model's own world frame, with the activations the rasterizer uses. It is what
``wtbench export`` writes as a standard 3DGS PLY and what a viewer draws; :func:`render_frame` rasterizes it.

The model's world frame is not the scene's: a dynamic method adjusts the cameras (bundle adjustment), so its
world differs from the given one by the similarity :attr:`GaussianFrame.scene_to_model` (a camera ``w2c``
given in the scene maps to ``scene_to_model.apply_w2c(w2c)``; depths grow by ``scene_to_model.scale``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import torch

from worldtree.gaussians import SH_C0, GaussianSet
from worldtree.render import rasterize
from worldtree.stages.cameras import Sim3, centres

RenderMode = Literal["rgb", "depth", "alpha", "dynamic"]
"""What :func:`render_frame` (and ``Method.render_mode``) returns: ``rgb`` [H, W, 3] in [0, 1]; ``depth``
[H, W] z-depth in the scene's units (NaN where less than half opaque); ``alpha`` [H, W] accumulated
opacity; ``dynamic`` [H, W, 3] the dynamic Gaussians alone, on black."""

RENDER_MODES: tuple[str, ...] = ("rgb", "depth", "alpha", "dynamic")

# Opacities are stored activated; the PLY wants logits. Clamped in float64 so that a float32 opacity of exactly
# 0 or 1 (a temporal falloff underflows to 0) stays finite and its sigmoid in float32 gives the value back.
_LOGIT_EPS = 1e-12


@dataclass
class GaussianFrame:
    """The N Gaussians one method draws at ``time`` (model world frame, see the module docstring).

    All tensors are on one device, float32 (``dynamic`` bool), first dimension N.
    """

    time: int
    """The time index (training-frame index) this frame is of."""
    means: torch.Tensor
    """``[N, 3]`` centres (model world units)."""
    quats: torch.Tensor
    """``[N, 4]`` unit rotations, (w, x, y, z)."""
    log_scales: torch.Tensor
    """``[N, 3]`` natural log of the per-axis standard deviations (model world units): the PLY's ``scale_*``."""
    opacities: torch.Tensor
    """``[N]`` activated opacities in [0, 1] at this time (a dynamic Gaussian's temporal falloff included); the
    PLY stores their logits (:attr:`opacity_logits`)."""
    sh0: torch.Tensor
    """``[N, 3]`` degree-0 spherical-harmonic coefficient (the PLY's ``f_dc_*``): RGB = ``max(0, SH_C0 sh0 +
    0.5)``."""
    dynamic: torch.Tensor
    """``[N]`` bool: drawn by the motion model (dynamic Gaussians and a tree node's ancestors), not the static
    background."""
    scene_to_model: Sim3
    """Similarity from the scene's (given) world frame to this frame's (identity for a static model)."""
    shN: torch.Tensor | None = None
    """``[N, K, 3]`` higher SH coefficients, ``K = (degree + 1)^2 - 1`` (None: view-independent colour)."""
    node: int | None = None
    """The tree node that draws this time (WorldTree), None for methods without a tree."""

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        shapes = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacities": (n,), "sh0": (n, 3),
                  "dynamic": (n,)}  # fmt: skip
        for name, shape in shapes.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"GaussianFrame.{name}: shape {got}, expected {shape}")
        if self.shN is not None and (self.shN.dim() != 3 or self.shN.shape[0] != n or self.shN.shape[2] != 3):
            raise ValueError(f"GaussianFrame.shN: shape {tuple(self.shN.shape)}, expected ({n}, K, 3)")

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def scales(self) -> torch.Tensor:
        """``[N, 3]`` per-axis standard deviations (model world units)."""
        return self.log_scales.exp()

    @property
    def opacity_logits(self) -> torch.Tensor:
        """``[N]`` ``log(p / (1 - p))`` of :attr:`opacities` (computed in float64, ``p`` clamped to
        ``[1e-12, 1 - 1e-12]``), float32: what the 3DGS PLY's ``opacity`` holds."""
        p = self.opacities.double().clamp(_LOGIT_EPS, 1.0 - _LOGIT_EPS)
        return (torch.log(p) - torch.log1p(-p)).float()

    @property
    def colors(self) -> torch.Tensor:
        """``[N, 3]`` view-independent RGB from :attr:`sh0` (as :attr:`GaussianSet.colors`)."""
        return (SH_C0 * self.sh0 + 0.5).clamp_min(0.0)

    def to_gaussian_set(self) -> GaussianSet:
        """The frame as a static :class:`GaussianSet` (raw parameters; what ``write_ply`` writes)."""
        params = {
            "means": self.means,
            "quats": self.quats,
            "log_scales": self.log_scales,
            "opacity_logits": self.opacity_logits.to(self.means.device),
            "sh0": self.sh0,
        }
        if self.shN is not None:
            params["shN"] = self.shN
        return GaussianSet({k: v.detach().float() for k, v in params.items()})

    def view_colors(self, cam_centre: torch.Tensor | None = None) -> torch.Tensor:
        """``[N, 3]`` RGB seen from ``cam_centre [3]`` (model world); view-independent without :attr:`shN`."""
        if self.shN is None or cam_centre is None:
            return self.colors
        return self.to_gaussian_set().view_colors(cam_centre)

    def render_list(self, cam_centre: torch.Tensor | None = None):
        """``(means, quats, log_scales, opacities, colours)`` for :func:`worldtree.render.rasterize`."""
        return self.means, self.quats, self.log_scales, self.opacities, self.view_colors(cam_centre)

    def select(self, keep: torch.Tensor) -> GaussianFrame:
        """The Gaussians of the bool mask ``keep [N]`` (e.g. ``frame.select(frame.dynamic)``)."""
        return dataclasses.replace(
            self,
            means=self.means[keep],
            quats=self.quats[keep],
            log_scales=self.log_scales[keep],
            opacities=self.opacities[keep],
            sh0=self.sh0[keep],
            dynamic=self.dynamic[keep],
            shN=None if self.shN is None else self.shN[keep],
        )

    def to(self, device: torch.device | str) -> GaussianFrame:
        """A copy with every tensor on ``device``."""
        names = ("means", "quats", "log_scales", "opacities", "sh0", "dynamic")
        moved = {f: getattr(self, f).to(device) for f in names}
        return dataclasses.replace(self, **moved, shN=None if self.shN is None else self.shN.to(device))

    def write_ply(self, path) -> None:
        """Write the frame as a standard 3DGS PLY (:meth:`GaussianSet.write_ply`, atomically)."""
        self.to_gaussian_set().write_ply(path)


@torch.no_grad()
def render_frame(
    frame: GaussianFrame,
    K: torch.Tensor,
    w2c: torch.Tensor,
    width: int,
    height: int,
    mode: RenderMode = "rgb",
    backend: str = "auto",
    background: torch.Tensor | None = None,
) -> torch.Tensor:
    """Rasterize ``frame`` from camera ``K [3, 3]`` / ``w2c [4, 4]`` (the model's world frame) as ``mode``
    (:data:`RenderMode`): ``[H, W, 3]`` for ``rgb`` / ``dynamic``, ``[H, W]`` for ``depth`` (scene units,
    NaN where alpha < 0.5) and ``alpha``."""
    if mode not in RENDER_MODES:
        raise ValueError(f"render mode {mode!r}: choose one of {', '.join(RENDER_MODES)}")
    if mode == "dynamic":
        frame = frame.select(frame.dynamic)
    dev = frame.means.device
    K = K.to(dev, torch.float32)
    w2c = w2c.to(dev, torch.float32)
    if len(frame) == 0:  # nothing drawn (a static model's dynamic part): the background alone
        if mode in ("rgb", "dynamic"):
            bg = torch.zeros(3, device=dev) if background is None else background.to(dev, torch.float32)
            return bg.expand(height, width, 3).clone()
        return torch.full((height, width), float("nan") if mode == "depth" else 0.0, device=dev)
    out = rasterize(*frame.render_list(centres(w2c)), K, w2c, width, height, background=background,
                    backend=backend)  # fmt: skip
    if mode in ("rgb", "dynamic"):
        return out.rgb.clamp(0.0, 1.0)
    if mode == "alpha":
        return out.alpha
    z = out.depth / out.alpha.clamp_min(1e-6) / float(frame.scene_to_model.scale)
    return torch.where(out.alpha >= 0.5, z, torch.full_like(z, float("nan")))
