"""What the viewer shows, without viser: time slider -> time index, render mode -> image, image encoding."""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

#: Render modes in the order of the viewer's menu: label shown -> what the source renders.
MODES: dict[str, str] = {
    "colour": "rgb",
    "depth": "depth",
    "dynamic part": "dynamic",
    "tree node": "rgb",  # the colour image tinted with the colour of the tree node that renders this time
}
#: Modes that need a source with tree nodes (:meth:`ViewSource.node_label` not None).
TREE_MODES = ("tree node",)
#: How strongly the tree-node mode tints the colour image (0: not at all, 1: flat node colour).
NODE_TINT = 0.45
#: JPEG quality of the previews sent while the camera moves (still images are PNG, lossless).
PREVIEW_JPEG_QUALITY = 80
# Distinct, saturated colours for tree nodes (a node keeps its colour: picked by a checksum of its label).
_PALETTE = np.array(
    [
        [230, 25, 75], [60, 180, 75], [255, 225, 25], [0, 130, 200], [245, 130, 48], [145, 30, 180],
        [70, 240, 240], [240, 50, 230], [210, 245, 60], [250, 190, 212], [0, 128, 128], [170, 110, 40],
    ],
    dtype=np.uint8,
)  # fmt: skip


def time_index(value: float, count: int) -> int:
    """Index into the run's times (``0 .. count-1``) of a time-slider ``value`` (rounded, clamped)."""
    if count <= 0:
        raise ValueError("a run without times has nothing to show")
    return int(min(max(round(float(value)), 0), count - 1))


def next_time_index(index: int, count: int) -> int:
    """The index shown after ``index`` while playing: the next one, wrapping to the first after the last."""
    return (index + 1) % count


def modes_for(has_tree: bool) -> list[str]:
    """Menu labels of the render modes a source offers (the tree-node mode only for a tree method)."""
    return [m for m in MODES if has_tree or m not in TREE_MODES]


def to_uint8(rgb) -> np.ndarray:
    """``uint8 [H, W, 3]`` of an RGB image in [0, 1] (tensor or array ``[H, W, 3]``): clamped, then
    ``floor(x * 255 + 0.5)``, the rounding ``wtbench run`` writes its test renders with."""
    arr = _numpy(rgb).astype(np.float32)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"expected an RGB image [H, W, 3], got shape {arr.shape}")
    return (np.clip(arr, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def colourise_depth(depth) -> np.ndarray:
    """``uint8 [H, W, 3]`` of a depth map ``[H, W]`` or ``[H, W, 1]`` (world units; 0, negative or non-finite:
    nothing rendered there, shown black): turbo colours from near (red) to far (blue) over the 2nd..98th
    percentile of this image's depths, so a far outlier does not flatten the rest."""
    from matplotlib import colormaps

    d = _numpy(depth).astype(np.float64)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[..., 0]
    if d.ndim != 2:
        raise ValueError(f"expected a depth map [H, W], got shape {d.shape}")
    valid = np.isfinite(d) & (d > 0)
    out = np.zeros((*d.shape, 3), dtype=np.uint8)
    if not valid.any():
        return out
    lo, hi = np.percentile(d[valid], [2.0, 98.0])
    t = np.clip((hi - d[valid]) / max(hi - lo, 1e-12), 0.0, 1.0)  # near -> 1
    out[valid] = (colormaps["turbo"](t)[:, :3] * 255.0 + 0.5).astype(np.uint8)
    return out


def node_colour(label: str) -> np.ndarray:
    """``uint8 [3]`` colour of the tree node called ``label`` (the same label always gets the same colour)."""
    return _PALETTE[zlib.crc32(label.encode()) % len(_PALETTE)]


def tint(image: np.ndarray, colour: np.ndarray, amount: float = NODE_TINT) -> np.ndarray:
    """``uint8 [H, W, 3]``: ``image`` blended towards the flat ``colour [3]`` by ``amount`` in [0, 1]."""
    mixed = (1.0 - amount) * image.astype(np.float32) + amount * colour.astype(np.float32)[None, None]
    return (mixed + 0.5).astype(np.uint8)


def to_display(rendered, mode: str, node_label: str | None = None) -> np.ndarray:
    """The image shown for a render of the source in menu mode ``mode`` (see :data:`MODES`): ``uint8
    [H, W, 3]``. ``rendered``: the source's output for ``MODES[mode]`` (RGB ``[H, W, 3]`` in [0, 1], or depth
    ``[H, W]``); ``node_label``: the tree node rendering this time (the tree-node mode tints by it)."""
    if mode not in MODES:
        raise ValueError(f"unknown render mode {mode!r}; one of {', '.join(MODES)}")
    if MODES[mode] == "depth":
        return colourise_depth(rendered)
    image = to_uint8(rendered)
    if mode in TREE_MODES and node_label is not None:
        return tint(image, node_colour(node_label))
    return image


@dataclass(frozen=True)
class Encoding:
    """How an image travels to the browser."""

    format: str
    """``"png"`` (lossless) or ``"jpeg"``."""
    jpeg_quality: int | None
    """JPEG quality (None for PNG)."""


def encoding_for(preview: bool) -> Encoding:
    """JPEG for the small previews while the camera moves (fast, small); PNG for the full image when still, so
    that what the browser shows is the rendered image exactly."""
    return Encoding("jpeg", PREVIEW_JPEG_QUALITY) if preview else Encoding("png", None)


def _numpy(x) -> np.ndarray:
    if hasattr(x, "detach"):  # a torch tensor, on any device
        x = x.detach().float().cpu().numpy()
    return np.asarray(x)
