"""DQB skinning speed: forward + backward ms per call of ``deform_dual_planes``, compiled kernel vs tensor version.

    python -m benchmarks.speed.skinning [--sizes 20000x8,100000x8,300000x8] [--threads 2] [--iters 5]

A size is ``GAUSSIANSxNEIGHBOURS``: random Gaussians with K neighbours each, already gathered into the
component-major planes ``Scaffold.deform`` passes (positions [3, N, K], radii [N, K], dual quaternions [4, N, K]),
with a validity mask and a weight correction, as a photometric step of the scaffold methods deforms its Gaussians
to one frame (the graph rows have K = 16 there). One call = the deformation and the backward of a linear loss
of its outputs into every input. Both versions run in the same process, alternately, and the best of ``--iters``
calls is printed (the machine is shared: a slower call is another job's doing); figures are printed, never
asserted. ``--cpu-time`` reports process CPU time instead of wall time (with one thread: robust to other load).
"""

from __future__ import annotations

import argparse
import time

from benchmarks.speed.arap import parse_size_pairs


def _inputs(n: int, k: int, seed: int = 0):
    """Float32 inputs of deform_dual_planes for n Gaussians and k neighbours (leaves requiring grad) and the mask."""
    import torch

    from worldtree.motion import dualquat

    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(n, 3, generator=g)
    quats = torch.randn(n, 4, generator=g)
    nb_pos = pts.t()[:, :, None] + 0.5 * torch.randn(3, n, k, generator=g)
    sigma = 0.3 + torch.rand(n, k, generator=g)
    real, dual = dualquat.from_quat_trans(
        torch.randn(n, k, 4, generator=g), 0.1 * torch.randn(n, k, 3, generator=g)
    )
    valid = torch.rand(n, k, generator=g) > 0.2
    corr = 0.1 * torch.randn(n, k, generator=g)
    leaves = [pts, quats, nb_pos, sigma, real.permute(2, 0, 1), dual.permute(2, 0, 1), corr]
    return [x.contiguous().requires_grad_(True) for x in leaves], valid


def main(argv: list[str] | None = None) -> None:
    import torch

    from worldtree.motion import skinning
    from worldtree.render import cpu_kernel

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="20000x8,100000x8,300000x8")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--iters", type=int, default=5)
    ap.add_argument("--cpu-time", action="store_true", help="process CPU time instead of wall time")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    if cpu_kernel.ops() is None:
        raise SystemExit(f"the compiled kernel does not build here: {cpu_kernel.build_error()}")
    clock = time.process_time if args.cpu_time else time.perf_counter
    print(f"threads {args.threads}, kernel target {cpu_kernel.loaded_target()}, {'CPU' if args.cpu_time else 'wall'} time")
    print("| Gaussians | K | tensor version ms | compiled ms | ratio |")
    print("| --: | --: | --: | --: | --: |")
    versions = {"tensor": skinning._deform_dual_planes_tensor, "compiled": skinning.deform_dual_planes}
    for n, k in parse_size_pairs(args.sizes):
        leaves, valid = _inputs(n, k)
        g = torch.Generator().manual_seed(1)
        wp, wq = torch.randn(n, 3, generator=g), torch.randn(n, 4, generator=g)

        def call(fn, leaves=leaves, valid=valid, wp=wp, wq=wq):
            p_t, q_t = fn(*leaves[:6], valid, leaves[6])
            torch.autograd.grad((p_t * wp).sum() + (q_t * wq).sum(), leaves)

        best = dict.fromkeys(versions, float("inf"))
        for fn in versions.values():
            call(fn)  # warm-up
        for _ in range(args.iters):
            for name, fn in versions.items():
                t0 = clock()
                call(fn)
                best[name] = min(best[name], (clock() - t0) * 1000)
        ratio = best["tensor"] / max(best["compiled"], 1e-9)
        print(f"| {n} | {k} | {best['tensor']:.1f} | {best['compiled']:.1f} | {ratio:.1f}x |")


if __name__ == "__main__":
    main()
