"""Image reading and writing shared by the dataset builder, the trainer and the evaluation harness.

Conventions: images in memory are RGB ``uint8`` arrays ``[H, W, 3]``; masks are ``bool`` arrays ``[H, W]``.
16-bit files are reduced to 8 bits by rounding ``v / 257``; an alpha channel is dropped (not composited),
which is what the NVIDIA-LS evaluation code does by reading only the colour channels.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

import cv2
import numpy as np

from worldtree.infra.atomic import atomic_write_bytes
from worldtree.infra.errors import UserError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
# The largest image (file read, or output size asked for) in megapixels, and the variable that raises it.
# A 20000x20000 PNG is 1.2 MB on disk but 1.2 GB decoded and ~10 GB once scored in float: refuse it up front.
DEFAULT_MAX_MEGAPIXELS = 100
MAX_MEGAPIXELS_ENV = "WTBENCH_MAX_MEGAPIXELS"


def max_pixels() -> int:
    """The image size limit in pixels: ``$WTBENCH_MAX_MEGAPIXELS`` (default 100) million."""
    raw = os.environ.get(MAX_MEGAPIXELS_ENV, "").strip()
    if not raw:
        return DEFAULT_MAX_MEGAPIXELS * 1_000_000
    try:
        mp = float(raw)
    except ValueError:
        mp = float("nan")
    if not (mp > 0 and mp < 1e7):  # also refuses NaN
        raise UserError(f"${MAX_MEGAPIXELS_ENV}={raw!r}: give a positive number of megapixels, e.g. 400")
    return int(mp * 1_000_000)


def check_pixels(width: int, height: int, what: str) -> None:
    """Refuse an image of ``width`` x ``height`` over :func:`max_pixels` (``what`` names the file or option),
    in one line naming the limit and how to raise it."""
    limit = max_pixels()
    if width * height > limit:
        raise UserError(
            f"{what}: {width}x{height} is {_megapixels(width * height)} megapixels, over the {limit / 1e6:g}-megapixel "
            f"limit; set {MAX_MEGAPIXELS_ENV}={-(-width * height // 1_000_000)} to allow it (if the memory is "
            "there) or use smaller images"
        )


def _megapixels(pixels: int) -> str:
    mp = pixels / 1e6
    return f"{mp:.0f}" if mp >= 10 else f"{mp:.2g}"


def image_size(data: bytes | np.ndarray) -> tuple[int, int] | None:
    """(width, height) of an encoded PNG, JPEG or BMP image from its header alone (nothing is decoded);
    None for another format or a header too damaged to read."""
    b = data.tobytes() if isinstance(data, np.ndarray) else bytes(data)
    if b[:8] == b"\x89PNG\r\n\x1a\n" and len(b) >= 24 and b[12:16] == b"IHDR":
        return struct.unpack(">II", b[16:24])
    if b[:2] == b"BM" and len(b) >= 26:
        w, h = struct.unpack("<ii", b[18:26])
        return abs(w), abs(h)  # a negative height means a top-down bitmap
    if b[:2] == b"\xff\xd8":
        return _jpeg_size(b)
    return None


# JPEG start-of-frame markers (every SOFn except DHT C4, JPG C8 and DAC CC): they hold the frame size.
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _jpeg_size(b: bytes) -> tuple[int, int] | None:
    i = 2
    while i + 4 <= len(b):
        if b[i] != 0xFF:
            return None
        marker = b[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD9)):  # markers without a length
            i += 2
            continue
        (length,) = struct.unpack(">H", b[i + 2 : i + 4])
        if marker in _SOF:
            if i + 9 > len(b):
                return None
            h, w = struct.unpack(">HH", b[i + 5 : i + 9])
            return w, h
        if marker == 0xDA:  # start of scan before any frame header
            return None
        i += 2 + length
    return None


def _imread(path: Path) -> np.ndarray:
    if not path.is_file():
        raise UserError(f"{path}: no such image file")
    data = np.fromfile(str(path), dtype=np.uint8)
    if data.size:
        # Size from the header before decoding: a small file can decode to gigabytes. A file whose size the
        # header does not give is not decoded either (another format could hide any size).
        size = image_size(data)
        if size is None:
            raise UserError(
                f"{path}: cannot decode image (not a PNG, JPEG or BMP file, or its header is unreadable or "
                "truncated); replace or remove it"
            )
        check_pixels(*size, str(path))
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


def as_uint8_array(images: np.ndarray) -> np.ndarray:
    """``images`` (any shape) as ``uint8``: returned as they are when ``uint8``, else float in [0, 1] clamped,
    times 255 and rounded to the nearest level (half to even, as ``torch.round``; NaN reads as 0). The numpy
    twin of :func:`worldtree.pixels.as_uint8`, for the OpenCV code (priors, previews, the generator), which does
    not load torch."""
    a = np.asarray(images)
    if a.dtype == np.uint8:
        return a
    if not np.issubdtype(a.dtype, np.floating):
        raise TypeError(f"as_uint8_array: expected uint8 or floating-point images, got {a.dtype}")
    # In the input's own float precision (the callers' results stay what they were); NaN to 0 first, because
    # a NaN cast to uint8 is undefined in numpy.
    return np.round(np.clip(np.nan_to_num(a, nan=0.0), 0.0, 1.0) * 255.0).astype(np.uint8)


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
