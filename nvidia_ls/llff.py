"""Conversions between OpenCV cameras and LLFF ``poses_bounds.npy``.

LLFF stores, per camera, a row of 17 floats: the row-major 3x5 matrix ``[R | t | (H, W, f)]`` of the
camera-to-world pose with rotation columns ``[down, right, back]``, then near and far. OpenCV camera axes are
``[right, down, forward]``, so OpenCV c2w columns are ``[c1, c0, -c2]`` of the LLFF rotation and back.
LLFF has one focal length and the principal point at the image centre; in OpenCV pixel convention (pixel
centres at integer coordinates) that centre is ``((W - 1) / 2, (H - 1) / 2)``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from worldtree.infra.errors import UserError


def opencv_to_llff(
    w2cs: np.ndarray, Ks: np.ndarray, height: int, width: int, bounds: np.ndarray
) -> np.ndarray:
    """Pack OpenCV cameras into LLFF rows.

    Args:
        w2cs: ``[N, 4, 4]`` world-to-camera poses (OpenCV).
        Ks: ``[N, 3, 3]`` intrinsics; LLFF keeps only ``fx`` (principal point assumed at the centre).
        height, width: image size in pixels.
        bounds: ``[N, 2]`` near/far depth per camera.

    Returns:
        ``[N, 17]`` float64 array.
    """
    w2cs = np.asarray(w2cs, np.float64)
    n = w2cs.shape[0]
    c2w = np.linalg.inv(w2cs)[:, :3, :4]
    rot = np.stack([c2w[:, :, 1], c2w[:, :, 0], -c2w[:, :, 2]], axis=2)
    hwf = np.zeros((n, 3, 1))
    hwf[:, 0, 0] = height
    hwf[:, 1, 0] = width
    hwf[:, 2, 0] = np.asarray(Ks, np.float64)[:, 0, 0]
    mat = np.concatenate([rot, c2w[:, :, 3:4], hwf], axis=2)  # [N, 3, 5]
    return np.concatenate([mat.reshape(n, 15), np.asarray(bounds, np.float64).reshape(n, 2)], axis=1)


def llff_to_opencv(pb: np.ndarray, width: int | None = None, height: int | None = None):
    """Unpack LLFF rows into OpenCV cameras.

    Args:
        pb: ``[N, 17]`` poses_bounds.
        width, height: size of the images the intrinsics are for; the focal length is scaled from the
            stored ``W`` (defaults: the stored size).

    Returns:
        ``(Ks [N, 3, 3], w2cs [N, 4, 4], bounds [N, 2])``.
    """
    pb = np.asarray(pb, np.float64)
    n = pb.shape[0]
    mat = pb[:, :15].reshape(n, 3, 5)
    rot = mat[:, :, :3]
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, :3, 0] = rot[:, :, 1]
    c2w[:, :3, 1] = rot[:, :, 0]
    c2w[:, :3, 2] = -rot[:, :, 2]
    c2w[:, :3, 3] = mat[:, :, 3]
    w2cs = np.linalg.inv(c2w)
    h_file, w_file, f = mat[:, 0, 4], mat[:, 1, 4], mat[:, 2, 4]
    width = w_file if width is None else np.full(n, float(width))
    height = h_file if height is None else np.full(n, float(height))
    scale = np.asarray(width, float) / w_file
    Ks = np.tile(np.eye(3), (n, 1, 1))
    Ks[:, 0, 0] = f * scale
    Ks[:, 1, 1] = f * scale
    Ks[:, 0, 2] = (np.asarray(width, float) - 1) / 2
    Ks[:, 1, 2] = (np.asarray(height, float) - 1) / 2
    return Ks, w2cs, pb[:, 15:17].copy()


def load_poses_bounds(path: str | Path, n_cameras: int, width: int, height: int):
    """Read and check an LLFF file for a rig of ``n_cameras`` whose images are ``width x height``.

    Returns ``(Ks, w2cs, bounds)`` as :func:`llff_to_opencv`. Raises :class:`UserError` for a file of the
    wrong shape, non-finite values, an aspect ratio that does not match the images, or bad rotations.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"--poses {path}: no such file; give an LLFF poses_bounds.npy")
    from nvidia_ls.scene_checks import read_pose_rows

    # Empty, damaged, non-numeric, complex, wrong shape, NaN: one line.
    pb = read_pose_rows(path, "--poses", rows=n_cameras).astype(np.float64)
    mat = pb[:, :15].reshape(n_cameras, 3, 5)
    h_file, w_file, f = mat[:, 0, 4], mat[:, 1, 4], mat[:, 2, 4]
    if (h_file <= 0).any() or (w_file <= 0).any() or (f <= 0).any():
        raise UserError(f"--poses {path}: non-positive H, W or focal length in the hwf column")
    if np.abs(w_file / h_file - width / height).max() > 0.01 * width / height:
        raise UserError(
            f"--poses {path}: stored size {int(w_file[0])}x{int(h_file[0])} does not match the aspect of the "
            f"{width}x{height} images; give the poses of these images"
        )
    from nvidia_ls.scene_checks import camera_problem, rotation_problem

    for r in range(n_cameras):  # the checks `nvls verify` applies (nvidia_ls.scene_checks), before inverting
        why = rotation_problem(mat[r, :, :3])
        if why is not None:
            raise UserError(f"--poses {path}: row {r}: {why}; check the file")
    if (pb[:, 15] <= 0).any() or (pb[:, 16] <= pb[:, 15]).any():
        raise UserError(f"--poses {path}: near/far bounds must satisfy 0 < near < far")
    Ks, w2cs, bounds = llff_to_opencv(pb, width, height)
    for r in range(n_cameras):
        why = camera_problem(Ks[r], w2cs[r], width, height)
        if why is not None:
            raise UserError(f"--poses {path}: row {r}: {why}; check the file")
    return Ks, w2cs, bounds
