"""Speed of `nvls build` on a synthetic rig, broken into stages; prints the figures.

    python -m benchmarks.speed.nvls_build                      # 12 cameras x 200 steps at 480x270
    python -m benchmarks.speed.nvls_build --steps 40 --width 240 --height 135   # a quick run

The synthetic capture is rendered first (its time is reported apart: it is not part of a build). Stage
times come from the ``timings_s`` the build records in manifest.json: index (layout scan), sfm (pycolmap on
one time step), read (decoding raw frames), undistort (remap + resize), masks (background model), write
(PNG encoding, cameras.json, poses_bounds.npy, preview), hash (sha256 of every file).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from nvidia_ls.build import BuildConfig, build_scene
from nvidia_ls.synth import SynthConfig, write_raw_scene


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cameras", type=int, default=12)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--width", type=int, default=480)
    ap.add_argument("--height", type=int, default=270)
    ap.add_argument("--frames", type=int, default=160, help="--frames of the build")
    ap.add_argument("--camera-model", default="shared")
    ap.add_argument("--sfm-threads", type=int, default=1)
    ap.add_argument("--workdir", type=Path, default=None, help="keep the raw and built scene here")
    args = ap.parse_args(argv)

    with tempfile.TemporaryDirectory(prefix="nvls_speed_") as tmp:
        work = args.workdir or Path(tmp)
        cfg = SynthConfig(cameras=args.cameras, steps=args.steps, width=args.width, height=args.height)
        t0 = time.perf_counter()
        raw = write_raw_scene(work / "SpeedRig", cfg, force=True)
        t_synth = time.perf_counter() - t0
        t0 = time.perf_counter()
        scene = build_scene(
            raw,
            work / "built",
            BuildConfig(
                frames=args.frames, camera_model=args.camera_model, sfm_threads=args.sfm_threads, force=True
            ),
        )
        t_build = time.perf_counter() - t0
        man = json.loads((scene / "manifest.json").read_text())

    timings = man["timings_s"]
    n_files = len(man["files"])
    print(
        f"nvls build speed: {args.cameras} cameras x {args.steps} steps at {args.width}x{args.height}, "
        f"--frames {args.frames}, camera model {args.camera_model}, CPU threads available {os.cpu_count()}"
    )
    print(f"  synthetic capture rendered in {t_synth:.1f} s (not part of the build)")
    print(
        f"  build total {t_build:.2f} s for {man['counts']['frames']} training + {man['counts']['test_frames']} "
        f"test frames, {n_files} files"
    )
    print(f"  {'stage':<10} {'seconds':>9} {'share':>7}")
    for stage in ("index", "sfm", "read", "undistort", "masks", "write", "hash"):
        v = timings.get(stage, 0.0)
        print(f"  {stage:<10} {v:9.2f} {100 * v / max(t_build, 1e-9):6.1f}%")
    other = t_build - sum(timings.values())
    print(f"  {'other':<10} {other:9.2f} {100 * other / max(t_build, 1e-9):6.1f}%")
    print(
        f"  SfM: time step {man['poses'].get('sfm_time')}, reprojection error "
        f"{man['poses'].get('reprojection_error_px', float('nan')):.3f} px, {man['poses'].get('num_points')} points"
    )


if __name__ == "__main__":
    main()
