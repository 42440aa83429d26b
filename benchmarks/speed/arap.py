"""ARAP regulariser speed: forward + backward ms per call, compiled kernel vs the tensor version.

    python -m benchmarks.speed.arap [--sizes 12x511,40x514,12x2358,160x3208] [--threads 2] [--iters 5]

A size is ``FRAMESxNODES``: a scaffold built (``build_scaffold``) from random-walk trajectories of that many
tracks, so its three ARAP graphs (the base KNN graph and the two coarser levels) have the shapes a run's have.
One call = the ARAP terms of all three graphs and the backward of their sum, as a photometric step spends on them
(12 frames: the quick preset's motion window; 160: a whole NVIDIA-LS video, as the paper preset's window of all
frames). Figures are printed, never asserted; both versions run in the same process, so their ratio compares
across machines when the wall times do not.
"""

from __future__ import annotations

import argparse
import time


def parse_size_pairs(text: str) -> list[tuple[int, int]]:
    """``"AxB,CxD"`` -> ``[(A, B), (C, D)]`` (the kernel speed scripts' ``--sizes``)."""
    out = []
    for item in text.split(","):
        t, m = item.lower().split("x")
        out.append((int(t), int(m)))
    return out


def main(argv: list[str] | None = None) -> None:
    import torch

    from worldtree.motion import regularizers
    from worldtree.motion.regularizers import arap_loss
    from worldtree.motion.scaffold import build_scaffold
    from worldtree.render import cpu_kernel

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="12x511,40x514,12x2358,160x3208")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--iters", type=int, default=5)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    if cpu_kernel.ops() is None:
        raise SystemExit(f"the compiled kernel does not build here: {cpu_kernel.build_error()}")
    print(f"threads {args.threads}, kernel target {cpu_kernel.loaded_target()}")
    print("| frames | nodes | tensor version ms | compiled ms | ratio |")
    print("| --: | --: | --: | --: | --: |")
    for T, M in parse_size_pairs(args.sizes):
        g = torch.Generator().manual_seed(0)
        traj = torch.cumsum(torch.randn(T, M, 3, generator=g) * 0.01, 0) + torch.rand(1, M, 3, generator=g) * 2
        scf = build_scaffold(traj, torch.ones(T, M, dtype=torch.bool), 3.0)
        pos = scf.pos.detach().clone().requires_grad_(True)
        quat = scf.quat.detach().clone().requires_grad_(True)
        graphs = scf.arap_graphs()

        def call(pos=pos, quat=quat, graphs=graphs):
            total = pos.sum() * 0.0
            for graph in graphs:
                coord, length = arap_loss(pos, quat, graph)
                total = total + coord + length
            total.backward()

        times = {}
        for name, compiled in (("tensor", False), ("compiled", True)):
            original = regularizers._compiled_ops
            if not compiled:
                regularizers._compiled_ops = lambda *tensors: None
            try:
                call()  # warm-up
                n = args.iters if T * scf.M < 200_000 else max(1, args.iters // 2)
                t0 = time.perf_counter()
                for _ in range(n):
                    call()
                times[name] = (time.perf_counter() - t0) / n * 1000
            finally:
                regularizers._compiled_ops = original
        ratio = times["tensor"] / max(times["compiled"], 1e-9)
        print(f"| {T} | {scf.M} | {times['tensor']:.1f} | {times['compiled']:.1f} | {ratio:.1f}x |")


if __name__ == "__main__":
    main()
