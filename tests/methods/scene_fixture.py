"""A tiny scene folder in the docs/scene_format.md layout, ray-traced analytically (no rasterizer involved).

World: a smoothly textured plane at z = 4 and a small red square at z = 2 moving along x with time (the
dynamic content, masked in the test images). Pinhole cameras look along +z from positions on a short
horizontal rig; training frame t uses rig camera 2 + (t mod 6); the test camera (id 1) sits off the rig, or
(``test_on_rig``) at rig camera 2's place, as in the NVIDIA short protocol where it is frame 0's camera.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from worldtree.imageio import write_image

BG_Z = 4.0
FG_Z = 2.0
FG_HALF = 0.3
FG_RGB = np.array([0.9, 0.2, 0.1])


def _fg_centre_x(t: int) -> float:
    return -0.5 + 0.15 * t


def _trace(K: np.ndarray, centre: np.ndarray, width: int, height: int, t: int, ss: int = 3):
    """RGB float ``[H, W, 3]`` and foreground mask ``[H, W]`` of a camera with identity rotation at
    ``centre``, super-sampled ``ss x ss`` per pixel."""
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    u = (np.arange(width)[None, :, None, None] + offs[None, None, None, :]).repeat(height, 0)
    v = (np.arange(height)[:, None, None, None] + offs[None, None, :, None]).repeat(width, 1)
    u, v = np.broadcast_arrays(u, v)
    dx = (u - K[0, 2]) / K[0, 0]
    dy = (v - K[1, 2]) / K[1, 1]
    # Background plane hit.
    s = BG_Z - centre[2]
    x, y = centre[0] + s * dx, centre[1] + s * dy
    bg = np.stack(
        [
            0.5 + 0.3 * np.sin(1.7 * x + 0.3),
            0.5 + 0.3 * np.cos(2.1 * y + 1.0),
            0.5 + 0.25 * np.sin(1.1 * x - 1.6 * y),
        ],
        -1,
    )
    s2 = FG_Z - centre[2]
    fx, fy = centre[0] + s2 * dx, centre[1] + s2 * dy
    fg = (np.abs(fx - _fg_centre_x(t)) < FG_HALF) & (np.abs(fy) < FG_HALF)
    rgb = np.where(fg[..., None], FG_RGB, bg)
    return rgb.mean(axis=(2, 3)), fg.mean(axis=(2, 3)) > 0.5


def write_tiny_scene(
    root: Path, width: int = 64, height: int = 36, frames: int = 6, test_on_rig: bool = False
) -> Path:
    """Write the scene folder at ``root`` (created) and return it."""
    root = Path(root)
    for sub in ("images", "gt_images", "masks"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    f = 0.8 * width
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    rig = {1: np.array([0.05, 0.04, 0.0])}
    for i in range(6):
        rig[2 + i] = np.array([-0.3 + 0.12 * i, 0.0, 0.0])
    if test_on_rig:
        rig[1] = rig[2].copy()
    cameras = []
    for cid, c in rig.items():
        w2c = np.eye(4)
        w2c[:3, 3] = -c
        cameras.append({"id": cid, "K": K.tolist(), "dist": [0, 0, 0, 0, 0], "w2c": w2c.tolist()})
    frame_list, test_list = [], []
    for t in range(frames):
        cid = 2 + t % 6
        rgb, _ = _trace(K, rig[cid], width, height, t)
        name = f"images/{t:05d}.png"
        write_image(root / name, (rgb * 255 + 0.5).astype(np.uint8))
        frame_list.append({"index": t, "file": name, "camera": cid, "time": t, "source_time": t})
        rgb, fg = _trace(K, rig[1], width, height, t)
        gname, mname = f"gt_images/v001_t{t:03d}.png", f"masks/v001_t{t:03d}.png"
        write_image(root / gname, (rgb * 255 + 0.5).astype(np.uint8))
        write_image(root / mname, fg)
        test_list.append({"index": t, "file": gname, "mask": mname, "camera": 1, "time": t, "source_time": t})
    meta = {
        "schema": 1,
        "width": width,
        "height": height,
        "convention": "opencv: x right, y down, z forward; w2c maps world to camera",
        "test_camera": 1,
        "cameras": cameras,
        "frames": frame_list,
        "test_frames": test_list,
        "near": 1.0,
        "far": 6.0,
        "world_transform": {"scale": 1.0, "R": np.eye(3).tolist(), "t": [0, 0, 0], "note": "test fixture"},
    }
    (root / "cameras.json").write_text(json.dumps(meta, indent=1))
    (root / "manifest.json").write_text(json.dumps({"generator": "tests/methods/scene_fixture.py"}))
    return root
