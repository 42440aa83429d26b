"""A synthetic raw capture: a textured room and moving textured objects seen by a static camera rig.

The scene is rendered exactly by :mod:`nvidia_ls.raycast`, so every ground-truth quantity is known: camera
intrinsics and poses, per-pixel depth, dynamic masks, object ids and the rigid motion of each object.

World frame (OpenCV-like): x right, y down, z forward (away from the rig). The floor is the plane
``y = FLOOR_Y``; the rig looks along +z.

Library use::

    from nvidia_ls.synth import SynthConfig, write_raw_scene, make_scene, render_view
    raw = write_raw_scene("raw/Synth", SynthConfig(cameras=12, steps=24, width=160, height=90))
    scene = make_scene(SynthConfig())
    view = render_view(scene, scene.Ks[0], scene.w2cs[0], scene.width, scene.height, time=3.5)
"""

from __future__ import annotations

import json
import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from nvidia_ls import llff
from nvidia_ls.raycast import Primitive, cast
from nvidia_ls.writer import save_image
from worldtree import __version__
from worldtree.imageio import as_uint8_array, check_pixels
from worldtree.infra.atomic import atomic_dir, atomic_write_json
from worldtree.infra.cores import available_cores
from worldtree.infra.errors import SettingError, UserError
from worldtree.infra.output_paths import check_replaceable

FLOOR_Y = 1.0
MOTIONS = ("constant", "slow_fast", "near_static", "slow", "fast")
"""Motion profiles: the phase of the objects' loop reached at the last time step (the objects run one loop
over the clip at ``constant`` speed; ``slow`` a quarter loop, ``fast`` two loops, ``near_static`` 2 % of one,
so they barely move; ``slow_fast`` one loop, its first half at a quarter of the second's speed)."""
LAYOUTS = ("multiview", "camera_folders", "videos")
RIGS = ("rows", "row", "arc")
"""Rig layouts: "rows" (two rows on a gentle arc aimed at the scene centre), "row" (one straight row, every
camera looking along +z, as the NVIDIA rig) and "arc" (one row on a wide arc of +-``ARC_HALF_DEG`` degrees
around the scene centre, every camera aimed at it)."""
PATHS = ("loop", "straight", "turning", "enter_leave")
"""Object paths: "loop" (closed loops), "straight" (a straight segment at constant speed), "turning" (a half
circle at constant speed: the direction turns by 180 degrees) and "enter_leave" (a straight crossing that
starts and ends behind the side walls, so every camera sees each object enter and leave)."""
TEXTURES = ("fine", "smooth")
"""Textures: "fine" (five octaves of colour noise plus small discs and rectangles) or "smooth" (the two
lowest octaves only, no shapes, sinusoidal instead of square stripes on the moving objects)."""
CAMERA_ORDERS = ("spatial", "shuffled")
"""Camera ids: "spatial" (ids follow the rig positions) or "shuffled" (positions permuted by the seed)."""
KINDS = ("room", "twin")
"""Scene kinds: "room" (the textured room and its rigs) or "twin" (a generated twin of a real capture: its rig
read from an LLFF ``poses_bounds.npy``, see :class:`TwinGeometry`)."""
ARC_HALF_DEG = 40.0
"""Half the angle the "arc" rig spans around the scene centre (degrees)."""
SCENE_CENTRE = (0.0, 0.2, 4.0)
"""The point the rigs are arranged around (world units)."""
RIG_RADIUS = 4.0
"""Distance from :data:`SCENE_CENTRE` to the cameras of the "rows" and "arc" rigs."""
# Written into every raw capture this module makes: --force replaces only a folder holding it.
SYNTH_MARKERS = ("gt/cameras.json",)
TWIN_POSES = "twin_poses_bounds.npy"
"""Name under ``gt/`` of the copy of the real rig a twin capture was made from."""


@dataclass
class SynthConfig:
    """Configuration of a synthetic raw scene (one source of defaults; also the ``nvls synth`` options: each field
    is ``--field-name`` with the string under it as its help)."""

    cameras: int = 12
    """Rig cameras: two rows for --rig rows (first row cam01.., left to right), one row otherwise."""
    steps: int = 30
    """Number of time steps rendered."""
    width: int = 320
    """Image width in pixels."""
    height: int = 180
    """Image height in pixels."""
    seed: int = 0
    """Seed of textures, of the small per-camera aiming jitter and of --camera-order shuffled."""
    motion: str = "constant"
    """Speed profile along the path: constant | slow_fast (first half 4x slower than the second) | near_static
    (2% of a loop) | slow (a quarter) | fast (two loops; an open path is run forth and back)."""
    objects: int = 2
    """Moving objects: 0, 1 (a sphere) or 2 (a sphere and a box)."""
    supersample: int = 2
    """Anti-aliasing: rays per pixel along each axis for the colour images (depth/masks use pixel centres)."""
    depth: bool = False
    """Also write ground-truth z-depth maps (float32 .npy, world units) for every camera and time."""
    image_ext: str = "png"
    """Raw image format: png (lossless) | jpg."""
    layout: str = "multiview"
    """Raw layout: multiview (mv_images/%05d/cam%02d) | camera_folders (cam%02d/%05d) | videos."""
    fov_deg: float = 60.0
    """Horizontal field of view of every camera (degrees)."""
    rig_width: float = 1.6
    """Distance between the outermost cameras of a row (world units; --rig rows and row)."""
    fps: float = 30.0
    """Frame rate of the videos written for --layout videos."""
    rig: str = "rows"
    """Rig layout: rows (two rows on a gentle arc) | row (one straight row looking along +z in parallel, as the
    NVIDIA rig) | arc (one row on a +-40 degree arc around the scene centre, aimed at it)."""
    path: str = "loop"
    """Object paths: loop (closed loops) | straight (constant velocity) | turning (a half circle at constant
    speed) | enter_leave (across the room, from behind one side wall to behind the other)."""
    texture: str = "fine"
    """Textures: fine (multi-octave noise and small shapes) | smooth (low frequencies only)."""
    camera_order: str = "spatial"
    """Camera ids: spatial (ids follow the rig positions) | shuffled (positions permuted by --seed, so
    consecutive ids jump across the rig)."""
    kind: str = "room"
    """Scene kind: room (the textured room) | twin (the rig of --poses, a wall at its far depth, a person-sized
    box at half that depth and a textured ball held near the rig moving a quarter image width per step)."""
    poses: Path | None = None
    """LLFF poses_bounds.npy whose rig --kind twin reproduces (one row per camera; --cameras must match)."""
    exposure: float = 0.0
    """Unmatched cameras: each camera's image is scaled by exp(e), e uniform in +-EXPOSURE, and each of its
    channels by exp(w), w uniform in +-EXPOSURE/2 (white balance); drawn from --seed and the camera id. 0: the
    cameras are matched. Ground truth (masks, depth) is unaffected."""
    noise: float = 0.0
    """Sensor noise: Gaussian, this standard deviation in 8-bit grey levels, independent per pixel, channel,
    camera and time step (drawn from --seed). 0: none."""
    shutter: float = 0.0
    """Motion blur: the fraction of a time step the shutter stays open, centred on the step; the colours are
    averaged over that interval. 0: an instant. Ground truth (masks, depth) is taken at the step itself."""

    def check(self) -> None:
        """Raise :class:`UserError` for values the generator cannot honour."""
        if self.cameras < 2:
            raise SettingError.of_field(self, "cameras", "need at least 2 cameras")
        if self.steps < 1:
            raise SettingError.of_field(self, "steps", "need at least 1 time step")
        if self.width < 16 or self.height < 16:
            raise UserError(f"--width/--height {self.width}x{self.height}: need at least 16x16 pixels")
        check_pixels(self.width, self.height, "--width/--height")
        if self.objects not in (0, 1, 2):
            raise SettingError.of_field(self, "objects", "choose 0, 1 or 2")
        if self.supersample < 1:
            raise SettingError.of_field(self, "supersample", "must be >= 1")
        if not (math.isfinite(self.exposure) and 0.0 <= self.exposure <= 1.0):
            raise SettingError.of_field(self, "exposure", "choose a spread between 0 and 1 (0.1: +-10 %)")
        if not (math.isfinite(self.noise) and 0.0 <= self.noise <= 64.0):
            raise SettingError.of_field(self, "noise", "choose a standard deviation between 0 and 64 grey levels")
        if not (math.isfinite(self.shutter) and 0.0 <= self.shutter <= 1.0):
            raise SettingError.of_field(self, "shutter", "choose a fraction of a time step between 0 and 1")
        if not 10.0 <= self.fov_deg <= 120.0:
            raise SettingError.of_field(self, "fov_deg", "choose a field of view between 10 and 120 degrees")
        for name, choices in (("motion", MOTIONS), ("image_ext", ("png", "jpg")), ("layout", LAYOUTS),
                              ("rig", RIGS), ("path", PATHS), ("texture", TEXTURES),
                              ("camera_order", CAMERA_ORDERS), ("kind", KINDS)):  # fmt: skip
            value = getattr(self, name)
            if value not in choices:
                why = f"choose one of {', '.join(choices)}"
                raise SettingError.of_field(self, name, why, shown=repr(value))
        if self.kind == "twin":
            if self.poses is None:
                raise UserError("--kind twin: give the real rig with --poses PATH/poses_bounds.npy")
            # The twin's rig and motion come from the real capture; these options shape the room only.
            default = SynthConfig()
            for flag, value, base in (
                ("--rig", self.rig, default.rig),
                ("--path", self.path, default.path),
                ("--motion", self.motion, default.motion),
            ):
                if value != base:
                    raise UserError(
                        f"{flag} {value}: applies to --kind room; the twin's rig and motion are fixed"
                    )
        elif self.poses is not None:
            raise UserError(
                f"--poses {self.poses}: only --kind twin reads a rig; drop --poses or add --kind twin"
            )


@dataclass
class SynthScene:
    """Everything needed to render the synthetic scene at any camera and (fractional) time.

    Attributes:
        cfg: the configuration it was made from.
        Ks: ``[N, 3, 3]`` intrinsics (OpenCV: pixel centres at integer coordinates).
        w2cs: ``[N, 4, 4]`` world-to-camera poses (OpenCV).
        static: primitives of the static set (object id 0).
        objects: the moving primitives (object ids 1..).
        rig_positions: ``[N]`` rig position (0-based, in rig order) of each camera; ``arange(N)`` unless
            ``cfg.camera_order`` is "shuffled".
        twin: the twin's layout and motion (``cfg.kind == "twin"``), else None.
    """

    cfg: SynthConfig
    Ks: np.ndarray
    w2cs: np.ndarray
    static: list[Primitive]
    objects: list[Primitive]
    rig_positions: np.ndarray | None = None
    twin: TwinGeometry | None = None

    @property
    def width(self) -> int:
        return self.cfg.width

    @property
    def height(self) -> int:
        return self.cfg.height

    def phase(self, time: float) -> float:
        """Motion phase (loops done; 1 = one loop at constant speed) at (fractional) time step ``time``
        in [0, steps-1]."""
        tau = 0.0 if self.cfg.steps <= 1 else float(np.clip(time / (self.cfg.steps - 1), 0.0, 1.0))
        speed = {"constant": 1.0, "near_static": 0.02, "slow": 0.25, "fast": 2.0}.get(self.cfg.motion)
        if speed is not None:
            return speed * tau
        # slow_fast: speed 1 on the first half, 4 on the second, integrated and normalised to end at 1.
        slow, fast = 1.0, 4.0
        total = 0.5 * slow + 0.5 * fast
        return (slow * min(tau, 0.5) + fast * max(tau - 0.5, 0.0)) / total

    def object_pose(self, index: int, time: float) -> np.ndarray:
        """``[4, 4]`` world-from-object transform of moving object ``index`` (0-based) at time ``time``.

        The one source of object motion: rendering, ``gt/objects.json``, :func:`gt_flow` and ``nvls gt-priors``
        all call it. Rotation follows the phase on every path; the centre follows ``cfg.path``."""
        if not 0 <= index < len(self.objects):
            raise IndexError(f"object {index}: the scene has {len(self.objects)} moving objects")
        if self.twin is not None:
            return self.twin.object_pose(index, time)
        phi = 2.0 * math.pi * self.phase(time)
        T = np.eye(4)
        if self.cfg.path != "loop":
            T[:3, :3] = _object_rotation(index, phi)
            T[:3, 3] = open_path_point(self.cfg.path, index, _fold(self.phase(time)))
            return T
        if index == 0:  # the sphere: sweeps left-right-left while bouncing and spinning
            T[:3, :3] = _object_rotation(index, phi)
            T[:3, 3] = [
                1.3 * math.sin(phi),
                FLOOR_Y - 0.45 - 0.35 * abs(math.sin(2 * phi)),
                3.6 + 0.5 * math.cos(phi),
            ]
        else:  # the box: circles in depth while tumbling
            T[:3, :3] = _object_rotation(index, phi)
            T[:3, 3] = [
                0.9 + 0.8 * math.cos(phi + 1.0),
                0.1 + 0.3 * math.sin(2 * phi),
                5.0 + 0.8 * math.sin(phi + 1.0),
            ]
        return T


# Open paths, per object (sphere, box), in world units. Endpoints keep clear of the static boxes and of each
# other; "enter_leave" starts and ends with the whole object behind a side wall (x = -+3.5), so no camera
# inside the room sees it at the first and last time step.
STRAIGHT = (((-1.4, FLOOR_Y - 0.55, 3.0), (1.4, FLOOR_Y - 0.55, 4.2)), ((1.5, -0.1, 5.4), (-0.6, 0.2, 4.6)))
"""``(start, end)`` of each object's "straight" path."""
ENTER_LEAVE = (
    ((-4.1, FLOOR_Y - 0.55, 2.6), (4.1, FLOOR_Y - 0.55, 3.4)),
    ((4.2, -0.3, 4.2), (-4.2, -0.3, 3.6)),
)
"""``(start, end)`` of each object's "enter_leave" path."""
TURNING = (((0.0, FLOOR_Y - 0.55, 3.4), 1.3, ((-1.0, 0.0, 0.0), (0.0, 0.0, -1.0))),
           ((0.6, 0.35, 5.0), 0.9, ((1.0, 0.0, 0.0), (0.0, -1.0, 0.0))))  # fmt: skip
"""``(centre, radius, (a, b))`` of each object's "turning" half circle ``centre + radius (cos(pi s) a +
sin(pi s) b)``: the sphere swings towards the rig in a horizontal plane, the box arches up in a vertical one."""


def open_path_point(path: str, index: int, s: float) -> np.ndarray:
    """``[3]`` centre of object ``index`` at path parameter ``s`` in [0, 1] of an open path (not "loop").

    Every open path is traversed at constant speed in ``s``: "straight" and "enter_leave" interpolate their
    endpoints linearly, "turning" runs a half circle at constant angular speed."""
    if path in ("straight", "enter_leave"):
        a, b = (np.asarray(p, float) for p in (STRAIGHT if path == "straight" else ENTER_LEAVE)[index])
        return a + s * (b - a)
    if path == "turning":
        centre, radius, (a, b) = TURNING[index]
        ang = math.pi * s
        return np.asarray(centre, float) + radius * (
            math.cos(ang) * np.asarray(a, float) + math.sin(ang) * np.asarray(b, float)
        )
    raise ValueError(f"path {path!r} is not an open path")


def _fold(phase: float) -> float:
    """Phase -> open-path parameter: the path is run forth (0..1) and back (1..2) ("fast" runs it twice)."""
    p = phase % 2.0
    return p if p <= 1.0 else 2.0 - p


def _object_rotation(index: int, phi: float) -> np.ndarray:
    """``[3, 3]`` world-from-object rotation of object ``index`` at loop angle ``phi`` (the sphere spins, the
    box tumbles), the same on every path."""
    if index == 0:
        return _axis_angle([0.0, 1.0, 0.3], 3.0 * phi)
    return _axis_angle([0.0, 1.0, 0.0], 2.0 * phi) @ _axis_angle([1.0, 0.0, 0.0], phi)


@dataclass
class SynthView:
    """One rendered view. rgb ``[H, W, 3]`` uint8; depth ``[H, W]`` float32 z-depth (inf = no hit);
    object_id ``[H, W]`` int16 (0 static set, k >= 1 moving object k, -1 nothing)."""

    rgb: np.ndarray
    depth: np.ndarray
    object_id: np.ndarray

    @property
    def dynamic_mask(self) -> np.ndarray:
        """``[H, W]`` bool: pixel centre sees a moving object."""
        return self.object_id > 0


def _axis_angle(axis, angle: float) -> np.ndarray:
    rvec = np.asarray(axis, dtype=np.float64)
    rvec = rvec / np.linalg.norm(rvec) * angle
    return cv2.Rodrigues(rvec)[0]


SMOOTH_OCTAVES = 2
"""Noise octaves (of five, coarsest first) a "smooth" texture keeps."""


def _texture(rng: np.random.Generator, size: int, vivid: bool, smooth: bool = False) -> np.ndarray:
    """Multi-octave colour noise plus random discs and rectangles: rich corners and blobs for SIFT.

    ``smooth`` keeps the coarsest :data:`SMOOTH_OCTAVES` octaves (rescaled to the same total amplitude), draws no
    shapes and makes the stripes sinusoidal. It draws the same random numbers either way, so the later textures
    of a scene (and its aiming jitter) do not depend on the texture option."""
    tex = np.zeros((size, size, 3), np.float32)
    octaves = ((4, 0.35), (8, 0.25), (16, 0.2), (32, 0.12), (64, 0.08))
    for k, (cells, amp) in enumerate(octaves):
        grid = rng.random((cells, cells, 3)).astype(np.float32)
        if smooth and k >= SMOOTH_OCTAVES:
            continue
        tex += amp * cv2.resize(grid, (size, size), interpolation=cv2.INTER_CUBIC)
    if smooth:
        tex *= np.float32(sum(a for _, a in octaves) / sum(a for _, a in octaves[:SMOOTH_OCTAVES]))
    tex = np.clip(tex, 0, 1)
    if vivid:
        # Moving objects: saturated stripes so they stand apart from the earthy static set.
        hue = rng.random(3)
        wave = np.sin(np.arange(size) * 2 * np.pi / (size / 6))[None, :]
        stripes = (0.5 + 0.5 * wave if smooth else wave > 0).astype(np.float32)
        tex = 0.5 * tex + 0.5 * (
            stripes[..., None] * hue[None, None, :] + (1 - stripes[..., None]) * hue[::-1]
        )
    img = (tex * 255).astype(np.uint8)
    n_shapes = 60 if vivid else 90
    for _ in range(n_shapes):
        col = tuple(int(x) for x in rng.integers(0, 256, 3))
        x, y = (int(v) for v in rng.integers(0, size, 2))
        r = int(rng.integers(size // 64 + 2, size // 12 + 3))
        disc = rng.random() < 0.5
        if smooth:
            continue
        if disc:
            cv2.circle(img, (x, y), r, col, -1, lineType=cv2.LINE_AA)
        else:
            cv2.rectangle(img, (x - r, y - r // 2), (x + r, y + r), col, -1, lineType=cv2.LINE_AA)
    return img.astype(np.float32) / 255.0


def _look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """OpenCV world-to-camera ``[4, 4]`` looking from ``centre`` at ``target`` with image y along world +y."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ centre
    return w2c


def _rig(cfg: SynthConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intrinsics, poses and rig positions of the cameras of ``cfg.rig`` (see :data:`RIGS`), ids in
    ``cfg.camera_order``."""
    n = cfg.cameras
    f = 0.5 * cfg.width / math.tan(math.radians(cfg.fov_deg) / 2)
    K = np.array([[f, 0, (cfg.width - 1) / 2], [0, f, (cfg.height - 1) / 2], [0, 0, 1.0]])
    target = np.array(SCENE_CENTRE)
    radius = RIG_RADIUS
    # Drawn for every rig (used by "rows" only), so the textures drawn next are the same on every rig.
    jitter = [rng.normal(0.0, 0.05, 3) for _ in range(n)]  # real rigs are never aimed perfectly
    w2cs = []
    for i in range(n):
        if cfg.rig == "rows":
            per_row = math.ceil(n / 2)
            half_angle = math.asin(min(0.99, cfg.rig_width / 2 / radius))
            row, col = divmod(i, per_row)
            ncol = per_row if row == 0 else n - per_row
            a = 0.0 if ncol == 1 else -half_angle + 2 * half_angle * col / (ncol - 1)
            centre = np.array([radius * math.sin(a), -0.12 + 0.24 * row, target[2] - radius * math.cos(a)])
            w2cs.append(_look_at(centre, target + jitter[i]))
        elif cfg.rig == "row":  # exactly parallel optical axes along +z (rotation = identity)
            centre = np.array([-cfg.rig_width / 2 + cfg.rig_width * i / (n - 1), 0.0, target[2] - radius])
            w2cs.append(_look_at(centre, centre + np.array([0.0, 0.0, 1.0])))
        else:  # arc: exactly aimed at the centre, so the optical axes meet there
            a = math.radians(ARC_HALF_DEG) * (2 * i / (n - 1) - 1)
            centre = np.array([radius * math.sin(a), target[1], target[2] - radius * math.cos(a)])
            w2cs.append(_look_at(centre, target))
    positions = _camera_positions(n, cfg.camera_order, cfg.seed)
    return np.stack([K.copy() for _ in range(n)]), np.stack(w2cs)[positions], positions


def _camera_positions(n: int, order: str, seed: int) -> np.ndarray:
    """``[n]`` rig position of each camera id (0-based): identity, or a seeded permutation that is not one."""
    if order == "spatial":
        return np.arange(n)
    # Its own generator: shuffling must not change the textures or the aiming drawn from the scene's.
    rng = np.random.default_rng([seed, 0x5EED])
    while True:
        perm = rng.permutation(n)
        if np.any(perm != np.arange(n)):
            return perm


# The twin, in units of the wall's depth D (the median far bound of the real rig): a person-sized box at D / 2
# standing on the floor, a ball held near the rig at 0.3 D. At D ~ 8 m the person is 2.4 m tall (from below the
# image to near its top, as in Balloon1) and the ball 0.65 m across; at 0.3 D it shifts about half an image
# between cameras 0 and 5 of Balloon1's rig, as the real balloon does.
TWIN_FLOOR = 0.19
"""Floor below the mean camera (y down), in units of D."""
TWIN_PERSON = {"depth": 0.5, "x": 0.06, "half": (0.04, 0.15, 0.025), "sway": 0.015}
"""Person box: depth, lateral position, half extents and (when it moves, ``objects == 2``) sway amplitude, in D."""
TWIN_BALL = {"depth": 0.3, "radius": 0.04, "y": -0.02, "bob": 0.01, "u": -0.1}
"""Ball: depth, radius, height and vertical bob amplitude in D; ``u``: the centre of its sweep in image widths
of the mean camera (left of centre, so the test camera 1 at one end of a Balloon1-like rig keeps it in view)."""
TWIN_SHIFT = 0.25
"""Horizontal speed of the ball: image widths per time step, in the rig's mean camera."""
TWIN_SWEEP = 0.7
"""The ball runs back and forth over this fraction of the image width (turning between steps, so 12 steps
do not repeat a position)."""


@dataclass
class TwinGeometry:
    """Layout of a twin scene in its rig frame (origin at the mean camera centre, axes of the mean camera:
    x right, y down, z forward; units of the real rig's poses).

    Attributes:
        rig_to_world: ``[4, 4]`` rigid transform from the rig frame to the world of the real poses.
        wall: D, the depth of the back wall (median far bound of the real file).
        width_per_depth: image width / focal length (the view's width per unit depth).
        person_moves: the person box is moving object 2 (else it is part of the static set).
    """

    rig_to_world: np.ndarray
    wall: float
    width_per_depth: float
    person_moves: bool

    def ball_centre(self, time: float) -> np.ndarray:
        """``[3]`` ball centre in the rig frame at (fractional) time step ``time``.

        Its x runs at :data:`TWIN_SHIFT` image widths per step (a triangle wave over :data:`TWIN_SWEEP` of the
        width, so the clip does not repeat with 12 steps) at the fixed depth ``0.3 D``."""
        D, z = self.wall, TWIN_BALL["depth"] * self.wall
        s = (TWIN_SHIFT * time) % (2 * TWIN_SWEEP)
        u = TWIN_BALL["u"] + (s if s <= TWIN_SWEEP else 2 * TWIN_SWEEP - s) - TWIN_SWEEP / 2  # image widths
        y = (TWIN_BALL["y"] + TWIN_BALL["bob"] * math.sin(2 * math.pi * time / 7.0)) * D
        return np.array([u * self.width_per_depth * z, y, z])

    def person_centre(self, time: float) -> np.ndarray:
        """``[3]`` centre of the person box in the rig frame (swaying only when it moves)."""
        D = self.wall
        sway = TWIN_PERSON["sway"] * math.sin(2 * math.pi * time / 12.0) if self.person_moves else 0.0
        return np.array([(TWIN_PERSON["x"] + sway) * D, (TWIN_FLOOR - TWIN_PERSON["half"][1]) * D,
                         TWIN_PERSON["depth"] * D])  # fmt: skip

    def object_pose(self, index: int, time: float) -> np.ndarray:
        """``[4, 4]`` world-from-object transform of the ball (0) or the moving person (1) at ``time``."""
        local = np.eye(4)
        if index == 0:  # the ball spins slowly as it is carried
            local[:3, :3] = _axis_angle([0.2, 1.0, 0.0], 0.4 * time)
            local[:3, 3] = self.ball_centre(time)
        else:  # the person turns a little as they sway
            local[:3, :3] = _axis_angle([0.0, 1.0, 0.0], 0.15 * math.sin(2 * math.pi * time / 12.0))
            local[:3, 3] = self.person_centre(time)
        return self.rig_to_world @ local


def _rig_frame(w2cs: np.ndarray) -> np.ndarray:
    """``[4, 4]`` rig-to-world transform: origin at the mean camera centre, rotation the mean camera rotation."""
    U, _, Vt = np.linalg.svd(np.asarray(w2cs)[:, :3, :3].mean(0))
    R = U @ Vt  # world -> mean camera (nearest rotation to the mean of the world->camera rotations)
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    M = np.eye(4)
    M[:3, :3] = R.T
    M[:3, 3] = np.stack([-w[:3, :3].T @ w[:3, 3] for w in w2cs]).mean(0)
    return M


def _make_twin(cfg: SynthConfig) -> SynthScene:
    """The twin of a real capture (``cfg.kind == "twin"``): its rig, a wall, a floor, a person and a ball."""
    Ks, w2cs, bounds = llff.load_poses_bounds(cfg.poses, cfg.cameras, cfg.width, cfg.height)
    positions = _camera_positions(cfg.cameras, cfg.camera_order, cfg.seed)
    M = _rig_frame(w2cs)
    D = float(np.median(bounds[:, 1]))
    geo = TwinGeometry(M, D, cfg.width / float(np.median(Ks[:, 0, 0])), cfg.objects >= 2)
    rng = np.random.default_rng(cfg.seed)
    smooth = cfg.texture == "smooth"
    tpu = 64.0 * 8.0 / D  # the room's texture density relative to its back wall's depth
    R_rw = M[:3, :3]

    def place(kind, size, tex, object_id, R_local, c_local) -> Primitive:
        c = M[:3, :3] @ np.asarray(c_local, float) + M[:3, 3]
        return Primitive(kind, np.asarray(size, float), tex, tpu, object_id, R_rw @ R_local, c)

    floor = TWIN_FLOOR * D
    static = [
        # The back wall and the floor reach past every camera's view, so every ray hits something.
        place("plane", [2 * D, D + floor, 0], _texture(rng, 512, False, smooth), 0, np.eye(3), [-D, -D, D]),
        place("plane", [2 * D, 1.3 * D, 0], _texture(rng, 512, False, smooth), 0,
              np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]), [-D, floor, -0.3 * D]),
    ]  # fmt: skip
    person_tex = _texture(rng, 256, False, smooth)
    half = np.asarray(TWIN_PERSON["half"]) * D
    if not geo.person_moves:
        static.append(place("box", half, person_tex, 0, np.eye(3), geo.person_centre(0.0)))
    objects = []
    if cfg.objects >= 1:
        objects.append(Primitive("sphere", np.array([TWIN_BALL["radius"] * D, 0, 0]),
                                 _texture(rng, 256, True, smooth), tpu, 1))  # fmt: skip
    if geo.person_moves:
        objects.append(Primitive("box", half, person_tex, tpu, 2))
    return SynthScene(cfg, Ks[positions], w2cs[positions], static, objects, positions, geo)


def make_scene(cfg: SynthConfig) -> SynthScene:
    """Build the scene description (textures, rig, objects) for ``cfg``; deterministic in ``cfg.seed``."""
    cfg.check()
    if cfg.kind == "twin":
        return _make_twin(cfg)
    rng = np.random.default_rng(cfg.seed)
    Ks, w2cs, positions = _rig(cfg, rng)
    smooth = cfg.texture == "smooth"
    tpu = 64.0  # texels per world unit: about one texel per pixel at 480 px width on the back wall

    def plane(origin, u_axis, v_axis, size_u, size_v) -> Primitive:
        u = np.asarray(u_axis, float)
        v = np.asarray(v_axis, float)
        R = np.stack([u, v, np.cross(u, v)], axis=1)
        return Primitive(
            "plane",
            np.array([size_u, size_v, 0.0]),
            _texture(rng, 512, False, smooth),
            tpu,
            0,
            R,
            np.asarray(origin, float),
        )

    x0, x1, ceil, back, front = -3.5, 3.5, -2.5, 8.0, -1.0
    static = [
        plane([x0, FLOOR_Y, front], [1, 0, 0], [0, 0, 1], x1 - x0, back - front),  # floor
        plane([x0, ceil, back], [1, 0, 0], [0, 1, 0], x1 - x0, FLOOR_Y - ceil),  # back wall
        plane([x0, ceil, front], [0, 0, 1], [0, 1, 0], back - front, FLOOR_Y - ceil),  # left wall
        plane([x1, ceil, front], [0, 0, 1], [0, 1, 0], back - front, FLOOR_Y - ceil),  # right wall
        plane([x0, ceil, front], [1, 0, 0], [0, 0, 1], x1 - x0, back - front),  # ceiling
    ]
    for centre, half in (([-1.6, FLOOR_Y - 0.45, 5.2], 0.45), ([1.9, FLOOR_Y - 0.35, 6.3], 0.35)):
        static.append(
            Primitive(
                "box",
                np.full(3, half),
                _texture(rng, 256, False, smooth),
                tpu,
                0,
                np.eye(3),
                np.asarray(centre, float),
            )
        )
    objects = []
    if cfg.objects >= 1:
        objects.append(Primitive("sphere", np.array([0.45, 0, 0]), _texture(rng, 256, True, smooth), tpu, 1))
    if cfg.objects >= 2:
        objects.append(Primitive("box", np.full(3, 0.3), _texture(rng, 256, True, smooth), tpu, 2))
    return SynthScene(cfg, Ks, w2cs, static, objects, positions)


def pixel_rays(K: np.ndarray, w2c: np.ndarray, pix: np.ndarray):
    """Rays of camera ``K, w2c`` (OpenCV) through pixel positions ``pix`` ``[..., 2]``: world origin ``[3]``,
    unit world directions ``[..., 3]`` and z per unit length ``[...]`` (float64)."""
    hom = np.concatenate([pix, np.ones(pix.shape[:-1] + (1,))], axis=-1)
    dc = hom @ np.linalg.inv(K).T
    dc = dc / np.linalg.norm(dc, axis=-1, keepdims=True)
    R = w2c[:3, :3]
    return -R.T @ w2c[:3, 3], dc @ R, dc[..., 2]


def _rays(K: np.ndarray, w2c: np.ndarray, width: int, height: int, ss: int):
    """World origin ``[3]``, unit directions ``[H*ss, W*ss, 3]`` and z-per-unit-length ``[H*ss, W*ss]``."""
    offs = (np.arange(ss) + 0.5) / ss - 0.5  # sub-pixel offsets around each pixel centre
    xs = (np.arange(width)[:, None] + offs[None, :]).reshape(-1)
    ys = (np.arange(height)[:, None] + offs[None, :]).reshape(-1)
    u, v = np.meshgrid(xs, ys)
    origin, dirs, zfac = pixel_rays(K, w2c, np.stack([u, v], axis=-1))
    return origin, dirs.astype(np.float32), zfac.astype(np.float32)


def _trace(prims, poses, origin, dirs, zfac):
    shape = dirs.shape[:2]
    t, rgb, oid = cast(prims, poses, origin, dirs.reshape(-1, 3))
    return t.reshape(shape) * zfac, rgb.reshape(*shape, 3), oid.reshape(shape)


def _downsample(rgb: np.ndarray, ss: int) -> np.ndarray:
    if ss > 1:
        # INTER_AREA with an integer factor is the exact box average of each ss x ss block.
        h, w = rgb.shape[0] // ss, rgb.shape[1] // ss
        rgb = cv2.resize(rgb.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
    return as_uint8_array(rgb)


SHUTTER_SAMPLES = 8
"""Instants a colour is averaged over when the shutter is open (``SynthConfig.shutter`` > 0)."""


def shutter_times(time: float, shutter: float) -> np.ndarray:
    """The instants (time steps) averaged for a shutter open ``shutter`` of a step, centred on ``time``: the
    midpoints of :data:`SHUTTER_SAMPLES` equal parts of the interval, so a motion linear in time is blurred
    exactly as its average."""
    if shutter <= 0.0:
        return np.asarray([time])
    return time + shutter * ((np.arange(SHUTTER_SAMPLES) + 0.5) / SHUTTER_SAMPLES - 0.5)


class _CameraRenderer:
    """Renders one camera at many times, tracing the static set once and only the objects per time."""

    def __init__(self, scene: SynthScene, K, w2c, width: int, height: int, supersample: int,
                 shutter: float = 0.0):  # fmt: skip
        self.scene = scene
        self.shutter = shutter
        self.ss = supersample
        self.K = np.asarray(K, float)
        self.w2c = np.asarray(w2c, float)
        self.rays = [_rays(K, w2c, width, height, s) for s in sorted({1, supersample})]
        self.static = [_trace(scene.static, [None] * len(scene.static), *r) for r in self.rays]

    def _composite(self, k: int, time: float):
        origin, dirs, zfac = self.rays[k]
        depth, rgb, oid = (a.copy() for a in self.static[k])
        ss = self.ss if k == len(self.rays) - 1 else 1
        for i, prim in enumerate(self.scene.objects):
            T = self.scene.object_pose(i, time)
            box = self._bbox(prim, T, ss, depth.shape)
            if box is None:
                continue
            y0, y1, x0, x1 = box
            d_o, rgb_o, id_o = _trace(
                [prim], [(T[:3, :3], T[:3, 3])], origin, dirs[y0:y1, x0:x1], zfac[y0:y1, x0:x1]
            )
            front = d_o < depth[y0:y1, x0:x1]
            depth[y0:y1, x0:x1][front] = d_o[front]
            rgb[y0:y1, x0:x1][front] = rgb_o[front]
            oid[y0:y1, x0:x1][front] = id_o[front]
        return depth, rgb, oid

    def _bbox(self, prim: Primitive, T: np.ndarray, ss: int, shape):
        """Pixel box (on the ``ss``-times grid) that contains the object's bounding sphere, or None."""
        # Only rays near the object can hit it: tracing just its screen box makes objects almost free.
        radius = float(np.linalg.norm(prim.size)) if prim.kind == "box" else float(prim.size[0])
        pc = self.w2c[:3, :3] @ T[:3, 3] + self.w2c[:3, 3]
        h, w = shape
        if pc[2] <= radius * 1.05:  # object reaches behind the camera: trace everything
            return 0, h, 0, w
        u = (self.K[0, 0] * pc[0] / pc[2] + self.K[0, 2] + 0.5) * ss
        v = (self.K[1, 1] * pc[1] / pc[2] + self.K[1, 2] + 0.5) * ss
        # Conservative screen radius of a sphere seen at distance z (covers perspective stretching).
        dist = float(np.linalg.norm(pc))
        r_pix = ss * max(self.K[0, 0], self.K[1, 1]) * radius / np.sqrt(max(dist**2 - radius**2, 1e-9))
        r_pix *= dist / pc[2] + 0.05
        x0, x1 = int(max(0, np.floor(u - r_pix) - 2)), int(min(w, np.ceil(u + r_pix) + 2))
        y0, y1 = int(max(0, np.floor(v - r_pix) - 2)), int(min(h, np.ceil(v + r_pix) + 2))
        if x0 >= x1 or y0 >= y1:
            return None
        return y0, y1, x0, x1

    def render(self, time: float) -> SynthView:
        depth, rgb, oid = self._composite(0, time)  # pixel centres: exact depth and ids
        k = len(self.rays) - 1
        if self.shutter > 0.0:
            rgb = np.mean([self._composite(k, float(u))[1] for u in shutter_times(time, self.shutter)], axis=0)
        elif self.ss > 1:
            _, rgb, _ = self._composite(k, time)
        return SynthView(_downsample(rgb, self.ss), depth.astype(np.float32), oid)


def render_view(
    scene: SynthScene,
    K: np.ndarray,
    w2c: np.ndarray,
    width: int,
    height: int,
    time: float,
    supersample: int = 1,
) -> SynthView:
    """Render any pinhole camera at any (fractional) time step.

    Args:
        scene: from :func:`make_scene`.
        K: ``[3, 3]`` OpenCV intrinsics (pixels); w2c: ``[4, 4]`` OpenCV world-to-camera.
        width, height: image size in pixels.
        time: time step in [0, steps-1] (fractional values interpolate the motion).
        supersample: rays per pixel along each axis for the colours.

    Returns:
        :class:`SynthView` with rgb, z-depth (world units) and object ids.
    """
    return _CameraRenderer(
        scene, np.asarray(K, float), np.asarray(w2c, float), width, height, supersample
    ).render(time)


def gt_flow(
    scene: SynthScene,
    K0: np.ndarray,
    w2c0: np.ndarray,
    t0: float,
    K1: np.ndarray,
    w2c1: np.ndarray,
    t1: float,
    width: int,
    height: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth 2D motion of every pixel of view 0 (camera ``K0, w2c0`` at time ``t0``) into view 1.

    Each pixel centre is lifted with its exact depth, moved with its object's rigid motion
    ``T_k(t1) T_k(t0)^-1`` (static points stay), and projected into camera ``K1, w2c1``. Occlusion at view 1
    is not tested: compare with ``render_view(...).depth`` of view 1 to find occluded pixels.

    Returns:
        flow ``[H, W, 2]`` float32 (pixels, x then y; NaN where nothing is hit or the point is behind view 1),
        and the object id map of view 0 ``[H, W]``.
    """
    view = render_view(scene, K0, w2c0, width, height, t0)
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pix = np.stack([u, v, np.ones_like(u)], axis=-1)
    cam = (pix @ np.linalg.inv(K0).T) * view.depth[..., None].astype(np.float64)
    world = (cam - w2c0[:3, 3]) @ w2c0[:3, :3]  # R^T (x_cam - t)
    for i in range(len(scene.objects)):
        sel = view.object_id == i + 1
        if sel.any():
            M = scene.object_pose(i, t1) @ np.linalg.inv(scene.object_pose(i, t0))
            world[sel] = world[sel] @ M[:3, :3].T + M[:3, 3]
    cam1 = world @ w2c1[:3, :3].T + w2c1[:3, 3]
    proj = cam1 @ np.asarray(K1, np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv1 = proj[..., :2] / proj[..., 2:3]
    flow = (uv1 - pix[..., :2]).astype(np.float32)
    flow[(view.object_id < 0) | ~(cam1[..., 2] > 1e-9)] = np.nan
    return flow, view.object_id


def _near_far(depth: np.ndarray) -> list[float]:
    d = depth[np.isfinite(depth)]
    return [0.9 * float(np.percentile(d, 1)), 1.1 * float(np.percentile(d, 99))]


def gt_near_far(scene: SynthScene) -> np.ndarray:
    """``[N, 2]`` near/far per camera: 1st/99th depth percentile of the static set, widened by 10%."""
    out = []
    for K, w2c in zip(scene.Ks, scene.w2cs, strict=True):
        origin, dirs, zfac = _rays(K, w2c, scene.width, scene.height, 1)
        out.append(_near_far(_trace(scene.static, [None] * len(scene.static), origin, dirs, zfac)[0]))
    return np.asarray(out)


def write_raw_scene(
    out_dir: str | Path, cfg: SynthConfig | None = None, force: bool = False, progress=None
) -> Path:
    """Render the scene and write it as a raw capture plus ground truth.

    Layout (for ``cfg.layout == "multiview"``)::

        OUT/mv_images/%05d/cam%02d.png     raw images (or cam%02d/%05d.png, or cam%02d.mp4)
        OUT/gt/cameras.json                 K, w2c (OpenCV) per camera, image size, config
        OUT/gt/poses_bounds.npy             the same poses in LLFF format, (N, 17)
        OUT/gt/masks/%05d/cam%02d.png       dynamic mask of every camera and time (0/255)
        OUT/gt/objects.json                 per-time world-from-object 4x4 of each moving object
        OUT/gt/depth/%05d/cam%02d.npy       float32 z-depth, world units (only with cfg.depth)
        OUT/gt/twin_poses_bounds.npy        the real rig a twin was made from (only for cfg.kind "twin")

    Args:
        out_dir: the scene folder to create.
        cfg: generator settings (defaults: :class:`SynthConfig`).
        force: replace an existing folder.
        progress: optional callable ``(done, total)`` called after each camera (cameras render on a thread per
            core; calls are serialised and ``done`` counts up).

    Returns:
        ``out_dir``.
    """
    cfg = cfg or SynthConfig()
    cfg.check()
    out_dir = Path(out_dir)
    if out_dir.exists() and not force:
        raise UserError(f"{out_dir}: already exists; choose another folder or pass --force to replace it")
    if force:
        check_replaceable(
            Path(os.path.abspath(out_dir)), "--force", "raw capture of `nvls synth`", SYNTH_MARKERS
        )
    scene = make_scene(cfg)
    with atomic_dir(out_dir, force=True) as tmp:
        # Cameras are independent and numpy's ray casting releases the GIL for most of its work, so a thread
        # per core renders them side by side (about 1.7x on 2 cores); results do not depend on the order.
        workers = max(1, min(cfg.cameras, available_cores()))
        done = iter(range(1, cfg.cameras + 1))
        lock = threading.Lock()

        def one(ci: int) -> list[float]:
            nf = _write_camera(tmp, scene, cfg, ci)
            if progress is not None:
                with lock:
                    progress(next(done), cfg.cameras)
            return nf

        with ThreadPoolExecutor(workers) as pool:
            bounds = np.asarray(list(pool.map(one, range(cfg.cameras))))
        _write_gt(tmp / "gt", scene, cfg, bounds)
        if cfg.kind == "twin":  # the capture stays self-contained: gt-priors rebuilds the twin from this copy
            np.save(tmp / "gt" / TWIN_POSES, np.load(cfg.poses, allow_pickle=False))
    return out_dir


def camera_gains(cfg: SynthConfig, cam: int) -> np.ndarray:
    """``[3]`` per-channel gain of rig camera ``cam`` (1-based) under ``cfg.exposure`` (ones when it is 0)."""
    if cfg.exposure == 0.0:
        return np.ones(3)
    rng = np.random.default_rng([cfg.seed, 7919, cam])  # its own stream: the scene's draws stay as they were
    e = rng.uniform(-cfg.exposure, cfg.exposure)
    w = rng.uniform(-cfg.exposure / 2, cfg.exposure / 2, size=3)
    return np.exp(e + w)


def sensor_image(rgb: np.ndarray, cfg: SynthConfig, cam: int, step: int) -> np.ndarray:
    """What camera ``cam`` (1-based) records of the rendered ``rgb`` ``[H, W, 3]`` uint8 at time ``step``: its
    gains (:func:`camera_gains`) and ``cfg.noise`` grey levels of Gaussian noise, rounded and clipped to uint8.
    Returns ``rgb`` itself when both are off."""
    if cfg.exposure == 0.0 and cfg.noise == 0.0:
        return rgb
    out = rgb.astype(np.float64) * camera_gains(cfg, cam)
    if cfg.noise > 0.0:
        out += np.random.default_rng([cfg.seed, 104729, cam, step]).normal(0.0, cfg.noise, size=out.shape)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _write_camera(tmp: Path, scene, cfg: SynthConfig, ci: int) -> list[float]:
    """Render rig camera ``ci`` (0-based) at every time step: its raw images (or video), ground-truth masks
    and depth. Returns its (near, far)."""
    cam, gt = ci + 1, tmp / "gt"
    renderer = _CameraRenderer(
        scene, scene.Ks[ci], scene.w2cs[ci], cfg.width, cfg.height, cfg.supersample, cfg.shutter
    )
    near_far = _near_far(renderer.static[0][0])
    writer = None
    if cfg.layout == "videos":
        fourcc = cv2.VideoWriter_fourcc(*"mp4v")
        writer = cv2.VideoWriter(str(tmp / f"cam{cam:02d}.mp4"), fourcc, cfg.fps, (cfg.width, cfg.height))
        if not writer.isOpened():
            raise UserError("OpenCV cannot write mp4v videos here; use --layout multiview")
    for t in range(cfg.steps):
        view = renderer.render(float(t))
        rgb = sensor_image(view.rgb, cfg, cam, t)
        if cfg.layout == "multiview":
            save_image(tmp / "mv_images" / f"{t:05d}" / f"cam{cam:02d}.{cfg.image_ext}", rgb)
        elif cfg.layout == "camera_folders":
            save_image(tmp / f"cam{cam:02d}" / f"{t:05d}.{cfg.image_ext}", rgb)
        else:
            writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        save_image(gt / "masks" / f"{t:05d}" / f"cam{cam:02d}.png", view.dynamic_mask)
        if cfg.depth:
            (gt / "depth" / f"{t:05d}").mkdir(parents=True, exist_ok=True)
            np.save(gt / "depth" / f"{t:05d}" / f"cam{cam:02d}.npy", view.depth)
    if writer is not None:
        writer.release()
    return near_far


def _write_gt(gt: Path, scene, cfg: SynthConfig, bounds: np.ndarray) -> None:
    """``gt/poses_bounds.npy``, ``gt/cameras.json`` and ``gt/objects.json`` (see :func:`write_raw_scene`)."""
    n, steps = cfg.cameras, cfg.steps
    gt.mkdir(parents=True, exist_ok=True)
    np.save(gt / "poses_bounds.npy", llff.opencv_to_llff(scene.w2cs, scene.Ks, cfg.height, cfg.width, bounds))
    cams = [
        {
            "id": i + 1,
            "K": scene.Ks[i],
            "w2c": scene.w2cs[i],
            "near": bounds[i, 0],
            "far": bounds[i, 1],
            "rig_position": int(scene.rig_positions[i]),
        }
        for i in range(n)
    ]
    atomic_write_json(
        gt / "cameras.json",
        {
            "convention": "opencv: x right, y down, z forward; w2c maps world to camera; pixel centres at "
            "integer coordinates",
            "width": cfg.width,
            "height": cfg.height,
            "cameras": cams,
            "config": asdict(cfg),
            "tool_version": __version__,
        },
    )
    objects = [
        {"id": i + 1, "kind": p.kind, "size": p.size,
         "world_from_object": [scene.object_pose(i, float(t)) for t in range(steps)]}
        for i, p in enumerate(scene.objects)
    ]  # fmt: skip
    atomic_write_json(
        gt / "objects.json",
        {
            "note": "world_from_object 4x4 per time step; object ids match gt/masks (id k = objects[k-1])",
            "objects": objects,
            "phase": [scene.phase(float(t)) for t in range(steps)],
        },
    )


def read_gt_cameras(raw_dir: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``(Ks [N, 3, 3], w2cs [N, 4, 4])`` from ``RAW/gt/cameras.json`` of a synthetic scene."""
    meta = json.loads((Path(raw_dir) / "gt" / "cameras.json").read_text())
    Ks = np.asarray([c["K"] for c in meta["cameras"]], float)
    w2cs = np.asarray([c["w2c"] for c in meta["cameras"]], float)
    return Ks, w2cs
