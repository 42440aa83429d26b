"""Test helper: write a closed-form generated capture in the DynamicNeRF layout (what `nvls import` reads).

``images/NNN.png``, LLFF ``poses_bounds.npy`` (one row per frame), ``disp/NNN.npy`` (exact inverse depth,
optionally scaled and shifted like a relative MiDaS map), ``flow/NNN_fwd.npz`` / ``NNN_bwd.npz`` (exact flow
to the next / previous frame, key ``flow``, plus ``mask``), ``motion_masks/NNN.png`` and the test views
``gt/v000_tXXX.png`` (the camera of frame 0 at every time, the 12-frame protocol).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmarks.fixtures.planar_scene import PlanarScene
from nvidia_ls import llff
from worldtree.imageio import write_image


def export_dynamicnerf(
    scene: PlanarScene, out: Path, disp_scale: float = 1.0, disp_shift: float = 0.0
) -> dict[str, np.ndarray]:
    """Write the layout under ``out``; returns the exact arrays written (rgb u8, depth, masks, Ks, w2cs,
    flow {(i, j): [H, W, 2]}, test rgb u8)."""
    fr = scene.frames()
    T = fr["rgb"].shape[0]
    H, W = scene.cfg.height, scene.cfg.width
    rgb = np.round(fr["rgb"] * 255).astype(np.uint8)
    for t in range(T):
        write_image(out / "images" / f"{t:03d}.png", rgb[t])
        write_image(out / "motion_masks" / f"{t:03d}.png", fr["mask"][t])
        (out / "disp").mkdir(parents=True, exist_ok=True)
        np.save(out / "disp" / f"{t:03d}.npy", (disp_scale / fr["depth"][t] + disp_shift).astype(np.float32))
    bounds = np.tile([[0.5, 8.0]], (T, 1))
    np.save(out / "poses_bounds.npy", llff.opencv_to_llff(fr["w2cs"], fr["Ks"], H, W, bounds))
    flows = {}
    (out / "flow").mkdir(parents=True, exist_ok=True)
    for t in range(T):
        for j, tag in ((t + 1, "fwd"), (t - 1, "bwd")):
            if 0 <= j < T:
                f, valid = scene.flow(t, j)
                flows[(t, j)] = f
                np.savez(out / "flow" / f"{t:03d}_{tag}.npz", flow=f, mask=valid)
    K0, w2c0 = scene.frame_pose(0)
    test = np.stack([np.round(scene.render(K0, w2c0, t)["rgb"] * 255).astype(np.uint8) for t in range(T)])
    for t in range(T):
        write_image(out / "gt" / f"v000_t{t:03d}.png", test[t])
    return {"rgb": rgb, "depth": fr["depth"], "mask": fr["mask"], "Ks": fr["Ks"], "w2cs": fr["w2cs"],
            "flow": flows, "test": test}  # fmt: skip
