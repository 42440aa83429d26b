"""`wtbench sweep`: run a named grid of configurations (ablations, depths, chain lengths) over scenes."""

from __future__ import annotations

from pathlib import Path

import typer

from benchmarks.commands.run import PRIOR_HELP


def register(app: typer.Typer) -> None:
    @app.command(
        "sweep",
        help=(
            "Run a grid of configurations (paper-ablation, depth, chain, split) over scenes; skips finished "
            "runs, goes on past a failed one and reports it."
        ),
    )
    def _cmd(
        scenes: list[Path] = typer.Option(
            ..., "--scenes", help="Scene folders, or folders of scene folders (repeatable)."
        ),
        grid: str = typer.Option("paper-ablation", "--grid", help="paper-ablation, depth, chain or split."),
        method: str = typer.Option("worldtree", "--method", "-m", help="Registered method to sweep."),
        runs_dir: Path = typer.Option(Path("runs"), "--out", "-o", help="Root folder of the run folders."),
        preset: str = typer.Option("paper", "--preset", help="Config preset: quick or paper."),
        device: str = typer.Option("auto", "--device", help="auto, cpu, cuda or cuda:N."),
        steps: int | None = typer.Option(None, "--steps", help="Override the root's training steps."),
        seed: int | None = typer.Option(None, "--seed", help="Override the random seed."),
        lpips_weights: Path | None = typer.Option(
            None, "--lpips-weights", help="Folder holding alexnet-owt-7be5be79.pth and alex.pth."
        ),
        set_: list[str] | None = typer.Option(
            None,
            "--set",
            metavar="KEY=VALUE",
            help="Change any config field in every run, e.g. photometric.lambda_depth=0.1; repeatable "
            "(as `wtbench run --set`).",
        ),
        masks: Path | None = typer.Option(None, "--masks", help=PRIOR_HELP["masks"]),
        tracks: Path | None = typer.Option(None, "--tracks", help=PRIOR_HELP["tracks"]),
        depth_maps: Path | None = typer.Option(None, "--depth-maps", help=PRIOR_HELP["depth_maps"]),
        flow: Path | None = typer.Option(None, "--flow", help=PRIOR_HELP["flow"]),
        dry_run: bool = typer.Option(False, "--dry-run", help="List the runs and exit."),
    ) -> None:
        from benchmarks.runner.runs import resolve_prior_paths

        priors = resolve_prior_paths(
            {"masks": masks, "tracks": tracks, "depth_maps": depth_maps, "flow": flow}
        )
        sweep(
            scenes, grid, method, runs_dir, preset, device, steps, seed, lpips_weights, dry_run,
            sets=list(set_ or []), priors=priors,
        )  # fmt: skip


def sweep(
    scenes,
    grid,
    method,
    runs_dir,
    preset,
    device,
    steps,
    seed,
    lpips_weights,
    dry_run,
    sets=None,
    priors=None,
) -> None:
    """Resolve scenes and grid, run them, print a summary and write RUNS_DIR/sweep-<grid>.json. ``sets``
    (``KEY=VALUE``) and ``priors`` (``benchmarks.runner.runs.PRIOR_OPTIONS`` name -> path) go to every run; they are
    checked against the method's config once, before the first run."""
    import warnings

    from benchmarks.commands.run import _command_line, _one_line_warning
    from benchmarks.runner.config_overrides import split_assignment
    from benchmarks.runner.runs import RunRequest, execute, resolve_config
    from benchmarks.runner.sweep import find_scenes, grid_points, run_sweep, write_report
    from methods.registry import get_method
    from worldtree.errors import UserError
    from worldtree.folder_lock import FolderLock
    from worldtree.output_paths import check_output_folder

    sets, priors = list(sets or []), dict(priors or {})
    found = find_scenes(scenes)
    points = grid_points(grid)
    overrides = {k: v for k, v in (("steps", steps), ("seed", seed)) if v is not None}
    grid_keys = {k for p in points for k in p.options}
    for item in sets:
        key = split_assignment(item)[0]
        if key in grid_keys:
            raise UserError(f"--set {item}: the {grid} grid sets {key} itself; drop the --set")
    if sets or priors:
        # A bad key or path would fail every run of the grid alike: refuse it once, up front.
        probe = RunRequest(
            scene=Path("."), method=method, preset=preset, overrides=overrides, sets=sets, priors=priors
        )
        resolve_config(get_method(method), probe)
    if dry_run:
        for s in found:
            for p in points:
                extra = f"  set {sets}" if sets else ""
                extra += f"  priors {priors}" if priors else ""
                print(f"{s.name}: {p.label}  {p.options}{extra}")
        return

    def make_request(scene: Path, pt) -> RunRequest:
        cmd = _command_line(
            method, scene, runs_dir, preset, device, overrides, lpips_weights, False, None, pt.options,
            sets=sets, priors=priors,
        )  # fmt: skip
        return RunRequest(
            scene=scene,
            method=method,
            runs_dir=runs_dir,
            preset=preset,
            device=device,
            overrides=overrides,
            options=dict(pt.options),
            sets=list(sets),
            priors=dict(priors),
            lpips_weights=lpips_weights,
            command=cmd,
        )

    check_output_folder(runs_dir, "-o")
    report = runs_dir / f"sweep-{grid}.json"
    # One sweep per report: a second `wtbench sweep` of the same grid into the same RUNS_DIR stops at once
    # (each run folder is locked by `wtbench run`'s execute as well).
    with FolderLock(report, "sweep report"), warnings.catch_warnings():
        warnings.showwarning = _one_line_warning
        outcomes = run_sweep(found, points, make_request, execute)
        write_report(
            report, grid, outcomes, _report_config(method, preset, device, overrides, sets, priors, found)
        )
    counts = {s: sum(o.status == s for o in outcomes) for s in ("done", "skipped", "failed")}
    print(
        f"sweep {grid}: {counts['done']} done, {counts['skipped']} already finished, {counts['failed']} failed"
    )
    for o in outcomes:
        if o.status == "failed":
            print(f"  failed: {o.scene} {o.label}: {o.error}")
    print(f"report: {report}; tables: wtbench table {runs_dir} -o table.csv")
    if counts["failed"]:
        raise typer.Exit(1)


def _report_config(method, preset, device, overrides, sets, priors, scenes) -> dict:
    """The sweep's settings as recorded in its report."""
    return {
        "method": method,
        "preset": preset,
        "device": device,
        "overrides": overrides,
        "sets": sets,
        "imported_priors": priors,
        "scenes": scenes,
    }
