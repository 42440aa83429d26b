"""`nvls`: build, check and describe NVIDIA-LS scenes; generate synthetic raw rigs.

A thin layer over the library: :func:`nvidia_ls.build.build_scene`, :func:`nvidia_ls.synth.write_raw_scene`,
:func:`nvidia_ls.manifest.verify_scene`, :func:`nvidia_ls.info.describe_scene`,
:func:`nvidia_ls.gt_priors.write_gt_priors`.
"""

from __future__ import annotations

from pathlib import Path

import typer

from nvidia_ls.config_options import ConfigCommand, Shown, config_options
from worldtree.infra.cli_runner import INTERRUPTED_NO_CHECKPOINT, run_cli

app = typer.Typer(
    name="nvls",
    help="Build the NVIDIA-LS benchmark from raw multi-view captures of a static camera rig.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _console():
    from rich.console import Console

    return Console(stderr=True)


def _build_options():
    """``nvls build``'s options: every field of :class:`~nvidia_ls.build.BuildConfig`, with its default and help."""
    from nvidia_ls.build import BuildConfig, parse_size

    return BuildConfig, config_options(
        BuildConfig,
        {
            "size": Shown(
                type=str | None, parse=parse_size, help="Output size WxH (same aspect as the raw images)."
            )
        },
    )


def build(
    raw_dir: Path = typer.Argument(
        ..., help="Raw scene: mv_images/%05d/cam%02d.*, camNN/%05d.* or camNN.mp4."
    ),
    out_dir: Path = typer.Option(
        Path("scenes"), "-o", "--out-dir", help="Parent folder of the scene folder."
    ),
    cfg=None,  # the BuildConfig made from the generated options (ConfigCommand)
) -> None:
    from rich.progress import Progress

    from nvidia_ls.build import build_scene

    console = _console()

    def log(msg: str) -> None:
        console.print(f"[yellow]{msg}[/yellow]" if msg.startswith("warning") else msg, highlight=False)

    with Progress(console=console, transient=True) as prog:
        task = prog.add_task("cameras", total=None)

        def progress(stage: str, done: int, total: int) -> None:
            prog.update(task, description=stage, completed=done, total=total)

        path = build_scene(raw_dir, out_dir, cfg, log=log, progress=progress)
    console.print(f"wrote {path}", highlight=False)


# The options are generated from BuildConfig when the app runs (not at import: it would import torch before
# main() sets the OpenMP policy).
app.command("build", help="Turn one raw scene into an NVIDIA-LS scene folder OUT_DIR/<Scene>/.")(
    ConfigCommand(build, _build_options)
)


def _synth_options():
    """``nvls synth``'s options: every field of :class:`~nvidia_ls.synth.SynthConfig`, with its default and help."""
    from nvidia_ls.synth import SynthConfig

    return SynthConfig, config_options(SynthConfig)


def synth(
    out_dir: Path = typer.Argument(..., help="Scene folder to create."),
    force: bool = typer.Option(False, "--force", help="Replace an existing folder."),
    cfg=None,  # the SynthConfig made from the generated options (ConfigCommand)
) -> None:
    from nvidia_ls.synth import write_raw_scene
    from worldtree.infra.output_paths import check_output_folder

    check_output_folder(out_dir, "OUT_DIR")  # OUT_DIR under a file: one line before rendering
    console = _console()
    with console.status("rendering") as status:
        path = write_raw_scene(
            out_dir, cfg, force=force, progress=lambda d, n: status.update(f"rendering camera {d}/{n}")
        )
    console.print(f"wrote {path}", highlight=False)


# Options generated from SynthConfig like build's (one source of defaults and help).
app.command(
    "synth",
    help="Write a synthetic raw rig scene with ground-truth poses, masks (and depth) under OUT_DIR/gt.",
)(ConfigCommand(synth, _synth_options))


@app.command(
    "gt-priors",
    help="Write exact priors (dynamic masks, depth, point tracks) of a scene built from an `nvls synth` capture.",
)
def gt_priors(
    raw_dir: Path = typer.Argument(..., help="Raw capture written by `nvls synth` (holds gt/)."),
    scene_dir: Path = typer.Argument(..., help="Scene folder `nvls build` made from RAW_DIR."),
    out: Path | None = typer.Option(None, "--out", help="Output folder (default: SCENE_DIR/gt_priors)."),
    track_stride: int = typer.Option(8, help="Spacing in pixels of the grid of track query points."),
    seed_every: int = typer.Option(4, help="Seed query points in every K-th training frame."),
    force: bool = typer.Option(False, "--force", help="Replace an existing output folder."),
) -> None:
    from rich.progress import Progress

    from nvidia_ls.gt_priors import GtPriorsConfig, write_gt_priors
    from worldtree.infra.output_paths import check_output_folder

    if out is not None:
        check_output_folder(out, "--out")
    cfg = GtPriorsConfig(track_stride=track_stride, seed_every=seed_every, force=force)
    console = _console()
    with Progress(console=console, transient=True) as prog:
        task = prog.add_task("render", total=None)

        def progress(stage: str, done: int, total: int) -> None:
            prog.update(task, description=stage, completed=done, total=total)

        path = write_gt_priors(raw_dir, scene_dir, out, cfg, progress=progress)
    console.print(f"wrote {path}", highlight=False)


def _import_options():
    """``nvls import``'s options: every field of :class:`~nvidia_ls.importer.ImportConfig` (its nested
    ``video`` settings as ``--video-*``), with its default and help."""
    from nvidia_ls.build import parse_size
    from nvidia_ls.importer import ImportConfig

    return ImportConfig, config_options(
        ImportConfig,
        {
            "size": Shown(
                type=str | None, parse=parse_size,
                help="Output size WxH (same aspect as the images), e.g. 480x270; default: the images' size.",
            )
        },
    )  # fmt: skip


def import_(
    source: Path = typer.Argument(
        ...,
        help="A scene folder holding images/ and poses_bounds.npy (DynamicNeRF or NVIDIA-LS layout), or your "
        "own clip: a video file (.mp4, .mov, ...) or a folder of frames, whose cameras SfM estimates.",
    ),
    out_dir: Path = typer.Option(
        Path("scenes"), "-o", "--out-dir", help="Parent folder of the scene folder."
    ),
    cfg=None,  # the ImportConfig made from the generated options (ConfigCommand)
) -> None:
    from rich.progress import Progress

    from nvidia_ls.importer import OPTIONAL_WHY, import_scene, run_args

    console = _console()
    with Progress(console=console, transient=True) as prog:
        task = prog.add_task("import", total=None)

        def progress(stage: str, done: int, total: int) -> None:
            prog.update(task, description=stage, completed=done, total=total or None)

        path = import_scene(
            source, out_dir, cfg, progress=progress,
            log=lambda m: console.print(m, style="yellow", markup=False, soft_wrap=True),
        )  # fmt: skip
    console.print(f"wrote {path}", highlight=False, markup=False, soft_wrap=True)
    if cfg.no_poses:
        console.print(
            f"2D priors without poses: wtbench prep {path} --epi-from-flow --preview", highlight=False,
            soft_wrap=True,
        )  # fmt: skip
    args, optional = run_args(path), run_args(path, optional=True)
    if args or optional:
        import shlex

        run = ["wtbench", "run", "--scene", str(path), "--method", "base"]
        # One line whatever the terminal's width (soft_wrap: no line breaks inserted), so that the command
        # copied from a log runs as it is.
        if args:
            console.print(
                "run with its priors: " + shlex.join(run + args), highlight=False, markup=False, soft_wrap=True
            )
        if optional:
            console.print(
                f"not suggested, {OPTIONAL_WHY}: " + shlex.join(run + args + optional),
                highlight=False, markup=False, soft_wrap=True,
            )  # fmt: skip


# Options generated from ImportConfig like build's (one source of defaults and help).
app.command(
    "import",
    help="Turn a scene in the DynamicNeRF layout (images/, poses_bounds.npy, disp/, flow/, motion_masks/, "
    "v000_tXXX.png test views) or the NVIDIA-LS release layout into a scene folder OUT_DIR/<Scene>/, with its "
    "network priors under imported/ ready for `wtbench run`; or your own video / frames folder, cameras by "
    "pycolmap SfM, no test views (docs/nvidia_ls.md).",
)(ConfigCommand(import_, _import_options))


@app.command(help="Re-check a built scene against its manifest; exit 1 listing problems.")
def verify(
    scene: Path = typer.Argument(..., help="Scene folder written by `nvls build`."),
    no_hash: bool = typer.Option(False, "--no-hash", help="Skip the sha256 checks (faster)."),
) -> None:
    from nvidia_ls.manifest import verify_scene
    from worldtree.infra.errors import UserError

    if not scene.is_dir():
        raise UserError(f"{scene}: not a folder; give a scene folder written by `nvls build`")
    problems = verify_scene(scene, check_hashes=not no_hash)
    console = _console()
    if problems:
        console.print(f"[red]{scene}: {len(problems)} problem(s)[/red]", highlight=False)
        for p in problems:
            console.print(f"  - {p}", highlight=False, markup=False)
        # Not typer.Exit: with standalone_mode=False click returns its code instead of exiting.
        raise SystemExit(1)
    console.print(f"[green]{scene}: ok[/green]", highlight=False)


@app.command(help="Print a summary of a built scene.")
def info(scene: Path = typer.Argument(..., help="Scene folder written by `nvls build`.")) -> None:
    from rich.console import Console

    from nvidia_ls.info import describe_scene

    Console().print(describe_scene(scene))


def main() -> None:
    """Console-script entry point."""
    from worldtree.infra import openmp_policy, thread_governor

    openmp_policy.configure()  # before torch is imported: a short spin between OpenMP loops, then sleep
    thread_governor.enable()  # one torch thread while other processes use the cores
    # nvls keeps no checkpoints: every command writes its folder whole (atomic_dir) or removes it.
    run_cli(app, interrupted=INTERRUPTED_NO_CHECKPOINT)


if __name__ == "__main__":
    main()
