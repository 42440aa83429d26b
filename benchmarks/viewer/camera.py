"""The viewer's camera geometry, without viser: poses, intrinsics, resolution and letterboxing.

Conventions. The project's poses are OpenCV world-to-camera matrices ``w2c [4, 4]`` (camera x right, y down,
z forward). viser reports a browser camera as ``wxyz`` (unit quaternion, scalar first) and ``position`` (world
units) with ``P_world = R(wxyz) @ p_camera + position``, in the same OpenCV camera axes (+z looks forward, -y
is up on screen), plus ``fov`` (vertical field of view of the canvas, radians) and the canvas size in pixels.
So ``R(wxyz)`` is the camera-to-world rotation and ``position`` the camera centre; no axis flip is needed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: While the camera moves, images are rendered this many times smaller per side (then full size when still).
PREVIEW_FACTOR = 4
#: Smallest rendered side, pixels (a preview of a small canvas stays recognisable).
MIN_SIDE = 16


def quat_to_matrix(wxyz) -> np.ndarray:
    """Rotation matrix ``[3, 3]`` of the quaternion ``wxyz`` (any non-zero norm; normalised here)."""
    w, x, y, z = np.asarray(wxyz, dtype=np.float64) / np.linalg.norm(wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(R) -> np.ndarray:
    """Unit quaternion ``wxyz [4]`` (``w >= 0``) of the rotation matrix ``R [3, 3]``."""
    R = np.asarray(R, dtype=np.float64)
    # Shepperd's method: take the largest of the four squared components first, for accuracy near 180 deg.
    tr = np.trace(R)
    sq = np.array([1 + tr, 1 + 2 * R[0, 0] - tr, 1 + 2 * R[1, 1] - tr, 1 + 2 * R[2, 2] - tr])
    i = int(np.argmax(sq))
    s = 2.0 * math.sqrt(max(sq[i], 1e-300))
    if i == 0:
        q = [s / 4, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif i == 1:
        q = [(R[2, 1] - R[1, 2]) / s, s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif i == 2:
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s]
    else:
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4]
    q = np.asarray(q) / np.linalg.norm(q)
    return -q if q[0] < 0 else q


def w2c_from_viser(wxyz, position) -> np.ndarray:
    """OpenCV world-to-camera ``[4, 4]`` (float64) of a viser camera (``wxyz [4]``, ``position [3]``)."""
    R_wc = quat_to_matrix(wxyz)
    w2c = np.eye(4)
    w2c[:3, :3] = R_wc.T
    w2c[:3, 3] = -R_wc.T @ np.asarray(position, dtype=np.float64)
    return w2c


def viser_from_w2c(w2c) -> tuple[np.ndarray, np.ndarray]:
    """``(wxyz [4], position [3])`` that place a viser camera (or frustum) at the pose ``w2c [4, 4]``.

    The rotation part of ``w2c`` is re-orthonormalised first (poses read from files carry rounding)."""
    w2c = np.asarray(w2c, dtype=np.float64)
    U, _, Vt = np.linalg.svd(w2c[:3, :3])
    R_cw = U @ Vt
    R_wc = R_cw.T
    return matrix_to_quat(R_wc), -R_wc @ w2c[:3, 3]


def free_intrinsics(fov_y: float, width: int, height: int) -> np.ndarray:
    """Pixel intrinsics ``K [3, 3]`` of a ``width x height`` image spanning the vertical field of view ``fov_y``
    (radians), square pixels, principal point at the centre (pixel centres at integers, so ``(W-1)/2``)."""
    f = 0.5 * height / math.tan(0.5 * fov_y)
    return np.array([[f, 0.0, 0.5 * (width - 1)], [0.0, f, 0.5 * (height - 1)], [0.0, 0.0, 1.0]])


def vertical_fov(K, height: int) -> float:
    """Vertical field of view (radians) of a camera ``K [3, 3]`` whose image is ``height`` pixels tall."""
    return 2.0 * math.atan(0.5 * height / float(np.asarray(K)[1, 1]))


def render_size(canvas_w: int, canvas_h: int, max_size: int, moving: bool) -> tuple[int, int]:
    """``(width, height)`` to render for a ``canvas_w x canvas_h`` browser canvas: the canvas's own size with its
    longer side capped at ``max_size`` pixels, :data:`PREVIEW_FACTOR` times smaller per side while ``moving``;
    the aspect ratio is kept. A canvas not yet measured (0 pixels) counts as 640 x 480."""
    if canvas_w <= 0 or canvas_h <= 0:
        canvas_w, canvas_h = 640, 480
    scale = min(1.0, max_size / max(canvas_w, canvas_h))
    if moving:
        scale /= PREVIEW_FACTOR
    # The shorter side stays at least MIN_SIDE (the aspect ratio is kept); never larger than the canvas.
    scale = min(1.0, max(scale, MIN_SIDE / min(canvas_w, canvas_h)))
    w, h = max(1, round(canvas_w * scale)), max(1, round(canvas_h * scale))
    return int(w), int(h)


@dataclass(frozen=True)
class Letterbox:
    """Where a camera's own ``width x height`` image sits in a padded image of the canvas's aspect ratio."""

    width: int
    """Padded image width, pixels."""
    height: int
    """Padded image height, pixels."""
    x0: int
    """Column of the camera image's left edge in the padded image."""
    y0: int
    """Row of the camera image's top edge in the padded image."""

    def crop(self, image: np.ndarray, width: int, height: int) -> np.ndarray:
        """The camera's ``[height, width, ...]`` part of a padded ``image``."""
        return image[self.y0 : self.y0 + height, self.x0 : self.x0 + width]


def letterbox(width: int, height: int, aspect: float) -> Letterbox:
    """Pad a ``width x height`` image (centred, black bars) to the canvas ``aspect`` (width / height): the
    browser stretches the background image over the canvas, so a named camera's exact image is padded rather
    than re-rendered at another shape."""
    if aspect <= 0 or not math.isfinite(aspect):
        return Letterbox(width, height, 0, 0)
    if aspect >= width / height:
        pw = max(width, round(height * aspect))
        return Letterbox(pw, height, (pw - width) // 2, 0)
    ph = max(height, round(width / aspect))
    return Letterbox(width, ph, 0, (ph - height) // 2)


def letterbox_fov(K, width: int, height: int, aspect: float) -> float:
    """Vertical field of view (radians) for the browser camera so that the letterboxed image of a camera
    ``K [3, 3]``, ``width x height`` lines up with the 3D scene drawn over it (frusta, grid)."""
    return vertical_fov(K, letterbox(width, height, aspect).height)


def same_pose(w2c_a, w2c_b, scale: float, tol: float = 1e-4) -> bool:
    """Whether two ``w2c [4, 4]`` poses agree: rotations within ``tol`` (Frobenius norm of the difference,
    about radians for small angles) and camera centres within ``tol * scale`` world units (``scale``: the
    scene's size). Used to tell the browser echoing a pose the server set from the user moving the camera."""
    a, b = np.asarray(w2c_a, dtype=np.float64), np.asarray(w2c_b, dtype=np.float64)
    if np.linalg.norm(a[:3, :3] - b[:3, :3]) > tol:
        return False
    ca = -a[:3, :3].T @ a[:3, 3]
    cb = -b[:3, :3].T @ b[:3, 3]
    return bool(np.linalg.norm(ca - cb) <= tol * max(scale, 1e-9))


def camera_centres(w2cs) -> np.ndarray:
    """Camera centres ``[N, 3]`` (world units) of the poses ``w2cs [N, 4, 4]``."""
    w2cs = np.asarray(w2cs, dtype=np.float64).reshape(-1, 4, 4)
    return -np.einsum("nji,nj->ni", w2cs[:, :3, :3], w2cs[:, :3, 3])


def scene_up(w2cs) -> np.ndarray:
    """World up direction ``[3]`` (unit) of a set of poses ``w2cs [N, 4, 4]``: the mean of their cameras' -y
    axes (OpenCV: y points down on screen), so orbiting in the browser keeps the captured horizon level."""
    w2cs = np.asarray(w2cs, dtype=np.float64).reshape(-1, 4, 4)
    up = -w2cs[:, 1, :3].sum(axis=0)  # row 1 of R_cw = the camera's y axis in world coordinates
    n = np.linalg.norm(up)
    return up / n if n > 1e-9 else np.array([0.0, -1.0, 0.0])


def scene_scale(w2cs) -> float:
    """A length (world units) for the cameras' spread: the largest distance of a camera centre from their mean,
    or 1 for a single camera (or cameras at one point)."""
    c = camera_centres(w2cs)
    r = float(np.linalg.norm(c - c.mean(axis=0), axis=1).max()) if len(c) else 0.0
    return r if r > 1e-6 else 1.0
