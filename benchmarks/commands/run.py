"""`wtbench run`: train a registered method on a scene, render the test camera and score it."""

from __future__ import annotations

import warnings
from pathlib import Path

import typer

from benchmarks.commands import run_options as opt
from benchmarks.commands.run_options import RunOptions, one_line_warning


def register(app: typer.Typer) -> None:
    @app.command(
        "run",
        help=(
            "Train a method on a scene, render the test camera at every test time and score it. Writes "
            "RUNS_DIR/<scene>/<method>/<preset[-overrides]>/; re-running resumes or skips a finished run."
        ),
    )
    def _cmd(
        method: str | None = typer.Option(
            None, "--method", "-m", help="Registered method name, e.g. static."
        ),
        scene: Path | None = typer.Option(
            None, "--scene", "-s", help="Scene folder written by `nvls build`."
        ),
        runs_dir: Path = opt.OUT,
        preset: str = opt.PRESET,
        device: str = opt.DEVICE,
        steps: int | None = opt.STEPS,
        seed: int | None = opt.SEED,
        downscale: int | None = typer.Option(None, "--downscale", help="Override the training image shrink."),
        ablate: list[str] | None = typer.Option(
            None, "--ablate", help="worldtree: ablate a component (ba, sw, tpt, sac); repeat for several."
        ),
        depth: str | None = typer.Option(
            None,
            "--depth",
            help="worldtree: deepest tree layer (default 2), or 'auto' (docs/worldtree_method.md).",
        ),
        chain_length: int | None = typer.Option(
            None, "--chain-length", help="worldtree: ancestors rendered at test time (default: all)."
        ),
        split: str | None = typer.Option(
            None, "--split", help="worldtree: split strategy binary (default), gradient or flow."
        ),
        sequential: bool = typer.Option(
            False, "--sequential", help="worldtree: train each layer's nodes one after another."
        ),
        set_: list[str] | None = opt.SET,
        masks: Path | None = opt.MASKS,
        tracks: Path | None = opt.TRACKS,
        depth_maps: Path | None = opt.DEPTH_MAPS,
        flow: Path | None = opt.FLOW,
        lpips_weights: Path | None = opt.LPIPS_WEIGHTS,
        tensorboard: bool = typer.Option(False, "--tensorboard", help="Log scalars for TensorBoard."),
        force: bool = typer.Option(False, "--force", help="Delete an existing run folder and start again."),
        tag: str | None = typer.Option(None, "--tag", help="Run-folder name instead of preset+overrides."),
        list_: bool = typer.Option(
            False, "--list", help="List the registered methods and presets, then exit."
        ),
    ) -> None:
        from benchmarks.runner.runs import execute
        from worldtree.errors import UserError

        if list_:
            _print_methods()
            return
        if method is None or scene is None:
            raise UserError(
                "`wtbench run` needs --method NAME and --scene FOLDER (see --list for the methods)"
            )
        run = RunOptions.from_cli(
            method, masks, tracks, depth_maps, flow, steps, seed, downscale, set_, runs_dir=runs_dir,
            preset=preset, device=device, lpips_weights=lpips_weights, tensorboard=tensorboard, tag=tag,
        )  # fmt: skip
        req = run.request(scene, _options(ablate, depth, chain_length, split, sequential), force=force)
        with warnings.catch_warnings():
            warnings.showwarning = one_line_warning
            result = execute(req)
        if not result.skipped:
            scores = "  ".join(f"{k} {v:.4f}" for k, v in result.mean.items())
            print(f"done: {result.folder.root}  {scores}")


def _options(ablate, depth, chain_length, split, sequential) -> dict:
    """The method options given (``benchmarks.runner.runs.METHOD_OPTIONS``); ablations sorted and deduplicated."""
    opts: dict = {}
    if ablate:
        opts["ablate"] = sorted({a.strip().lower() for a in ablate})
    if depth is not None and depth.strip().isdigit():
        depth = int(depth)  # an integer depth stays an integer in config.json and the folder name
    for k, v in (("depth", depth), ("chain_length", chain_length), ("split", split)):
        if v is not None:
            opts[k] = v
    if sequential:
        opts["sequential"] = True
    return opts


def _print_methods() -> None:
    from methods.registry import list_methods

    for spec in list_methods():
        print(f"{spec.name:12s} {spec.description}  (presets: {', '.join(sorted(spec.presets))})")
