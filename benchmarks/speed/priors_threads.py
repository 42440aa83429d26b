"""Wall and CPU time of the classical priors against the number of threads, and whether the results agree.

    python -m benchmarks.speed.priors_threads SCENE [--threads 1,2] [--frames N] [--downscale D]

Loads a scene built by `nvls build`, keeps its first ``--frames`` training frames (all by default) at
``--downscale``, and runs :func:`worldtree.priors.compute_priors` without a cache once per thread count
(``PriorsConfig.threads``). Prints per run the wall seconds, the CPU seconds of the process (every thread), the
seconds spent in each prior (from the progress callback) and whether every array equals the first run's
bit for bit. Figures are printed, never asserted; run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
import types

from worldtree.priors import PriorsConfig, compute_priors
from worldtree.scene import load_scene


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", help="scene folder written by nvls build")
    ap.add_argument("--threads", default="1,2", help="comma-separated thread counts (0: one per core)")
    ap.add_argument("--frames", type=int, default=0, help="first N training frames (0: all)")
    ap.add_argument("--downscale", type=int, default=1)
    args = ap.parse_args(argv)
    try:
        counts = [int(x) for x in args.threads.split(",") if x.strip()]
    except ValueError:
        print(f"--threads {args.threads!r}: give comma-separated integers, e.g. 1,2", file=sys.stderr)
        return 2
    s = load_scene(args.scene, downscale=args.downscale, load_masks=False)
    n = s.num_frames if args.frames <= 0 else min(args.frames, s.num_frames)
    sub = types.SimpleNamespace(
        images=s.images[:n], Ks=s.Ks[:n], w2cs=s.w2cs[:n], near=s.near, far=s.far, name=s.name, root=None
    )
    print(f"{args.scene}: {n} frames at {s.width}x{s.height}")
    first = None
    for th in counts:
        spans: dict[str, list[float]] = {}
        t0 = time.perf_counter()

        def progress(stage: str, done: int, total: int, spans=spans, t0=t0) -> None:
            now = time.perf_counter() - t0
            spans.setdefault(stage, [now, now])[1] = now

        c0 = time.process_time()
        pri = compute_priors(sub, dataclasses.replace(PriorsConfig(), threads=th), None, progress)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        first = pri if first is None else first
        stages = "  ".join(f"{k} ends {b:.1f}" for k, (_, b) in spans.items())
        same = pri.identical(first)
        print(f"threads {th}: {wall:.1f} s wall, {cpu:.1f} s CPU; {stages}; same as the first run: {same}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
