"""Image tensors: held as read, compared in float.

Rule: a scene's frames stay ``uint8`` in memory (``[T, H, W, 3]``, a quarter of float32's size: 62 MB instead
of 249 MB for 160 frames at 480x270, in the main process and in every tree worker); whatever compares them
with a render converts the frames it uses, one at a time where it can, with :func:`unit_float`. Float
tensors (a test's hand-made scene, a render) pass through unchanged, so every consumer takes either.
"""

from __future__ import annotations

import torch

__all__ = ["as_uint8", "unit_float"]


def unit_float(images: torch.Tensor) -> torch.Tensor:
    """``images`` (any shape) as float32 in [0, 1]: ``uint8`` divided by 255, floating point returned as it
    is (no copy)."""
    if images.dtype == torch.uint8:
        return images.to(torch.float32).div_(255.0)
    if not images.is_floating_point():
        raise TypeError(f"unit_float: expected uint8 or floating-point images, got {images.dtype}")
    return images


def as_uint8(images: torch.Tensor) -> torch.Tensor:
    """``images`` (any shape) as ``uint8``: returned as they are when already ``uint8``, else float in [0, 1]
    clamped, times 255 and rounded (exact for values ``k / 255``, which is what :func:`unit_float` gives).
    The numpy twin, for code that must not load torch: :func:`worldtree.imageio.as_uint8_array`."""
    if images.dtype == torch.uint8:
        return images
    return images.detach().float().clamp(0.0, 1.0).mul(255.0).round_().to(torch.uint8)

