"""Training-view PSNR of a finished run: how well the model reproduces the frames it was trained on.

The only score of a scene without test views (your own video, `nvls import CLIP`): each training frame is
rendered from its own fitted pose at its own time (:func:`benchmarks.api.load_run`, camera ``train_NNN``) and
compared with the stored frame, as uint8 with the `worldtree` protocol's PSNR ``10 log10(255^2 / MSE)``. It
measures the fit, not novel-view synthesis: a model that memorises every frame scores high here.

Usage::

    python -m benchmarks.speed.train_psnr RUN_DIR [--every K] [--downscale D]

``--every K`` scores every K-th frame (faster); ``--downscale D`` renders and compares at the stored size
divided by D (the run's training size with the quick preset's 2). Prints per-frame PSNR, the mean and min.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from benchmarks.api import load_run
from benchmarks.evaluation.metrics.psnr import psnr
from worldtree.imageio import read_image
from worldtree.scene import _scaled_K
from worldtree.scene_schema import read_cameras, resolve_inside


def training_psnr(run_dir: Path, every: int = 1, downscale: int = 1) -> dict[int, float]:
    """``{frame index: PSNR dB}`` of every ``every``-th training frame of the run in ``run_dir``."""
    run = load_run(run_dir, device="cpu")
    doc = read_cameras(run.scene_dir)
    out: dict[int, float] = {}
    names = sorted(n for n, c in run.cameras.items() if c.kind == "train")
    for name in names[::every]:
        cam = run.cameras[name]
        gt = read_image(
            resolve_inside(run.scene_dir, doc.frames[cam.frame].file, run.scene_dir / "cameras.json")
        )
        w, h = cam.width // downscale, cam.height // downscale
        K = torch.as_tensor(_scaled_K(cam.K.numpy().astype(np.float64), downscale), dtype=torch.float32)
        if downscale > 1:
            gt = cv2.resize(gt, (w, h), interpolation=cv2.INTER_AREA)
        img = run.render((K, cam.w2c, w, h), cam.time) if downscale > 1 else run.render(cam)
        pred = (img.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)
        out[cam.frame] = float(psnr(torch.from_numpy(pred)[None], torch.from_numpy(gt)[None], 255.0)[0])
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="A finished run folder of `wtbench run`.")
    ap.add_argument("--every", type=int, default=1, help="Score every K-th training frame.")
    ap.add_argument("--downscale", type=int, default=1, help="Render and compare at the stored size / D.")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    scores = training_psnr(args.run, max(1, args.every), max(1, args.downscale))
    for f, v in scores.items():
        print(f"frame {f:4d}  PSNR {v:6.2f}")
    vals = np.array(list(scores.values()))
    print(
        f"training-view PSNR over {len(vals)} frames: mean {vals.mean():.2f} dB, min {vals.min():.2f}, "
        f"max {vals.max():.2f} ({time.perf_counter() - t0:.0f} s)"
    )


if __name__ == "__main__":
    main()
