"""Photometric step speed of the Base method with the compiled motion kernels and with their tensor versions.

    python -m benchmarks.speed.photometric_step [--scene SCENE] [--steps 60] [--measure 40] [--rounds 3]

Trains Base (quick preset, CPU) on the scene for ``--steps`` photometric steps (without --scene the demo's
320x180 x 40-step capture is generated, as ``benchmarks.speed.base`` does), then times ``--measure`` further
steps (forward and backward of the step's loss; no optimiser step, so every variant sees the same model) with
each way of computing the scaffold's node motions and smoothness terms, the variants alternating for
``--rounds`` rounds (the machine drifts; compare within a round):

- ``tensor``: :func:`worldtree.motion.skinning._relative_dual_tensor` and the tensor velocity and acceleration
  terms (the code before the two kernels);
- ``relative``: the compiled node-motion table (:func:`worldtree.motion.skinning.relative_dual`) only;
- ``compiled``: both compiled kernels (the default).

Prints the median wall and process CPU milliseconds per step of each round; figures are never asserted.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
import time
from pathlib import Path


def _variants():
    from worldtree.motion import regularizers, skinning

    tensor_smooth = regularizers._smoothness_tensor
    compiled_rel, compiled_smooth = skinning._relative_ops, regularizers.smoothness_losses
    off = lambda *args: None  # noqa: E731 - "no compiled ops": the tensor version
    return {
        "tensor": (off, tensor_smooth),
        "relative": (compiled_rel, tensor_smooth),
        "compiled": (compiled_rel, compiled_smooth),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", help="scene folder (default: generate the demo's capture)")
    ap.add_argument("--steps", type=int, default=60, help="photometric steps trained before timing")
    ap.add_argument("--measure", type=int, default=40, help="steps timed per variant and round")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args(argv)

    import torch

    from benchmarks.speed.base import _scene
    from methods.registry import get_method
    from worldtree.infra.determinism import deterministic_for
    from worldtree.motion import regularizers, skinning
    from worldtree.scene import load_scene
    from worldtree.trainer import TrainContext

    device = torch.device("cpu")
    deterministic_for(device)  # timed as `wtbench run` trains
    spec = get_method("base")
    cfg = spec.config("quick")
    tp = dataclasses.replace(cfg.test_pose, first_steps=2, next_steps=1)
    cfg = dataclasses.replace(cfg, steps=args.steps, test_pose=tp, checkpoint_every=10**9)
    variants = _variants()
    with tempfile.TemporaryDirectory() as tmp:
        scene = load_scene(_scene(args.scene, Path(tmp)), downscale=cfg.downscale).to(device)
        method = spec.build(cfg, scene, device)
        method.fit(TrainContext(checkpoint_dir=None, progress=False, resume=False))
    fit = method.state.fit
    H, W = fit.images.shape[1:3]
    print(
        f"{W}x{H}, {fit.T} frames, {len(fit.static)} static + {len(fit.dynamic)} dynamic Gaussians, "
        f"{fit.scaffold.M} scaffold nodes, {torch.get_num_threads()} threads; ms per step (median of {args.measure})"
    )
    saved = skinning._relative_ops, regularizers.smoothness_losses
    step = 10**6
    rows: dict[str, list[tuple[float, float]]] = {k: [] for k in variants}
    try:
        for _ in range(args.rounds):
            for name, (rel_ops, smooth) in variants.items():
                skinning._relative_ops, regularizers.smoothness_losses = rel_ops, smooth
                wall, cpu = [], []
                for _ in range(args.measure):
                    step += 1
                    t0, c0 = time.perf_counter(), time.process_time()
                    out = fit.training_step(step)
                    out.loss.backward()
                    wall.append(time.perf_counter() - t0)
                    cpu.append(time.process_time() - c0)
                    for opt in (fit.static_opt, fit.dyn_opt, fit.other_opt):
                        opt.zero_grad()
                rows[name].append((statistics.median(wall), statistics.median(cpu)))
    finally:
        skinning._relative_ops, regularizers.smoothness_losses = saved
    for name, vals in rows.items():
        walls = " ".join(f"{1000 * w:7.1f}" for w, _ in vals)
        cpus = " ".join(f"{1000 * c:7.1f}" for _, c in vals)
        print(f"  {name:<9} wall {walls}   cpu {cpus}")


if __name__ == "__main__":
    main()
