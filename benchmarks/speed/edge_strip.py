"""The strip at a rig's end, as a fixed camera sees it at every time: a test view's static part, scored without it.

The NVIDIA protocol's test camera is training frame 0's camera held at every time. The left (or right) edge of
its image is wall that few other training cameras see, so the model learns it almost from frame 0 alone, and
whatever moves or is misplaced there shows in every test view (issue #28: "the left edge of the wall ... is
smeared"). Where nothing moves in that strip (Balloon1's left tenth: posters on a wall, at every time), the
test view's strip is frame 0's own strip, so the strip can be scored on a scene without test views: the run
renders frame ``--frame``'s camera (its fitted pose) at every time and each render's strip is compared with
that frame's image, as uint8 PSNR (``10 log10(255^2 / MSE)``).

Usage::

    python -m benchmarks.speed.edge_strip RUN_DIR [RUN_DIR ...] [--frame 0] [--side left] [--fraction 0.1]

Prints, per run, the strip's PSNR at every time and the mean. A strip the moving objects enter is not static
and this measure does not apply there (check the training frames first).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from benchmarks.api import load_run
from benchmarks.evaluation.metrics.psnr import psnr
from worldtree.imageio import read_image
from worldtree.infra.errors import UserError
from worldtree.pixels import as_uint8
from worldtree.scene_schema import read_cameras, resolve_inside


def strip_psnr(run_dir: Path, frame: int = 0, side: str = "left", fraction: float = 0.1) -> dict[int, float]:
    """``{time: PSNR dB}`` of the ``fraction`` of the image width at ``side`` of training frame ``frame``'s
    camera, rendered at every time of the run in ``run_dir``, against that frame's stored image."""
    if side not in ("left", "right"):
        raise UserError(f"--side {side!r}: choose left or right")
    if not 0.0 < fraction <= 1.0:
        raise UserError(f"--fraction {fraction}: give a share of the image width in (0, 1]")
    run = load_run(run_dir, device="cpu")
    name = f"train_{frame:03d}"
    if name not in run.cameras:
        frames = sum(c.kind == "train" for c in run.cameras.values())
        raise UserError(f"--frame {frame}: {run_dir} has training frames 0..{frames - 1}")
    cam = run.cameras[name]
    doc = read_cameras(run.scene_dir)
    gt = read_image(resolve_inside(run.scene_dir, doc.frames[cam.frame].file, run.scene_dir / "cameras.json"))
    w = max(1, int(round(cam.width * fraction)))
    cols = slice(0, w) if side == "left" else slice(cam.width - w, cam.width)
    ref = torch.from_numpy(np.ascontiguousarray(gt[:, cols]))[None]
    out: dict[int, float] = {}
    for t in run.times:
        # The frame's camera at another time: its given pose, which the run maps to the one it fitted.
        img = run.render((cam.K, cam.w2c, cam.width, cam.height), int(t))
        out[int(t)] = float(psnr(as_uint8(img[:, cols].contiguous())[None], ref, 255.0)[0])
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", type=Path, nargs="+", help="Finished run folders of `wtbench run`.")
    ap.add_argument(
        "--frame", type=int, default=0, help="The training frame whose camera is held (default 0)."
    )
    ap.add_argument("--side", default="left", help="left or right edge of the image.")
    ap.add_argument("--fraction", type=float, default=0.1, help="Share of the image width scored.")
    args = ap.parse_args(argv)
    for run in args.runs:
        try:
            scores = strip_psnr(run, args.frame, args.side, args.fraction)
        except UserError as e:
            raise SystemExit(f"error: {e}") from None
        vals = np.array(list(scores.values()))
        per_time = " ".join(f"{v:.2f}" for v in vals)
        print(
            f"{run}: {args.side} {args.fraction:.0%} of frame {args.frame}'s camera at every time: {per_time}"
        )
        print(f"  mean {vals.mean():.2f} dB, min {vals.min():.2f}")


if __name__ == "__main__":
    main()
