"""Images of the report's frame viewer: down-scaled copies, the per-pixel error heat map and its colour bar."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from worldtree.infra.errors import UserError

#: The heat map's colour scale: mean absolute RGB error on [0, 1] values; at or above this it saturates.
ERROR_VMAX = 0.25
COLORMAP = "magma"


def fit_width(image: np.ndarray, width: int) -> np.ndarray:
    """``image`` ``[H, W, ...]`` scaled down (area averaging) to at most ``width`` pixels wide, aspect kept;
    never scaled up."""
    h, w = image.shape[:2]
    if w <= width:
        return image
    size = (width, max(1, round(h * width / w)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def error_map(
    pred: np.ndarray, gt: np.ndarray, vmax: float = ERROR_VMAX, width: int | None = None
) -> np.ndarray:
    """Heat map uint8 RGB ``[h, w, 3]`` of the mean absolute error over RGB between two uint8 ``[H, W, 3]``
    images, on [0, 1] values, coloured by :data:`COLORMAP` from 0 (dark) to ``vmax`` (bright, saturated
    above). ``width``: scale the error (not the images: noise would average out first) down to at most this
    many pixels wide before colouring, as :func:`fit_width`."""
    from matplotlib import colormaps

    if pred.shape != gt.shape:
        raise ValueError(f"error_map: shapes differ {pred.shape} vs {gt.shape}")
    err = np.abs(pred.astype(np.int16) - gt.astype(np.int16)).sum(axis=2).astype(np.float32) / (3 * 255.0)
    if width is not None:
        err = fit_width(err, width)
    scaled = np.clip(err / vmax, 0.0, 1.0)
    return (colormaps[COLORMAP](scaled)[..., :3] * 255.0 + 0.5).astype(np.uint8)


def mask_view(image: np.ndarray, mask: np.ndarray, dim: float = 0.25) -> np.ndarray:
    """``image`` (uint8 RGB ``[H, W, 3]``) kept inside ``mask`` (bool ``[H, W]``) and darkened to ``dim`` of
    its value outside, so the scored region shows whatever its colours."""
    out = (image.astype(np.float32) * dim + 0.5).astype(np.uint8)
    out[mask] = image[mask]
    return out


def write_jpeg(path: Path, image: np.ndarray, quality: int = 90) -> None:
    """Write uint8 RGB ``[H, W, 3]`` as JPEG (the report folder is temporary until complete, so no atomic
    write is needed per file)."""
    ok, buf = cv2.imencode(
        ".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality]
    )
    if not ok:
        raise UserError(f"{path}: OpenCV cannot encode JPEG here")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(buf.tobytes())


def write_colorbar(path: Path, vmax: float = ERROR_VMAX) -> None:
    """A small horizontal colour bar of the heat map's scale, as PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colorbar import ColorbarBase
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    fig = Figure(figsize=(4.0, 0.8), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    bar = ColorbarBase(ax, cmap=COLORMAP, norm=Normalize(0.0, vmax), orientation="horizontal", extend="max")
    bar.set_label("mean |render - ground truth| over RGB, values in [0, 1]", fontsize=8)
    ax.tick_params(labelsize=8)
    fig.savefig(path, format="png", dpi=100)
