"""Example of the Python API (docs/python_api.md): load a finished run, list its cameras and times, render the
test camera in colour, depth and its dynamic part, look through a training camera, get the Gaussians at a time.

    python docs/examples/python_api.py RUN_DIR OUT_DIR

Writes PNG files into OUT_DIR and prints what it found (tests/benchmarks/test_api.py runs it on a tiny run).
"""

import sys
from pathlib import Path

import numpy as np

from benchmarks.api import load_run
from worldtree.imageio import write_image


def to_png(img) -> np.ndarray:
    """``[H, W, 3]`` float in [0, 1] -> uint8, rounded as `wtbench run` writes its renders."""
    return (img.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)


def depth_to_png(depth) -> np.ndarray:
    """``[H, W]`` depth (NaN: nothing drawn) -> grey uint8, near bright, far dark, nothing black."""
    d = depth.numpy()
    ok = np.isfinite(d)
    out = np.zeros(d.shape, np.uint8)
    if ok.any():
        lo, hi = np.percentile(d[ok], [2, 98])
        out[ok] = (255 * (1 - np.clip((d[ok] - lo) / max(hi - lo, 1e-9), 0, 1))).astype(np.uint8)
    return out


def main(run_dir: str, out_dir: str) -> None:
    run = load_run(run_dir)  # CUDA when present, else the CPU
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    print(f"{run.method_name} run, {len(run.times)} times, cameras: {', '.join(run.cameras)}")

    t = run.times[len(run.times) // 3]
    cam = run.cameras["test"]
    write_image(out / f"test_t{t:03d}.png", to_png(run.render(cam, t)))  # = the run's renders/ at t
    write_image(out / f"depth_t{t:03d}.png", depth_to_png(run.render(cam, t, mode="depth")))
    write_image(out / f"dynamic_t{t:03d}.png", to_png(run.render(cam, t, mode="dynamic")))

    first = run.cameras["train_000"]  # a training camera, seen from its fitted pose at its own time
    write_image(out / f"train_000_t{first.time:03d}.png", to_png(run.render(first)))

    for time in (run.times[0], run.times[-1]):
        frame = run.gaussians_at(time)
        node = run.node_at(time)
        where = f", node {node}" if node is not None else ""
        print(f"time {time}: {len(frame)} Gaussians, {int(frame.dynamic.sum())} dynamic{where}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
