"""`wtbench run`: train a registered method on a scene, render the test camera and score it."""

from __future__ import annotations

import shlex
import sys
import warnings
from pathlib import Path

import typer

# Help of the imported-prior options, worded as `wtbench prep`'s options for the same files.
PRIOR_HELP = {
    "masks": "Folder of dynamic masks (one per frame) replacing EPI masks; sets priors.masks_source.",
    "tracks": "CoTracker .npy/.npz/.pt file of tracks to import; sets priors.tracks_source.",
    "depth_maps": "Depth file/folder to import (prep's --depth PATH); sets priors.depth_source.",
    "flow": "Folder of <i>_<j>.flo/.npy flow to import; sets priors.flow_source.",
}


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
        runs_dir: Path = typer.Option(Path("runs"), "--out", "-o", help="Root folder of the run folders."),
        preset: str = typer.Option("paper", "--preset", help="Config preset: quick (CPU minutes) or paper."),
        device: str = typer.Option("auto", "--device", help="auto, cpu, cuda or cuda:N."),
        steps: int | None = typer.Option(None, "--steps", help="Override the number of training steps."),
        seed: int | None = typer.Option(None, "--seed", help="Override the random seed."),
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
        set_: list[str] | None = typer.Option(
            None,
            "--set",
            metavar="KEY=VALUE",
            help="Change any config field, e.g. photometric.lambda_depth=0.1 or priors.epi.threshold_px=1.0 "
            "(dotted path, value parsed by the field's type); repeatable. See docs/running.md.",
        ),
        masks: Path | None = typer.Option(None, "--masks", help=PRIOR_HELP["masks"]),
        tracks: Path | None = typer.Option(None, "--tracks", help=PRIOR_HELP["tracks"]),
        depth_maps: Path | None = typer.Option(None, "--depth-maps", help=PRIOR_HELP["depth_maps"]),
        flow: Path | None = typer.Option(None, "--flow", help=PRIOR_HELP["flow"]),
        lpips_weights: Path | None = typer.Option(
            None, "--lpips-weights", help="Folder holding alexnet-owt-7be5be79.pth and alex.pth."
        ),
        tensorboard: bool = typer.Option(False, "--tensorboard", help="Log scalars for TensorBoard."),
        force: bool = typer.Option(False, "--force", help="Delete an existing run folder and start again."),
        tag: str | None = typer.Option(None, "--tag", help="Run-folder name instead of preset+overrides."),
        list_: bool = typer.Option(
            False, "--list", help="List the registered methods and presets, then exit."
        ),
    ) -> None:
        from benchmarks.runner.runs import RunRequest, execute, resolve_prior_paths
        from worldtree.errors import UserError

        if list_:
            _print_methods()
            return
        if method is None or scene is None:
            raise UserError(
                "`wtbench run` needs --method NAME and --scene FOLDER (see --list for the methods)"
            )
        overrides = {
            k: v for k, v in (("steps", steps), ("seed", seed), ("downscale", downscale)) if v is not None
        }
        options = _options(ablate, depth, chain_length, split, sequential)
        sets = list(set_ or [])
        priors = resolve_prior_paths(
            {"masks": masks, "tracks": tracks, "depth_maps": depth_maps, "flow": flow}
        )
        req = RunRequest(
            scene=scene,
            method=method,
            runs_dir=runs_dir,
            preset=preset,
            device=device,
            overrides=overrides,
            options=options,
            sets=sets,
            priors=priors,
            lpips_weights=lpips_weights,
            tensorboard=tensorboard,
            force=force,
            tag=tag,
            command=_command_line(
                method,
                scene,
                runs_dir,
                preset,
                device,
                overrides,
                lpips_weights,
                tensorboard,
                tag,
                options,
                sets=sets,
                priors=priors,
            ),
        )
        with warnings.catch_warnings():
            warnings.showwarning = _one_line_warning
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


def _command_line(
    method, scene, runs_dir, preset, device, overrides, lpips_weights, tensorboard, tag, options=None,
    sets=None, priors=None,
) -> str:  # fmt: skip
    """The command in canonical form (every resolved option), so that it can be pasted to repeat the run
    however it was invoked (shell, script, or in-process)."""
    from benchmarks.runner.runs import option_flag

    parts = ["wtbench", "run", "--method", method, "--scene", str(scene), "-o", str(runs_dir)]
    parts += ["--preset", preset, "--device", device]
    for k, v in overrides.items():
        parts += [f"--{k}", str(v)]
    for k, v in (options or {}).items():
        flag = option_flag(k)
        if k == "ablate":
            for a in v:
                parts += [flag, a]
        elif k == "sequential":
            parts.append(flag)
        else:
            parts += [flag, str(v)]
    for item in sets or ():
        parts += ["--set", item]
    for k, v in (priors or {}).items():
        parts += [option_flag(k), str(v)]
    if lpips_weights is not None:
        parts += ["--lpips-weights", str(lpips_weights)]
    if tensorboard:
        parts.append("--tensorboard")
    if tag is not None:
        parts += ["--tag", tag]
    return shlex.join(parts)


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Show warnings (e.g. missing LPIPS weights) as one ``warning:`` line, without source code."""
    print(f"warning: {message}", file=sys.stderr)


def _print_methods() -> None:
    from methods.registry import list_methods

    for spec in list_methods():
        print(f"{spec.name:12s} {spec.description}  (presets: {', '.join(sorted(spec.presets))})")
