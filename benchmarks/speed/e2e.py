"""Where a whole run's time goes: one quick-preset run, per stage and, inside each stage, per kind of work.

    python -m benchmarks.speed.e2e SCENE [--method worldtree] [--preset quick] [--out DIR] [--set KEY=VALUE ...]

Runs ``wtbench run`` on SCENE (a folder written by ``nvls build``, e.g. ``demo/scenes/SynthBalloon`` after
``wtbench demo``) in a fresh folder with a deterministic profiler (cProfile) switched per method stage, then
prints, for each stage (priors, ba, sw, scaffold, photometric, tree, test_pose, ...): its wall time and the
inclusive time of the rasterizer's forward and backward, the projection, skinning (DQB), losses, motion
regularisers, the optimiser, densification, the rest of autograd's backward and the Python left over. The CPU
model, its SIMD flags, the load average, the Gaussian count and the pixels per training image are printed with
them. Tree nodes are trained in this process (``sequential``) so that the profiler sees them.

cProfile adds a few microseconds per Python call, so Python-heavy stages look slower than in a plain run (the
plain stage times of the same run's timing.json are printed beside them); compiled work (the C++ rasterizer,
torch operators) is timed as it is. Figures are printed, never asserted.
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import json
import pstats
import sys
import tempfile
import time
from pathlib import Path

# Kinds of work: name -> predicate on a profiled function (file, line, function name). The time of a kind is
# the inclusive time of its functions when called from outside the kind (no double counting within a kind).
KINDS: list[tuple[str, str, tuple[str, ...] | None]] = [
    ("raster fwd", "worldtree/render/cpu_kernel.py", ("_RasterizeCPU.forward",)),
    ("raster bwd", "worldtree/render/cpu_kernel.py", ("_RasterizeCPU.backward",)),
    ("project fwd", "worldtree/render/cpu_kernel.py", ("_ProjectCPU.forward",)),
    ("project bwd", "worldtree/render/cpu_kernel.py", ("_ProjectCPU.backward",)),
    ("reference raster", "worldtree/render/reference.py", None),
    # Gaussians at a time: scaffold node motion (SE(3)) and dual-quaternion blend skinning of the Gaussians.
    ("motion+DQB", "worldtree/dynamic.py", None),
    ("motion+DQB", "worldtree/motion/skinning.py", None),
    ("motion+DQB", "worldtree/motion/dualquat.py", None),
    ("motion+DQB", "worldtree/motion/scaffold.py", None),
    ("motion+DQB", "worldtree/motion/se3.py", None),
    ("motion+DQB", "worldtree/motion/quaternion.py", None),
    ("losses", "worldtree/losses.py", None),
    ("motion regs", "worldtree/motion/regularizers.py", None),
    ("optimiser", "worldtree/optim.py", None),
    ("densify", "worldtree/strategy.py", None),
    ("autograd other", "torch/autograd/__init__.py", ("backward",)),
    ("checkpoints", "worldtree/checkpoint.py", None),
]


def _qualnames() -> dict[tuple[str, int], str]:
    """(file, first line) -> qualified name, for the autograd Functions whose methods share a bare name."""
    import inspect

    from worldtree.render import cpu_kernel

    out = {}
    for cls in (cpu_kernel._RasterizeCPU, cpu_kernel._ProjectCPU):
        for meth in ("forward", "backward"):
            fn = getattr(cls, meth)
            out[(inspect.getsourcefile(fn), inspect.getsourcelines(fn)[1])] = f"{cls.__name__}.{meth}"
    return out


def _kind_of(key: tuple[str, int, str], qual: dict[tuple[str, int], str]) -> str | None:
    file, line, name = key
    file = file.replace("\\", "/")
    for kind, suffix, names in KINDS:
        if not file.endswith(suffix):
            continue
        if names is None:
            return kind
        full = qual.get((file, line), name)
        if full in names:
            return kind
    return None


def kind_times(stats: pstats.Stats, qual: dict[tuple[str, int], str]) -> dict[str, float]:
    """Inclusive seconds per kind, counting each kind's entries from callers of another kind only.

    "autograd other" is autograd's backward minus the kernels' own backward functions inside it.
    """
    out: dict[str, float] = {}
    kinds = {key: _kind_of(key, qual) for key in stats.stats}
    for key, (_cc, _nc, _tt, _ct, callers) in stats.stats.items():
        kind = kinds[key]
        if kind is None:
            continue
        if not callers:  # called from a frame that began before profiling: an entry point
            out[kind] = out.get(kind, 0.0) + _ct
        for caller, (_c, _n, _t, ct) in callers.items():
            if kinds.get(caller) != kind:
                out[kind] = out.get(kind, 0.0) + ct
    if "autograd other" in out:
        inner = sum(out.get(k, 0.0) for k in ("raster bwd", "project bwd"))
        out["autograd other"] = max(out["autograd other"] - inner, 0.0)
    return out


class StageProfiles:
    """One cProfile.Profile per method stage; the innermost running stage collects."""

    def __init__(self) -> None:
        self.profiles: dict[str, cProfile.Profile] = {}
        self.wall: dict[str, float] = {}
        self.stack: list[str] = []

    @contextlib.contextmanager
    def stage(self, name: str):
        if self.stack:
            self.profiles[self.stack[-1]].disable()
        prof = self.profiles.setdefault(name, cProfile.Profile())
        self.stack.append(name)
        t0 = time.perf_counter()
        prof.enable()
        try:
            yield
        finally:
            prof.disable()
            self.wall[name] = self.wall.get(name, 0.0) + time.perf_counter() - t0
            self.stack.pop()
            if self.stack:
                self.profiles[self.stack[-1]].enable()


def instrument(profiles: StageProfiles) -> None:
    """Switch profilers at the stage boundaries of the Base-family methods (their :meth:`stages` lists)."""
    from methods.base import BaseMethod
    from methods.stages import Stage

    stages = BaseMethod.stages

    def profiled(st: Stage) -> Stage:
        def run(state) -> None:
            with profiles.stage(st.name):
                st.run(state)

        return Stage(st.name, run)

    def _stages(self):
        return [profiled(st) for st in stages(self)]

    BaseMethod.stages = _stages


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path, help="scene folder written by `nvls build` (e.g. demo/scenes/SynthBalloon)")
    ap.add_argument("--method", default="worldtree")
    ap.add_argument("--preset", default="quick")
    ap.add_argument("--out", type=Path, help="runs folder (default: a temporary one, deleted afterwards)")
    ap.add_argument("--set", dest="sets", action="append", default=[], help="KEY=VALUE config assignment")
    ap.add_argument("--top", type=int, default=12, help="functions listed per stage by own time")
    a = ap.parse_args(argv)

    import torch

    from benchmarks.runner.runs import RunRequest, execute
    from benchmarks.speed.machine_info import describe
    from worldtree.render.cpu_kernel import prepare

    print(describe())
    target, build_s = prepare()
    print(f"C++ rasterizer: {target} build ({build_s:.1f} s to build/load, not counted below); "
          f"torch threads {torch.get_num_threads()}")  # fmt: skip
    profiles = StageProfiles()
    instrument(profiles)
    tmp = None
    runs_dir = a.out
    if runs_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="wt_e2e_")
        runs_dir = Path(tmp.name)
    options = {"sequential": True} if a.method == "worldtree" else {}
    t0 = time.perf_counter()
    with profiles.stage("other"):  # whatever runs outside the method's stages (loading, init, render, eval)
        res = execute(
            RunRequest(scene=a.scene, method=a.method, runs_dir=runs_dir, preset=a.preset, device="cpu",
                       options=options, sets=list(a.sets), force=True, progress=False,
                       command="python -m benchmarks.speed.e2e")  # fmt: skip
        )
    total = time.perf_counter() - t0
    timing = json.loads(res.folder.timing_json.read_text())
    stats = timing.get("method_stats", {})
    plain = stats.get("stages_s", {})
    from worldtree.scene import load_scene

    scene = load_scene(a.scene)
    t_frames, height, width = scene.images.shape[:3]
    pixels = f"{width}x{height} ({width * height} pixels), {t_frames} training frames"
    print(f"run: {res.folder.root} | {total:.1f} s wall with the profiler | Gaussians at the end: "
          f"{stats.get('num_gaussians')} | training image {pixels}")  # fmt: skip
    print(f"run stages (timing.json): {', '.join(f'{k} {v:.1f}s' for k, v in timing['stages_s'].items())}")
    cpu = stats.get("stages_cpu_s", {})
    if cpu:
        print(f"method stages, CPU s of this process (timing.json): {', '.join(f'{k} {v:.1f}' for k, v in cpu.items())}")
    qual = _qualnames()
    cols = list(dict.fromkeys(k for k, _, _ in KINDS))
    head = f"{'stage':>12} {'wall s':>7} {'plain s':>7} " + " ".join(f"{c[:10]:>10}" for c in cols) + f" {'python':>7}"
    print()
    print("seconds per stage and kind of work (inclusive, so kinds can nest: a regulariser's call into the motion")
    print("code counts in both; 'python' = own time of the stage's other Python functions, torch operators not")
    print("included; 'plain s' = the stage's time in timing.json, measured outside the profiler's switching):")
    print(head)
    print("-" * len(head))
    tops = {}
    for name, prof in profiles.profiles.items():
        st = pstats.Stats(prof)
        kt = kind_times(st, qual)
        py_own = sum(
            tt for key, (_cc, _nc, tt, _ct, _callers) in st.stats.items()
            if _kind_of(key, qual) is None and not key[0].startswith("~") and "/torch/" not in key[0]
        )  # fmt: skip
        row = f"{name:>12} {profiles.wall[name]:7.1f} {plain.get(name, float('nan')):7.1f} "
        row += " ".join(f"{kt.get(c, 0.0):10.2f}" for c in cols) + f" {py_own:7.2f}"
        print(row)
        tops[name] = st
    for name, st in tops.items():
        print(f"\n[{name}] top {a.top} functions by own time:")
        st.sort_stats("tottime")
        width = 0
        for key in st.fcn_list[: a.top]:
            cc, nc, tt, ct, _ = st.stats[key]
            file, line, fn = key
            where = f"{Path(file).name}:{line}({fn})" if file != "~" else fn
            width = max(width, len(where))
            print(f"  {tt:8.2f} s own {ct:8.2f} s incl {nc:8d} calls  {where}")
    if tmp is not None:
        tmp.cleanup()
    sys.stdout.flush()


if __name__ == "__main__":
    from worldtree.infra.errors import UserError

    try:
        main()
    except UserError as e:
        sys.exit(f"error: {e}")
