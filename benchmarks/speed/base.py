"""Base method speed: stage times, iterations/second and peak memory for the first N steps of each stage.

    python -m benchmarks.speed.base [--scene SCENE] [--presets quick,paper] [--steps 200] [--device auto]

Without --scene a 320x180 x 40-step synthetic capture is generated and built (as `wtbench demo` does). Every
optimisation stage (BA, static warm-up, scaffold fit, photometric fit) is capped at --steps so the presets'
per-step costs can be compared; test-pose refinement is capped at 20 + 2 per frame. Figures are printed,
never asserted. Priors are computed once and cached under the scene, so the first preset's priors time
includes the computation and the next ones only the cache read.
"""

from __future__ import annotations

import argparse
import dataclasses
import resource
import sys
import tempfile
import time
from pathlib import Path


def _capped(cfg, steps: int):
    """``cfg`` with every stage limited to ``steps`` optimisation steps."""
    r = dataclasses.replace
    return r(
        cfg,
        steps=min(cfg.steps, steps),
        ba=r(cfg.ba, steps=min(cfg.ba.steps, steps)),
        sw=r(cfg.sw, steps=min(cfg.sw.steps, steps)),
        scaffold_fit=r(cfg.scaffold_fit, steps=min(cfg.scaffold_fit.steps, steps)),
        test_pose=r(cfg.test_pose, first_steps=20, next_steps=2),
        checkpoint_every=10**9,
    )


def _scene(path: str | None, work: Path) -> Path:
    if path:
        return Path(path)
    from nvidia_ls.build import BuildConfig, build_scene
    from nvidia_ls.synth import SynthConfig, write_raw_scene

    raw = write_raw_scene(work / "raw" / "SynthBalloon", SynthConfig(steps=40, motion="slow_fast"))
    return build_scene(raw, work / "scenes", BuildConfig())


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", help="scene folder (default: generate one)")
    ap.add_argument("--presets", default="quick,paper")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--device", default="auto")
    args = ap.parse_args(argv)

    import torch

    from methods.registry import get_method
    from worldtree.infra.determinism import deterministic_for
    from worldtree.infra.device import pick_device
    from worldtree.scene import load_scene
    from worldtree.trainer import TrainContext

    device = pick_device(args.device)
    deterministic_for(device)  # timed as `wtbench run` trains
    spec = get_method("base")
    with tempfile.TemporaryDirectory() as tmp:
        root = _scene(args.scene, Path(tmp))
        print(f"scene {root}  device {device}  threads {torch.get_num_threads()}  first {args.steps} steps")
        rows = []
        for preset in args.presets.split(","):
            cfg = _capped(spec.config(preset), args.steps)
            scene = load_scene(root, downscale=cfg.downscale).to(device)
            if device.type == "cuda":
                torch.cuda.reset_peak_memory_stats(device)
            t0 = time.perf_counter()
            method = spec.build(cfg, scene, device)
            method.fit(TrainContext(checkpoint_dir=None, progress=False, resume=False))
            wall = time.perf_counter() - t0
            st = method.stats()
            stages = st["stages_s"]
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB -> MiB on Linux
            cuda = torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else float("nan")
            steps = {"ba": cfg.ba.steps, "sw": cfg.sw.steps, "scaffold": cfg.scaffold_fit.steps,
                     "photometric": cfg.steps}  # fmt: skip
            rows.append((preset, scene.width, scene.height, stages, steps, wall, rss, cuda, st))
        for preset, w, h, stages, steps, wall, rss, cuda, st in rows:
            print(
                f"\npreset {preset}: {w}x{h}, {st['num_static']} static + {st['num_dynamic']} dynamic Gaussians"
            )
            print(f"  {'stage':<12} {'seconds':>8} {'steps':>6} {'it/s':>8}")
            for name, sec in stages.items():
                n = steps.get(name)
                rate = f"{n / sec:8.1f}" if n and sec > 0 else f"{'':>8}"
                print(f"  {name:<12} {sec:8.2f} {n if n is not None else '':>6} {rate}")
            print(f"  total {wall:.1f} s; peak RSS (process so far) {rss:.0f} MiB; CUDA peak {cuda:.0f} MiB")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
