"""Evaluation protocols: a named, versioned recipe turning image pairs (and masks) into per-frame scores.

Each protocol is a :class:`Protocol` subclass in its own module, registered by one line of :data:`PROTOCOLS`
(name -> ``module:Class``; its modules import this one, so the registry names them instead of importing them).
Formulas and the reasons behind every choice are in docs/evaluation.md.
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from typing import Any, ClassVar

import torch

from worldtree.infra.errors import UserError

#: Per-frame metric names every protocol returns, in CSV column order (AVGE columns are added by the caller).
METRICS = ("psnr", "ssim", "lpips", "mpsnr", "mssim", "mlpips")
MASKED = ("mpsnr", "mssim", "mlpips")


class Protocol(ABC):
    """A scoring recipe. Subclasses set the class attributes and implement :meth:`_score`."""

    name: ClassVar[str]  #: registry key, e.g. "worldtree"
    version: ClassVar[str]  #: bumped whenever a number it produces can change
    summary: ClassVar[str]  #: one line for --help and the record
    min_mask_pixels: ClassVar[int] = 1  #: masked SSIM needs at least this many masked pixels (else NaN)
    min_side: ClassVar[int]  #: smallest image side the SSIM window fits in

    @abstractmethod
    def settings(self) -> dict[str, Any]:
        """Every choice that affects the numbers, for the JSON record."""

    @abstractmethod
    def _score(self, pred, gt, mask, lpips) -> dict[str, torch.Tensor]:
        """Per-frame metrics; same arguments as :meth:`score`; masked keys only when ``mask`` is given."""

    def score(
        self, pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None, lpips=None
    ) -> dict[str, torch.Tensor]:
        """Score a batch of frames of one size.

        ``pred``, ``gt``: uint8 [B, H, W, 3] RGB; ``mask``: bool [B, H, W] or None; ``lpips``: a
        :class:`benchmarks.evaluation.lpips.LPIPS` on the images' device, or None. Returns float64 CPU tensors [B] for
        every name in :data:`METRICS`: NaN where not computed (no LPIPS model, no mask) and for every masked
        metric of a frame whose mask is empty. PSNR is +inf for identical inputs.
        """
        if (
            pred.dtype != torch.uint8
            or gt.dtype != torch.uint8
            or pred.shape != gt.shape
            or pred.shape[-1] != 3
        ):
            raise ValueError(
                f"expected two uint8 [B, H, W, 3] tensors, got {pred.dtype} {tuple(pred.shape)} "
                f"and {gt.dtype} {tuple(gt.shape)}"
            )
        if mask is not None and (mask.dtype != torch.bool or mask.shape != pred.shape[:-1]):
            raise ValueError(f"expected a bool [B, H, W] mask, got {mask.dtype} {tuple(mask.shape)}")
        got = self._score(pred, gt, mask, lpips)
        nan = torch.full((pred.shape[0],), float("nan"), dtype=torch.float64)
        out = {k: got[k].detach().to("cpu", torch.float64) if k in got else nan.clone() for k in METRICS}
        if mask is not None:
            empty = (mask.flatten(1).sum(1) == 0).cpu()
            for k in MASKED:
                out[k][empty] = float("nan")
        return out

    def record(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "version": self.version,
            "summary": self.summary,
            "settings": self.settings(),
        }


#: Smallest image side AlexNet (and so LPIPS) accepts: conv 11/4 then two 3/2 max-pools.
LPIPS_MIN_SIDE = 31


def lpips_input(img: torch.Tensor) -> torch.Tensor:
    """uint8-valued [B, 3, H, W] (any dtype, 0..255) -> float32 ``x / 127.5 - 1`` in [-1, 1]."""
    return (img.to(torch.float64) / 127.5 - 1.0).to(torch.float32)


#: The registered protocols, default first: name -> ``"module:Class"`` (the one place a protocol is added).
PROTOCOLS: dict[str, str] = {
    "worldtree": "benchmarks.evaluation.metrics.protocol_worldtree:WorldTreeProtocol",
    "dycheck": "benchmarks.evaluation.metrics.protocol_dycheck:DycheckProtocol",
}
#: Names of the registered protocols, default first.
PROTOCOL_NAMES = tuple(PROTOCOLS)


def get_protocol(name: str) -> Protocol:
    """The registered protocol called ``name``; an unknown name is a :class:`UserError` listing the choices."""
    if name not in PROTOCOLS:
        raise UserError(f"--protocol {name!r} is unknown; use one of: {', '.join(PROTOCOLS)}")
    module, cls_name = PROTOCOLS[name].split(":")
    cls = getattr(importlib.import_module(module), cls_name)
    if cls.name != name:  # a registry line naming the wrong class
        raise TypeError(f"PROTOCOLS[{name!r}] is {cls.__name__}, whose name is {cls.name!r}")
    return cls()
