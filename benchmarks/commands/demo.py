"""`wtbench demo`: the README's main job, end to end on a scene the project generates itself.

generate a raw 12-camera capture -> `nvls build` -> `wtbench run` (each registered demo method, quick
preset) -> `wtbench table` (CSV of the test-view scores). Every stage is skipped when its output already exists, so
re-running the command resumes where it stopped. With ``--gt-priors`` the methods that use 2D priors get the
scene's exact masks, tracks and depth (`nvls gt-priors`) instead of the classical ones.
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
    ) -> None:
        run_demo(out, methods, steps, size, device, preset, gt_priors=gt_priors)


def run_demo(
    out: Path,
    methods: list[str],
    steps: int,
    size: str,
    device: str,
    preset: str = "quick",
    gt_priors: bool = False,
) -> Path:
    """Run the demo pipeline into ``out``; returns the path of the summary CSV.

    With ``gt_priors`` the exact priors are written to ``SCENE/gt_priors`` (once) and imported by every
    method whose config has 2D priors; the others run as usual.
    """
    from rich.console import Console

    from benchmarks.commands.table import export_tables
    from benchmarks.runner.runs import RunRequest, execute
    from nvidia_ls.build import BuildConfig, build_scene, parse_size
    from nvidia_ls.gt_priors import GtPriorsConfig, write_gt_priors
    from nvidia_ls.synth import SynthConfig, write_raw_scene
    from worldtree.errors import UserError

    console = Console()
    wh = parse_size(size)
    if wh is None:
        raise UserError(f"--size {size!r}: give WxH, e.g. 160x90")
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

    from worldtree.device import pick_device

    if pick_device(device).type == "cpu":
        from worldtree.render.cpu_kernel import prepare

        target, seconds = prepare()
        what = f"{target} build" if target else "unavailable, using the PyTorch reference"
        console.print(f"C++ rasterizer: {what} ({seconds:.0f} s; compiled once per machine, then cached)")
    for m in methods:
        given = priors if priors and _uses_priors(m, preset) else {}
        flags = "".join(f" --{k.replace('_', '-')} {v}" for k, v in given.items())
        if priors and not given:
            console.print(f"  {m} uses no 2D priors: --gt-priors does not apply to it")
        console.print(f"[bold]3/3[/] wtbench run --method {m} --scene {scene} --preset {preset}{flags}")
        execute(
            RunRequest(
                scene=scene,
                method=m,
                runs_dir=out / "runs",
                preset=preset,
                device=device,
                priors=given,
                command=f"wtbench demo --method {m} --preset {preset}" + (" --gt-priors" if given else ""),
            )
        )
    csv = out / "table.csv"
    console.print(f"wtbench table {out / 'runs'} -o {csv}")
    export_tables([out / "runs"], csv)
    return csv


def _uses_priors(method: str, preset: str) -> bool:
    """Whether ``method``'s config has 2D priors (imported priors are refused by the others)."""
    import dataclasses

    from methods.registry import get_method

    cfg = get_method(method).config(preset)
    return "priors" in {f.name for f in dataclasses.fields(cfg)}
