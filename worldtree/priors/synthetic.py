"""A closed-form test scene for the priors: textured planes seen by a static rig, one moving textured square.

Everything is ray-cast analytically, so depth, optical flow, point tracks and the dynamic mask of any
(camera, time) are exact. It is small and fast on purpose: unit tests and the priors benchmark use it when the
full synthetic generator of ``nvidia_ls`` is not wanted.

World: OpenCV axes (x right, y down, z forward). A back wall ``z = wall_depth`` and a floor ``y = floor_y``
carry multi-octave value-noise textures; a square of side ``object_size`` (its own texture) faces the rig at
depth ``object_depth`` and moves on an ellipse while spinning about its normal. Rig cameras sit on a horizontal
line, toed in towards the wall centre; training frame t uses camera ``ping-pong(t)`` as in NVIDIA-LS.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

_LATTICE = 64  # side of the random lattice each texture octave samples (wraps around)


@dataclass(frozen=True)
class PlanarSceneConfig:
    """Settings of the closed-form scene (scene units are metres-like)."""

    width: int = 160
    height: int = 96
    num_frames: int = 8
    num_cameras: int = 11
    """Training rig cameras, visited in ping-pong order (1, 2, ..., n, n-1, ...)."""
    baseline: float = 0.1
    """Distance between neighbouring rig cameras."""
    focal_ratio: float = 0.9
    """Focal length as a fraction of the image width."""
    toe_in_depth: float = 4.0
    """Cameras are rotated to look at (0, 0, toe_in_depth)."""
    wall_depth: float = 4.0
    floor_y: float = 0.7
    object_depth: float = 2.2
    object_size: float = 0.9
    object_path: tuple[float, float] = (0.35, 0.25)
    """Semi-axes (x, y) of the ellipse the square's centre follows."""
    object_step: float = 0.25
    """Angle advanced along the ellipse per frame (radians); 0 gives a static scene."""
    object_spin: float = 0.05
    """Rotation of the square about its normal per frame (radians)."""
    texture_cells: tuple[float, ...] = (2.5, 6.0, 14.0)
    """Texture octaves in lattice cells per scene unit."""
    supersample: int = 2
    """Colour is averaged over supersample^2 rays per pixel (anti-aliasing)."""
    seed: int = 0


def ping_pong(t: int, n: int) -> int:
    """Camera index (0-based) of training frame t when n cameras are visited 0, 1, ..., n-1, n-2, ..., 1, 0."""
    if n <= 1:
        return 0
    period = 2 * (n - 1)
    k = t % period
    return k if k < n else period - k


class PlanarScene:
    """Ray-casts the scene of a :class:`PlanarSceneConfig`; all outputs are numpy float32/float64."""

    def __init__(self, cfg: PlanarSceneConfig) -> None:
        self.cfg = cfg
        rng = np.random.default_rng(cfg.seed)
        # One lattice per (texture, octave): wall, floor, object.
        self._lattices = [
            [rng.random((_LATTICE, _LATTICE, 3)).astype(np.float32) for _ in cfg.texture_cells]
            for _ in range(3)
        ]
        f = cfg.focal_ratio * cfg.width
        self.K = np.array([[f, 0, (cfg.width - 1) / 2], [0, f, (cfg.height - 1) / 2], [0, 0, 1]], np.float64)
        self.rig_w2c = [self._rig_pose(i) for i in range(cfg.num_cameras)]

    # ---------------------------------------------------------------- cameras
    def _rig_pose(self, i: int) -> np.ndarray:
        cfg = self.cfg
        x = (i - (cfg.num_cameras - 1) / 2) * cfg.baseline
        centre = np.array([x, 0.02 * np.sin(1.7 * i), 0.0])  # small vertical jitter, as in a real rig
        fwd = np.array([0.0, 0.0, cfg.toe_in_depth]) - centre
        fwd /= np.linalg.norm(fwd)
        right = np.cross(np.array([0.0, 1.0, 0.0]), fwd)
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        R = np.stack([right, down, fwd])  # rows: camera axes in world coordinates
        w2c = np.eye(4)
        w2c[:3, :3] = R
        w2c[:3, 3] = -R @ centre
        return w2c

    def frame_camera(self, t: int) -> int:
        """Rig camera index of training frame t."""
        return ping_pong(t, self.cfg.num_cameras)

    def frame_pose(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """(K [3,3], w2c [4,4]) of training frame t."""
        return self.K.copy(), self.rig_w2c[self.frame_camera(t)].copy()

    # ---------------------------------------------------------------- object motion
    def object_pose(self, t: float) -> np.ndarray:
        """Object-to-world rigid transform [4,4] of the square at time t."""
        cfg = self.cfg
        a = cfg.object_step * t
        c = np.array(
            [cfg.object_path[0] * np.sin(a), -cfg.object_path[1] * (1 - np.cos(a)), cfg.object_depth]
        )
        s = cfg.object_spin * t
        R = np.array([[np.cos(s), -np.sin(s), 0], [np.sin(s), np.cos(s), 0], [0, 0, 1]])
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = c
        return T

    # ---------------------------------------------------------------- ray casting
    def _texture(self, which: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        out = np.zeros((*u.shape, 3), np.float32)
        wsum = 0.0
        for k, (cells, lat) in enumerate(zip(self.cfg.texture_cells, self._lattices[which], strict=True)):
            mx = np.mod(u * cells, _LATTICE).astype(np.float32)
            my = np.mod(v * cells, _LATTICE).astype(np.float32)
            w = 0.6**k
            out += w * cv2.remap(lat, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            wsum += w
        # Averaging octaves pulls values to the mean; stretch the contrast back.
        return np.clip(0.5 + 2.2 * (out / wsum - 0.5), 0.05, 0.95)

    def _cast(self, K: np.ndarray, w2c: np.ndarray, t: float, px: np.ndarray, py: np.ndarray) -> dict:
        """Intersect the rays through pixel positions (px, py) [...]: world point, depth, kind, object coords."""
        R, tr = w2c[:3, :3], w2c[:3, 3]
        centre = -R.T @ tr
        rays_cam = np.stack([(px - K[0, 2]) / K[0, 0], (py - K[1, 2]) / K[1, 1], np.ones_like(px)], -1)
        d = rays_cam @ R  # world directions with unit camera z
        inf = np.full(px.shape, np.inf)
        # Wall z = wall_depth and floor y = floor_y (positive ray parameter only).
        with np.errstate(divide="ignore", invalid="ignore"):
            s_wall = (self.cfg.wall_depth - centre[2]) / d[..., 2]
            s_floor = (self.cfg.floor_y - centre[1]) / d[..., 1]
        s_wall = np.where(s_wall > 0, s_wall, inf)
        s_floor = np.where(s_floor > 0, s_floor, inf)
        # Square: move the ray into object coordinates and intersect z_obj = 0.
        T = self.object_pose(t)
        Ro, co = T[:3, :3], T[:3, 3]
        o_l = Ro.T @ (centre - co)
        d_l = d @ Ro
        with np.errstate(divide="ignore", invalid="ignore"):
            s_obj = -o_l[2] / d_l[..., 2]
        p_l = o_l + s_obj[..., None] * d_l
        half = self.cfg.object_size / 2
        hit = (s_obj > 0) & (np.abs(p_l[..., 0]) < half) & (np.abs(p_l[..., 1]) < half)
        s_obj = np.where(hit, s_obj, inf)
        s_all = np.stack([s_wall, s_floor, s_obj], -1)
        kind = np.argmin(s_all, -1)
        s = np.take_along_axis(s_all, kind[..., None], -1)[..., 0]
        kind = np.where(np.isfinite(s), kind, -1)
        s = np.where(np.isfinite(s), s, 1e6)
        X = centre + s[..., None] * d
        return {"X": X, "depth": s, "kind": kind, "obj": p_l}  # depth = s because d has unit camera z

    def _shade(self, hit: dict) -> np.ndarray:
        X, kind, p_l = hit["X"], hit["kind"], hit["obj"]
        rgb = np.zeros((*kind.shape, 3), np.float32)
        for k, (u, v) in enumerate(
            ((X[..., 0], X[..., 1]), (X[..., 0], X[..., 2]), (p_l[..., 0], p_l[..., 1]))
        ):
            sel = kind == k
            if sel.any():
                # Texture the whole grid, then select: remap maps must stay 2-D and small.
                rgb = np.where(sel[..., None], self._texture(k, u, v), rgb)
        return rgb

    def render(self, K: np.ndarray, w2c: np.ndarray, t: float) -> dict:
        """Render one view. Returns rgb [H,W,3] float32 in [0,1], depth [H,W] (camera z), mask [H,W] bool
        (the moving square), kind [H,W] int (0 wall, 1 floor, 2 square, -1 nothing)."""
        H, W, ss = self.cfg.height, self.cfg.width, max(1, self.cfg.supersample)
        py, px = np.mgrid[0:H, 0:W].astype(np.float64)
        centre_hit = self._cast(K, w2c, t, px, py)
        rgb = np.zeros((H, W, 3), np.float32)
        offs = (np.arange(ss) + 0.5) / ss - 0.5
        for oy in offs:
            for ox in offs:
                rgb += self._shade(self._cast(K, w2c, t, px + ox, py + oy))
        rgb /= ss * ss
        return {
            "rgb": rgb,
            "depth": centre_hit["depth"].astype(np.float32),
            "mask": centre_hit["kind"] == 2,
            "kind": centre_hit["kind"],
        }

    # ---------------------------------------------------------------- ground truth correspondences
    def _world_points(self, t: int, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points [N,3] seen at pixel positions pts [N,2] of training frame t and their kind [N]."""
        K, w2c = self.frame_pose(t)
        hit = self._cast(K, w2c, t, pts[:, 0].astype(np.float64), pts[:, 1].astype(np.float64))
        return hit["X"], hit["kind"]

    def transfer(self, t0: int, pts: np.ndarray, t1: int) -> tuple[np.ndarray, np.ndarray]:
        """Where the surface points seen at pts [N,2] of frame t0 appear in frame t1.

        Returns positions [N,2] and visibility [N] (in the image and not occluded in frame t1).
        """
        X, kind = self._world_points(t0, pts)
        obj = kind == 2
        if obj.any():
            M = self.object_pose(t1) @ np.linalg.inv(self.object_pose(t0))
            X[obj] = X[obj] @ M[:3, :3].T + M[:3, 3]
        K, w2c = self.frame_pose(t1)
        Xc = X @ w2c[:3, :3].T + w2c[:3, 3]
        z = Xc[:, 2]
        uv = (Xc[:, :2] / np.maximum(z, 1e-9)[:, None]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        H, W = self.cfg.height, self.cfg.width
        inside = (z > 0) & (uv[:, 0] > -0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < H - 0.5)
        vis = inside.copy()
        if inside.any():
            hit = self._cast(K, w2c, t1, uv[inside, 0], uv[inside, 1])
            vis[inside] = z[inside] <= hit["depth"] * (1 + 1e-3) + 1e-6
        vis &= kind >= 0
        return uv.astype(np.float32), vis

    def flow(self, t0: int, t1: int) -> tuple[np.ndarray, np.ndarray]:
        """Exact optical flow [H,W,2] from frame t0 to t1 and its validity [H,W] (visible in both)."""
        H, W = self.cfg.height, self.cfg.width
        py, px = np.mgrid[0:H, 0:W].astype(np.float32)
        pts = np.stack([px.ravel(), py.ravel()], -1)
        uv, vis = self.transfer(t0, pts, t1)
        return (uv - pts).reshape(H, W, 2), vis.reshape(H, W)

    # ---------------------------------------------------------------- the training video
    def frames(self) -> dict:
        """Render every training frame: rgb [T,H,W,3], depth [T,H,W], mask [T,H,W], Ks, w2cs, cameras."""
        out = {"rgb": [], "depth": [], "mask": [], "Ks": [], "w2cs": [], "cameras": []}
        for t in range(self.cfg.num_frames):
            K, w2c = self.frame_pose(t)
            r = self.render(K, w2c, t)
            for k in ("rgb", "depth", "mask"):
                out[k].append(r[k])
            out["Ks"].append(K)
            out["w2cs"].append(w2c)
            out["cameras"].append(self.frame_camera(t) + 2)  # rig ids start at 2 (1 is the test camera)
        return {k: np.stack(v) for k, v in out.items()}

    def to_scene(self, frames: dict | None = None, name: str = "planar"):
        """The training video as a :class:`worldtree.scene.Scene` (images quantised to 8 bits)."""
        from worldtree.scene import Scene

        fr = frames if frames is not None else self.frames()
        imgs = np.round(fr["rgb"] * 255).astype(np.uint8)
        T = imgs.shape[0]
        return Scene(
            name=name,
            root=Path(name),
            images=torch.from_numpy(imgs).float() / 255.0,
            Ks=torch.from_numpy(fr["Ks"]).float(),
            w2cs=torch.from_numpy(fr["w2cs"]).float(),
            frame_cameras=torch.from_numpy(fr["cameras"]).long(),
            times=torch.arange(T),
            test_images=torch.zeros(0, 1, 1, 3),
            test_K=torch.from_numpy(self.K).float(),
            test_w2c=torch.eye(4),
            test_times=torch.zeros(0, dtype=torch.long),
            test_masks=None,
            test_files=[],
            near=1.0,
            far=6.0,
        )


def write_scene_folder(scene: PlanarScene, out_dir: str | Path, frames: dict | None = None) -> Path:
    """Write the training video in the scene layout of ``docs/scene_format.md`` (no test camera).

    Enough for :func:`worldtree.scene.load_scene` and ``wtbench prep``; used by tests.
    """
    from worldtree.atomic import atomic_write_json
    from worldtree.imageio import write_image

    out = Path(out_dir)
    fr = frames if frames is not None else scene.frames()
    cams, frames_meta = {}, []
    for t in range(len(fr["rgb"])):
        write_image(out / "images" / f"{t:05d}.png", np.round(fr["rgb"][t] * 255).astype(np.uint8))
        cid = int(fr["cameras"][t])
        cams[cid] = {
            "id": cid,
            "K": fr["Ks"][t].tolist(),
            "dist": [0, 0, 0, 0, 0],
            "w2c": fr["w2cs"][t].tolist(),
        }
        frames_meta.append(
            {"index": t, "file": f"images/{t:05d}.png", "camera": cid, "time": t, "source_time": t}
        )
    atomic_write_json(
        out / "cameras.json",
        {
            "schema": 1,
            "width": scene.cfg.width,
            "height": scene.cfg.height,
            "convention": "opencv: x right, y down, z forward; w2c maps world to camera",
            "test_camera": 1,
            "cameras": [cams[k] for k in sorted(cams)],
            "frames": frames_meta,
            "test_frames": [],
            "near": 1.0,
            "far": 6.0,
        },
    )
    return out
