"""`wtbench demo`: the README's main job, end to end on a scene the project generates itself.

generate a raw 12-camera capture -> `nvls build` -> `wtbench run` (each registered demo method, quick
preset) -> `wtbench table` (CSV of the test-view scores). Every stage is skipped when its output already exists, so
re-running the command resumes where it stopped. With ``--gt-priors`` the methods that use 2D priors get the
scene's exact masks, tracks and depth (`nvls gt-priors`) instead of the classical ones.

Methods that grow a tree (WorldTree) run with ``--depth auto`` by default: a node is split only where its frames
need it (docs/worldtree_method.md, "Modelling only what a scene needs"); ``--depth 2`` gives the paper's fixed
tree. After each such run the demo prints the depth the tree reached, its leaves and why each node was split.
"""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command("demo", help="Run the whole pipeline on a generated scene (the README's main job).")
    def _cmd(
        out: Path = typer.Option(
            Path("demo"), "--out", "-o", help="Folder for the raw scene, scene and runs."
        ),
        methods: list[str] = typer.Option(
            ["worldtree"], "--method", "-m", help="Methods to run (repeatable); see `wtbench run --list`."
        ),
        steps: int = typer.Option(40, "--steps", help="Time steps of the generated capture."),
        size: str = typer.Option("320x180", "--size", help="Image size WxH of the generated capture."),
        device: str = typer.Option("auto", "--device", help="auto, cpu, cuda or cuda:N."),
        preset: str = typer.Option("quick", "--preset", help="Method preset (quick: minutes on a CPU)."),
        gt_priors: bool = typer.Option(
            False,
            "--gt-priors",
            help="Give methods the scene's exact masks, tracks and depth (`nvls gt-priors`; stand-in for "
            "network priors) instead of classical priors.",
        ),
        depth: str = typer.Option(
            "auto",
            "--depth",
            help="Tree depth of the methods that grow one (WorldTree): auto (split a node only where its "
            "frames need it) or a fixed depth, e.g. 2 (the paper's).",
        ),
    ) -> None:
        from worldtree.infra.output_paths import check_output_folder

        check_output_folder(out, "-o")
        run_demo(out, methods, steps, size, device, preset, gt_priors=gt_priors, depth=depth)


def run_demo(
    out: Path,
    methods: list[str],
    steps: int,
    size: str,
    device: str,
    preset: str = "quick",
    gt_priors: bool = False,
    depth: str = "auto",
) -> Path:
    """Run the demo pipeline into ``out``; returns the path of the summary CSV.

    With ``gt_priors`` the exact priors are written to ``SCENE/gt_priors`` (once) and imported by every
    method whose config has 2D priors; the others run as usual. ``depth`` (``"auto"`` or an integer as text)
    is given to every method that declares the option ``depth`` (``--depth`` of `wtbench run`); the others run
    without it.
    """
    from rich.console import Console

    from benchmarks.commands.table import export_tables
    from benchmarks.runner.runs import RunRequest, execute
    from nvidia_ls.build import BuildConfig, build_scene, parse_size
    from nvidia_ls.gt_priors import GtPriorsConfig, write_gt_priors
    from nvidia_ls.synth import SynthConfig, write_raw_scene
    from worldtree.infra.errors import UserError

    console = Console()
    wh = parse_size(size)
    if wh is None:
        raise UserError(f"--size {size!r}: give WxH, e.g. 160x90")
    from worldtree.infra.device import pick_device

    kernel = _KernelBuild() if pick_device(device).type == "cpu" else None
    name = "SynthBalloon"
    raw = out / "raw" / name
    if not (raw / "gt" / "cameras.json").is_file():
        console.print(f"[bold]1/3[/] generating raw capture: 12 cameras x {steps} steps at {size} -> {raw}")
        write_raw_scene(
            raw, SynthConfig(steps=steps, width=wh[0], height=wh[1], motion="slow_fast"), force=True
        )
    else:
        console.print(f"[bold]1/3[/] raw capture exists: {raw}")

    scene = out / "scenes" / name
    if not (scene / "manifest.json").is_file():
        console.print(f"[bold]2/3[/] nvls build {raw} -> {scene}")
        build_scene(raw, out / "scenes", BuildConfig(force=True), log=lambda s: console.print(f"  {s}"))
    else:
        console.print(f"[bold]2/3[/] scene exists: {scene}")

    priors: dict[str, str] = {}
    if gt_priors:
        gt_dir = scene / "gt_priors"
        if not (gt_dir / "gt_priors.json").is_file():
            console.print(f"[bold]2b[/] nvls gt-priors {raw} {scene}")
            write_gt_priors(raw, scene, gt_dir, GtPriorsConfig(force=True))
        else:
            console.print(f"[bold]2b[/] exact priors exist: {gt_dir}")
        priors = {"masks": str(gt_dir / "masks"), "tracks": str(gt_dir / "tracks.npz"),
                  "depth_maps": str(gt_dir / "depth")}  # fmt: skip

    if kernel is not None:
        target, seconds = kernel.result()
        what = f"{target} build" if target else "unavailable, using the PyTorch reference"
        console.print(f"C++ rasterizer: {what} ({seconds:.0f} s; compiled once per machine, then cached)")
    for m in methods:
        given = priors if priors and _uses_priors(m, preset) else {}
        flags = "".join(f" --{k.replace('_', '-')} {v}" for k, v in given.items())
        if priors and not given:
            console.print(f"  {m} uses no 2D priors: --gt-priors does not apply to it")
        options = {"depth": depth} if _declares_option(m, "depth") else {}
        flags += f" --depth {depth}" if options else ""
        console.print(f"[bold]3/3[/] wtbench run --method {m} --scene {scene} --preset {preset}{flags}")
        result = execute(
            RunRequest(
                scene=scene,
                method=m,
                runs_dir=out / "runs",
                preset=preset,
                device=device,
                priors=given,
                options=options,
                command=f"wtbench demo --method {m} --preset {preset}"
                + (" --gt-priors" if given else "")
                + (f" --depth {depth}" if options else ""),
            )
        )
        if options:
            console.print(f"  {m}: {tree_summary(result.folder.timing_json)}", highlight=False)
    csv = out / "table.csv"
    console.print(f"wtbench table {out / 'runs'} -o {csv}")
    export_tables([out / "runs"], csv)
    return csv


class _KernelBuild:
    """The CPU rasterizer's build (or cached load) in a background thread, started before the capture and the
    scene build: the compiler runs as a subprocess without the GIL, so its first build (about half a minute)
    overlaps them instead of coming before the training. A daemon thread: Ctrl-C does not wait for it (the
    build lock dies with the process, and a half-finished build is redone by the next run)."""

    def __init__(self) -> None:
        import threading

        self._out: tuple[str | None, float] | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="kernel-build", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from worldtree.render.cpu_kernel import prepare

        try:
            self._out = prepare()
        except BaseException as e:  # handed to the main thread by result()
            self._error = e

    def result(self) -> tuple[str | None, float]:
        """``cpu_kernel.prepare()``'s (target, seconds), once the build is done; re-raises its error."""
        self._thread.join()
        if self._error is not None:
            raise self._error
        assert self._out is not None
        return self._out


def _uses_priors(method: str, preset: str) -> bool:
    """Whether ``method``'s config has 2D priors (imported priors are refused by the others)."""
    return _config_has(method, preset, "priors")


def _declares_option(method: str, name: str) -> bool:
    """Whether ``method``'s spec declares the option ``name`` (``MethodSpec.options``)."""
    from methods.registry import get_method

    return any(o.field == name for o in get_method(method).options)


def _config_has(method: str, preset: str, name: str) -> bool:
    """Whether ``method``'s config (``preset``) has a field ``name``."""
    import dataclasses

    from methods.registry import get_method

    cfg = get_method(method).config(preset)
    return name in {f.name for f in dataclasses.fields(cfg)}


def tree_summary(timing_json: Path) -> str:
    """One line on the tree a run grew, from its ``timing.json``: the depth reached (its deepest node), the node
    count, which frames each rendering node renders (the leaves' intervals; with a one-sided split the parent
    renders the half of the child left out) and, under ``--depth auto``, why each node was or was not split
    and why a child was not trained (``method_stats.tree.auto``)."""
    import json

    from worldtree.tree.tpt import depth_of

    tree = json.loads(timing_json.read_text()).get("method_stats", {}).get("tree") or {}
    nodes = sorted(int(j) for j in tree.get("nodes") or [1])
    intervals = tree.get("intervals") or {}
    renders = tree.get("renders")
    line = f"tree depth {max(depth_of(j) for j in nodes)}, {len(nodes)} node{'s' if len(nodes) > 1 else ''}"
    if len(nodes) > 1 and renders:
        line += ", frames rendered by " + ", ".join(
            f"node {j}: " + " and ".join(f"{a}-{b}" for a, b in runs)
            for j, runs in sorted(renders.items(), key=lambda kv: int(kv[0]))
        )
    elif len(nodes) > 1 and intervals:  # a record without "renders" (before one-sided splits): the leaves
        leaves = [j for j in nodes if 2 * j not in nodes and 2 * j + 1 not in nodes]
        line += ", leaves over frames " + ", ".join("-".join(map(str, intervals[str(j)])) for j in leaves)
    auto = tree.get("auto") or {}
    if not auto:
        return line
    why = []
    for j, d in sorted(auto.items(), key=lambda kv: int(kv[0])):
        why.append(f"node {j}: {'split' if d.get('applied', d.get('split')) else 'leaf'} ({d.get('reason')})")
        for c, cd in sorted((d.get("children") or {}).items(), key=lambda kv: int(kv[0])):
            if not cd.get("train", True):
                why.append(f"node {c}: {cd.get('reason')}")
    return f"--depth auto chose {line} ({'; '.join(why)})"
