"""Undistort and resize frames with OpenCV, one remap table per distinct camera (shared by all time steps)."""

from __future__ import annotations

import cv2
import numpy as np


def scale_intrinsics(K: np.ndarray, src_wh: tuple[int, int], dst_wh: tuple[int, int]) -> np.ndarray:
    """Intrinsics ``[3, 3]`` of an image resized from ``src_wh`` to ``dst_wh`` (OpenCV pixel centres).

    Pixel centres move as ``x' = (x + 0.5) * s - 0.5`` with ``s = W' / W`` (and ``H' / H`` for y).
    """
    sx = dst_wh[0] / src_wh[0]
    sy = dst_wh[1] / src_wh[1]
    K = np.asarray(K, np.float64).copy()
    K[0, 0] *= sx
    K[1, 1] *= sy
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K


class Undistorter:
    """Removes lens distortion (keeping the same pinhole ``K``) and resizes to the output size.

    Args:
        K: ``[3, 3]`` intrinsics at the raw size; dist: ``[5]`` OpenCV distortion coefficients.
        raw_wh: raw image size; out_wh: output size.
    """

    def __init__(self, K: np.ndarray, dist: np.ndarray, raw_wh: tuple[int, int], out_wh: tuple[int, int]):
        self.raw_wh = tuple(raw_wh)
        self.out_wh = tuple(out_wh)
        self.K_out = scale_intrinsics(K, raw_wh, out_wh)
        self.maps = None
        if np.any(np.abs(np.asarray(dist)) > 0):
            K = np.asarray(K, np.float64)
            self.maps = cv2.initUndistortRectifyMap(
                K, np.asarray(dist, np.float64), None, K, self.raw_wh, cv2.CV_16SC2
            )

    def __call__(self, img: np.ndarray) -> np.ndarray:
        """RGB uint8 ``[H_raw, W_raw, 3]`` -> undistorted RGB uint8 ``[H_out, W_out, 3]``."""
        if self.maps is not None:
            img = cv2.remap(
                img, self.maps[0], self.maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
            )
        if self.out_wh != self.raw_wh:
            shrink = self.out_wh[0] < self.raw_wh[0]
            img = cv2.resize(img, self.out_wh, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_CUBIC)
        return img
