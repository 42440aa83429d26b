"""Image reading and writing shared by the dataset builder, the trainer and the evaluation harness.

Conventions: images in memory are RGB ``uint8`` arrays ``[H, W, 3]``; masks are ``bool`` arrays ``[H, W]``.
16-bit files are reduced to 8 bits by rounding ``v / 257``; an alpha channel is dropped (not composited),
which is what the NVIDIA-LS evaluation code does by reading only the colour channels.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from worldtree.atomic import atomic_write_bytes
from worldtree.errors import UserError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def _imread(path: Path) -> np.ndarray:
    if not path.is_file():
        raise UserError(f"{path}: no such image file")
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise UserError(f"{path}: cannot decode image (unreadable or truncated file); replace or remove it")
    return img


def _to_uint8(img: np.ndarray, path: Path) -> np.ndarray:
    if img.dtype == np.uint8:
        return img
    if img.dtype == np.uint16:
        return np.round(img.astype(np.float64) / 257.0).astype(np.uint8)
    raise UserError(f"{path}: unsupported pixel type {img.dtype}; save it as 8- or 16-bit PNG/JPG")


def read_image(path: str | Path) -> np.ndarray:
    """Read an image as RGB ``uint8`` ``[H, W, 3]`` (grey is replicated, alpha dropped, 16-bit rounded)."""
    path = Path(path)
    img = _to_uint8(_imread(path), path)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    elif img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    else:
        raise UserError(f"{path}: {img.shape[2]} channels; expected grey, RGB or RGBA")
    return np.ascontiguousarray(img)


def read_mask(path: str | Path) -> np.ndarray:
    """Read a mask as ``bool`` ``[H, W]``: true where the grey value is above half of the range."""
    path = Path(path)
    img = _to_uint8(_imread(path), path)
    if img.ndim == 3:
        # A mask saved as RGB(A) counts as set where any colour channel is set.
        img = img[:, :, :3].max(axis=2)
    return img > 127


def write_image(path: str | Path, image: np.ndarray) -> None:
    """Write RGB ``uint8`` ``[H, W, 3]`` or grey ``[H, W]`` (uint8 or bool) atomically; format from suffix."""
    path = Path(path)
    arr = np.asarray(image)
    if arr.dtype == bool:
        arr = arr.astype(np.uint8) * 255
    if arr.dtype != np.uint8:
        raise ValueError(f"write_image expects uint8 or bool, got {arr.dtype}")
    if arr.ndim == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(path.suffix or ".png", arr)
    if not ok:
        raise UserError(f"{path}: cannot encode an image with this suffix; use .png or .jpg")
    atomic_write_bytes(path, buf.tobytes())


def list_images(folder: str | Path) -> list[Path]:
    """Image files (PNG/JPG, any case) directly in ``folder``, sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise UserError(f"{folder}: not a folder")
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
