"""`wtbench sweep`: run a named grid of configurations (ablations, depths, chain lengths) over scenes."""

from __future__ import annotations

from pathlib import Path

import typer


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
        dry_run: bool = typer.Option(False, "--dry-run", help="List the runs and exit."),
    ) -> None:
        sweep(scenes, grid, method, runs_dir, preset, device, steps, seed, lpips_weights, dry_run)


def sweep(scenes, grid, method, runs_dir, preset, device, steps, seed, lpips_weights, dry_run) -> None:
    """Resolve scenes and grid, run them, print a summary and write RUNS_DIR/sweep-<grid>.json."""
    import warnings

    from benchmarks.commands.run import _command_line, _one_line_warning
    from benchmarks.runs import RunRequest, execute
    from benchmarks.sweep import find_scenes, grid_points, run_sweep, write_report

    found = find_scenes(scenes)
    points = grid_points(grid)
    if dry_run:
        for s in found:
            for p in points:
                print(f"{s.name}: {p.label}  {p.options}")
        return
    overrides = {k: v for k, v in (("steps", steps), ("seed", seed)) if v is not None}

    def make_request(scene: Path, pt) -> RunRequest:
        cmd = _command_line(
            method, scene, runs_dir, preset, device, overrides, lpips_weights, False, None, pt.options
        )
        return RunRequest(
            scene=scene,
            method=method,
            runs_dir=runs_dir,
            preset=preset,
            device=device,
            overrides=overrides,
            options=dict(pt.options),
            lpips_weights=lpips_weights,
            command=cmd,
        )

    with warnings.catch_warnings():
        warnings.showwarning = _one_line_warning
        outcomes = run_sweep(found, points, make_request, execute)
    report = runs_dir / f"sweep-{grid}.json"
    cfg = {"method": method, "preset": preset, "device": device, "overrides": overrides, "scenes": found}
    write_report(report, grid, outcomes, cfg)
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
