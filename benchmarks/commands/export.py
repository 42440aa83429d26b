"""`wtbench export`: a finished run's Gaussians at chosen times as 3DGS PLY files or one npz, with an index."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command(
        "export",
        help=(
            "Export a finished run's Gaussians at chosen times: standard 3DGS PLY files (one per time, opened by "
            "splat viewers and editors) or one npz of the raw time-dependent model, with index.json (time -> "
            "file, method, config digest, tool version). Format: docs/python_api.md."
        ),
    )
    def _cmd(
        run_dir: Path = typer.Argument(..., help="A run folder written by `wtbench run`."),
        out: Path = typer.Option(
            ..., "--out", "-o", help="Output folder (created; nothing is written outside)."
        ),
        fmt: str = typer.Option(
            "ply", "--format", help="ply (one file per time) or npz (raw model + frames)."
        ),
        times: str = typer.Option("all", "--times", help="Time indices, comma-separated (0,5,10), or all."),
        device: str = typer.Option("auto", "--device", help="auto (CUDA when present), cpu, cuda or cuda:N."),
    ) -> None:
        from benchmarks.reporting.export import export_folder

        index = export_folder(run_dir, out, fmt.strip().lower(), times, device)
        files = sorted({e["file"] for e in index["times"].values()})
        print(f"wrote {out}: {len(index['times'])} time(s) in {len(files)} {fmt} file(s), index.json")
