"""A contact sheet of a built scene: a row of training frames over a row of test frames with masks."""

from __future__ import annotations

import cv2
import numpy as np


def thumbnail(img: np.ndarray, width: int = 160) -> np.ndarray:
    """RGB uint8 image shrunk to ``width`` pixels wide (aspect kept)."""
    h, w = img.shape[:2]
    height = max(1, round(h * width / w))
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)


def overlay_mask(img: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """Tint masked pixels red (50%) and outline the mask; ``img`` RGB uint8, ``mask`` bool ``[H, W]``."""
    if mask is None:
        return img
    out = img.astype(np.float32)
    out[mask] = 0.5 * out[mask] + 0.5 * np.array([255.0, 0.0, 0.0])
    out = out.astype(np.uint8)
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(out, contours, -1, (255, 255, 0), 1)
    return out


def _label(img: np.ndarray, text: str) -> np.ndarray:
    img = img.copy()
    cv2.putText(img, text, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 2, cv2.LINE_AA)
    cv2.putText(img, text, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def contact_sheet(
    train: list[tuple[str, np.ndarray]],
    test: list[tuple[str, np.ndarray, np.ndarray | None]],
    width: int = 160,
) -> np.ndarray:
    """Two rows: labelled training thumbnails, then labelled test thumbnails with their masks overlaid.

    Args:
        train: ``(label, RGB uint8 image)`` pairs; test: ``(label, image, bool mask or None)``.
        width: thumbnail width in pixels.

    Returns:
        RGB uint8 sheet.
    """
    rows = []
    row_t = [_label(thumbnail(img, width), lab) for lab, img in train]
    row_g = []
    for lab, img, mask in test:
        small = thumbnail(img, width)
        m = None
        if mask is not None:
            m = (
                cv2.resize(
                    mask.astype(np.uint8), (small.shape[1], small.shape[0]), interpolation=cv2.INTER_NEAREST
                )
                > 0
            )
        row_g.append(_label(overlay_mask(small, m), lab))
    n = max(len(row_t), len(row_g), 1)
    for row in (row_t, row_g):
        if not row:
            continue
        h, w = row[0].shape[:2]
        cells = row + [np.zeros((h, w, 3), np.uint8)] * (n - len(row))
        rows.append(np.concatenate(cells, axis=1))
    return np.concatenate(rows, axis=0)
