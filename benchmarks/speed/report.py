"""Size and build time of `wtbench report` for a large generated sweep; prints seconds and page sizes.

    python -m benchmarks.speed.report [--scenes 4] [--configs 25] [--frames 24] [--width 480] [--height 270]
                                      [--viewer-frames 24]

Writes ``--scenes`` scene folders (smooth images with noise, a moving square as the mask) and ``--configs``
finished runs per scene (renders = ground truth plus noise, metrics.csv with per-frame rows, timing.json) in
a temporary folder, then times :func:`benchmarks.reporting.webreport.site.build_report` and prints the size of the
main page, the largest scene page, the whole site and its image count: what a browser has to load to open it.
The scores are drawn at random (the report's speed does not depend on them). Timings depend on the machine
and its load.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd


def make_sweep(root: Path, scenes: int, configs: int, frames: int, width: int, height: int) -> Path:
    """Scenes under ``root/scenes``, finished runs under ``root/runs`` (returned)."""
    from benchmarks.evaluation.evaluate import COLUMNS, EvalResult, write_result
    from worldtree.imageio import write_image
    from worldtree.infra.atomic import atomic_write_json

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:height, 0:width]
    runs = root / "runs"
    for s in range(scenes):
        scene = root / "scenes" / f"Scene{s}"
        for sub in ("gt_images", "masks"):
            (scene / sub).mkdir(parents=True)
        test = []
        gts = []
        for t in range(frames):
            base = np.stack([xx / width, yy / height, ((xx + yy + 3 * t + 17 * s) % 64) / 64.0], -1) * 255
            gt = np.clip(base + rng.normal(0, 4, base.shape), 0, 255).astype(np.uint8)
            mask = (np.abs(xx - width * (0.2 + 0.6 * t / max(1, frames - 1))) < width / 10) & (
                np.abs(yy - height / 2) < height / 6
            )
            write_image(scene / f"gt_images/v001_t{t:03d}.png", gt)
            write_image(scene / f"masks/v001_t{t:03d}.png", mask)
            test.append(
                {"file": f"gt_images/v001_t{t:03d}.png", "mask": f"masks/v001_t{t:03d}.png", "time": t}
            )
            gts.append(gt)
        (scene / "cameras.json").write_text(json.dumps({"schema": 1, "test_frames": test}))
        for c in range(configs):
            folder = runs / scene.name / "worldtree" / f"quick-depth{c}"
            (folder / "renders").mkdir(parents=True)
            noise = 2.0 + c
            for t, gt in enumerate(gts):
                pred = np.clip(gt + rng.normal(0, noise, gt.shape), 0, 255).astype(np.uint8)
                write_image(folder / f"renders/v001_t{t:03d}.png", pred)
            rows = [
                {
                    "frame": f"v001_t{t:03d}",
                    **{m: float(v) for m, v in zip(COLUMNS[1:], rng.random(8) + 20, strict=True)},
                }
                for t in range(frames)
            ]
            mean = {m: float(np.mean([r[m] for r in rows])) for m in COLUMNS[1:]}
            table = pd.DataFrame([*rows, {"frame": "mean", **mean}])[list(COLUMNS)]
            write_result(
                EvalResult(table, {"protocol": {"name": "worldtree", "version": "1"}}), folder / "metrics.csv"
            )
            record = {
                "method": "worldtree",
                "preset": "quick",
                "config": {"depth": c},
                "seed": 0,
                "scene": str(scene),
            }
            atomic_write_json(folder / "config.json", record)
            atomic_write_json(
                folder / "timing.json", {"stages_s": {"train": 10.0 + 5 * c}, "peak_rss_mib": 500.0}
            )
            atomic_write_json(folder / "DONE", {})
    return runs


def _size(path: Path) -> int:
    return (
        sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
        if path.is_dir()
        else path.stat().st_size
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--configs", type=int, default=25)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--width", type=int, default=480)
    ap.add_argument("--height", type=int, default=270)
    ap.add_argument("--viewer-frames", type=int, default=24)
    args = ap.parse_args()
    from benchmarks.reporting.webreport.site import ReportOptions, build_report

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        runs = make_sweep(tmp, args.scenes, args.configs, args.frames, args.width, args.height)
        print(f"generated {args.scenes * args.configs} runs in {time.perf_counter() - t0:.1f} s")
        out = tmp / "report"
        t0 = time.perf_counter()
        build_report([runs], out, ReportOptions(viewer_frames=args.viewer_frames), log=lambda s: None)
        dt = time.perf_counter() - t0
        pages = sorted((out / "scenes").glob("*.html"), key=lambda p: p.stat().st_size)
        images = [p for p in out.rglob("*") if p.suffix in (".png", ".jpg")]
        print(
            f"report of {args.scenes * args.configs} runs ({args.scenes} scenes x {args.configs} configurations, "
            f"{args.frames} frames {args.width}x{args.height}, viewer {args.viewer_frames or args.frames} frames)"
        )
        print(f"  build time        {dt:8.1f} s")
        print(f"  index.html        {_size(out / 'index.html') / 1e3:8.1f} kB")
        print(f"  largest scene page{_size(pages[-1]) / 1e3:8.1f} kB")
        print(f"  images            {len(images):8d} ({_size(out / 'img') / 1e6:.1f} MB in img/)")
        print(f"  whole site        {_size(out) / 1e6:8.1f} MB")


if __name__ == "__main__":
    main()
