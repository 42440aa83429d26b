"""Speed of the photometric fit's optimiser step: torch's fused Adam against the single-tensor one.

    python -m benchmarks.speed.optimizer_step [--static 13500] [--dynamic 4200] [--other 1040] [--steps 300]
                                              [--rounds 2] [--threads 1,2]

Builds the fit's three :class:`worldtree.optim.GroupedAdam` (static and dynamic Gaussian sets with the five
3DGS groups each, and one set of other rows; sizes default to the demo scene's), gives every tensor a random
gradient and times ``--steps`` steps of all three per variant, the variants alternating for ``--rounds`` rounds
(the machine drifts; compare within a round). Prints milliseconds per step; figures are never asserted.
"""

from __future__ import annotations

import argparse
import time

import torch

from worldtree.optim import ConstantLR, GroupedAdam

_GROUPS = {"means": (3,), "quats": (4,), "log_scales": (3,), "opacity_logits": (), "sh0": (3,)}
"""A Gaussian set's parameter groups and the trailing shape of each (as the 3DGS model holds them)."""


def optimizers(sizes: list[int], fused: bool, seed: int = 0) -> list[GroupedAdam]:
    """One optimiser per set of ``n`` rows in ``sizes``, every tensor with a random gradient."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for n in sizes:
        ps = {k: torch.nn.Parameter(torch.randn(n, *tail, generator=g)) for k, tail in _GROUPS.items()}
        for p in ps.values():
            p.grad = torch.randn(p.shape, generator=g)
        out.append(GroupedAdam(ps, {k: ConstantLR(1e-3) for k in ps}, fused=fused))
    return out


def time_steps(opts: list[GroupedAdam], steps: int) -> float:
    """Milliseconds per step of every optimiser in ``opts`` (one warm-up step first)."""
    for o in opts:
        o.step()
    t0 = time.perf_counter()
    for _ in range(steps):
        for o in opts:
            o.step()
    return (time.perf_counter() - t0) / max(steps, 1) * 1e3


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--static", type=int, default=13_500, help="static Gaussians")
    ap.add_argument("--dynamic", type=int, default=4_200, help="dynamic Gaussians")
    ap.add_argument("--other", type=int, default=1_040, help="rows of the third optimiser")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--threads", default="1,2", help="comma-separated torch thread counts")
    args = ap.parse_args(argv)
    sizes = [args.static, args.dynamic, args.other]
    for threads in (int(t) for t in args.threads.split(",")):
        torch.set_num_threads(threads)
        for r in range(1, args.rounds + 1):
            ms = {
                name: time_steps(optimizers(sizes, fused), args.steps)
                for name, fused in (("single", False), ("fused", True))
            }
            print(f"threads {threads} round {r}: " + ", ".join(f"{k} {v:.3f} ms/step" for k, v in ms.items()))


if __name__ == "__main__":
    main()
