"""Rasterizer speed: forward + backward ms/iteration and peak RSS, compiled CPU kernel vs PyTorch reference.

    python -m benchmarks.speed.render [--gaussians 20000] [--threads 1,2] [--iters 10] [--sizes 320x180,480x270]
                                      [--targets native,avx2,portable]

Each (backend, build target, size, threads) runs in its own subprocess so that its peak RSS
(resource.getrusage) is its own. One iteration = rasterize() (projection + compositing) and backward of a
weighted sum of rgb, alpha and depth, i.e. what a training step spends in the renderer (no optimiser). Figures
are printed, never asserted. Wall times on a shared machine depend on its load, so the script prints ratios
measured in the same run, which compare across machines: compiled vs reference, native vs avx2 and portable
builds, and 1 vs N threads (on an AVX-512 CPU the avx2 build stands in for an AVX2-only CPU's native build);
the CPU model, its SIMD instruction sets and the load average are printed with them, and the CPU time per
iteration (process_time, all threads) beside the wall time.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time


def make_scene(n: int, width: int, height: int, seed: int = 0):
    """A trained-scene-like cloud: N Gaussians in a box 2..6 units ahead, a few pixels wide each."""
    import torch

    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g) * torch.tensor([4.0, 2.4, 4.0]) - torch.tensor([2.0, 1.2, -2.0])
    quats = torch.randn(n, 4, generator=g)
    log_scales = torch.log(0.01 + 0.05 * torch.rand(n, 3, generator=g))
    opacities = 0.1 + 0.8 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    f = 0.8 * width
    K = torch.tensor([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    w2c = torch.eye(4)
    params = [means, quats, log_scales, opacities, colors, w2c]
    for p in params:
        p.requires_grad_(True)
    return params, K


def run_one(backend: str, n: int, width: int, height: int, threads: int, iters: int) -> dict:
    import torch

    from worldtree.render import cpu_kernel, rasterize

    torch.set_num_threads(threads)
    (means, quats, log_scales, opacities, colors, w2c), K = make_scene(n, width, height)
    g = torch.Generator().manual_seed(1)
    w_rgb = torch.rand(height, width, 3, generator=g)
    w_a = torch.rand(height, width, generator=g)

    def step():
        out = rasterize(means, quats, log_scales, opacities, colors, K, w2c, width, height, backend=backend)
        loss = (out.rgb * w_rgb).sum() + (out.alpha * w_a).sum() + 0.01 * out.depth.sum()
        loss.backward()
        return out

    out = step()  # warm-up (and, for the compiled backend, loading the cached build)
    step()
    times, cpu = [], []
    for _ in range(iters):
        t0, c0 = time.perf_counter(), time.process_time()
        step()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    times.sort()
    cpu.sort()
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # kilobytes on Linux
    return {
        "backend": out.backend,
        "target": cpu_kernel.loaded_target() if out.backend == "cpu" else "-",
        "ms_median": 1000 * times[len(times) // 2],
        "ms_min": 1000 * times[0],
        "cpu_ms_median": 1000 * cpu[len(cpu) // 2],
        "visible": int(out.visible.sum()),
        "coverage": float(out.alpha.detach().mean()),
        "peak_rss_mb": peak_kb / 1024,
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=20000, help="number of Gaussians")
    ap.add_argument("--threads", default="1,2", help="torch / OpenMP thread counts, comma-separated (e.g. 1,2)")
    ap.add_argument("--iters", type=int, default=10, help="timed iterations per compiled run")
    ap.add_argument("--reference-iters", type=int, default=3, help="timed iterations per reference run")
    ap.add_argument("--sizes", default="320x180,480x270", help="comma-separated WIDTHxHEIGHT list")
    ap.add_argument(
        "--targets",
        help="C++ build targets to time, comma-separated (default: those this CPU runs of native, avx2, portable)",
    )
    ap.add_argument("--no-reference", action="store_true", help="skip the PyTorch reference")
    ap.add_argument(
        "--omp-wait-policy",
        choices=["active", "passive"],
        help="set OMP_WAIT_POLICY in the measured processes (passive helps on an oversubscribed machine)",
    )
    ap.add_argument("--one", help=argparse.SUPPRESS)  # internal: run a single configuration, print JSON
    a = ap.parse_args(argv)
    if a.one:
        backend, size = a.one.split(":")
        w, h = (int(v) for v in size.split("x"))
        iters = a.iters if backend != "reference" else a.reference_iters
        print(json.dumps(run_one(backend, a.gaussians, w, h, int(a.threads), iters)))
        return

    from benchmarks.speed.machine_info import describe

    print(f"rasterizer forward+backward, {a.gaussians} Gaussians (median ms/iteration)")
    print(describe())
    policy = a.omp_wait_policy or os.environ.get("OMP_WAIT_POLICY", "default")
    print(f"OMP_WAIT_POLICY: {policy}")
    if a.targets is None:
        from worldtree.render.kernel_build import auto_order

        a.targets = ",".join(auto_order())
    variants = [("cpu", t.strip()) for t in a.targets.split(",") if t.strip()]
    if not a.no_reference:
        variants.append(("reference", "-"))
    header = (
        f"{'threads':>7} {'size':>9} {'backend':>10} {'target':>9} {'ms/iter':>9} {'min ms':>8} {'CPU ms':>8} "
        f"{'visible':>8} {'cover':>6} {'peak RSS MB':>12}"
    )
    print(header)
    print("-" * len(header))
    res: dict[tuple[str, str, str], dict] = {}  # (threads, size, variant) -> result
    for threads in a.threads.split(","):
        for size in a.sizes.split(","):
            for backend, target in variants:
                cmd = [sys.executable, "-m", "benchmarks.speed.render", "--one", f"{backend}:{size}"]
                cmd += ["--gaussians", str(a.gaussians), "--threads", threads, "--iters", str(a.iters)]
                cmd += ["--reference-iters", str(a.reference_iters)]
                env = dict(os.environ)
                if backend == "cpu":
                    env["WORLDTREE_RASTER_TARGET"] = target
                if a.omp_wait_policy:
                    env["OMP_WAIT_POLICY"] = a.omp_wait_policy.upper()
                proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
                label = target if backend == "cpu" else "-"
                if proc.returncode != 0:
                    print(
                        f"{threads:>7} {size:>9} {backend:>10} {label:>9} failed: "
                        f"{proc.stderr.strip().splitlines()[-1:]}"
                    )
                    continue
                r = json.loads(proc.stdout.strip().splitlines()[-1])
                if backend == "cpu" and r["backend"] != "cpu":
                    print(f"{threads:>7} {size:>9} {backend:>10} {label:>9} fell back to {r['backend']}")
                    continue
                res[(threads, size, f"{backend}:{label}")] = r
                print(
                    f"{threads:>7} {size:>9} {r['backend']:>10} {r['target']:>9} {r['ms_median']:9.1f} "
                    f"{r['ms_min']:8.1f} {r['cpu_ms_median']:8.1f} {r['visible']:8d} {r['coverage']:6.2f} "
                    f"{r['peak_rss_mb']:12.0f}"
                )
    print()
    print("ratios measured in this run (medians; > 1 means the first is faster; on a loaded machine the")
    print("CPU-time ratio is the steadier one, except across thread counts where only wall time shows the gain):")

    def ratio(slow: dict | None, fast: dict | None) -> str:
        if slow is None or fast is None:
            return "n/a"
        wall = slow["ms_median"] / max(fast["ms_median"], 1e-9)
        cpu = slow["cpu_ms_median"] / max(fast["cpu_ms_median"], 1e-9)
        return f"{wall:.2f}x wall, {cpu:.2f}x CPU time"

    thread_list = a.threads.split(",")
    for threads in thread_list:
        for size in a.sizes.split(","):
            ref = res.get((threads, size, "reference:-"))
            for _, target in (v for v in variants if v[0] == "cpu"):
                cpu = res.get((threads, size, f"cpu:{target}"))
                print(f"  {threads} threads {size}: {target} kernel vs reference {ratio(ref, cpu)}")
            nat = res.get((threads, size, "cpu:native"))
            for other in ("avx2", "portable"):
                built = res.get((threads, size, f"cpu:{other}"))
                if nat and built:
                    print(f"  {threads} threads {size}: native vs {other} build {ratio(built, nat)}")
    if len(thread_list) > 1:
        lo, hi = thread_list[0], thread_list[-1]
        for size in a.sizes.split(","):
            for backend, target in variants:
                key = f"{backend}:{target if backend == 'cpu' else '-'}"
                r1, rn = res.get((lo, size, key)), res.get((hi, size, key))
                print(f"  {size} {key}: {hi} threads vs {lo} {ratio(r1, rn)}")
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print("ms/iter and min ms are wall clock; CPU ms is process CPU time (all threads) per iteration.")


if __name__ == "__main__":
    main()
