"""`wtbench report`: a static results site (tables, plots, per-scene pages, frame viewer) of a folder of runs."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command(
        "report",
        help=(
            "Write a static results site of the runs under RUNS_DIR: the sortable wide table with best/second/"
            "third marked, speed-vs-error plots with the Pareto front, per-scene pages with per-frame curves "
            "and a frame viewer (render | ground truth | mask | error). Opens from the file system; runs not "
            "finished are listed with their state. Format: docs/report.md."
        ),
    )
    def _cmd(
        runs_dirs: list[Path] = typer.Argument(
            ..., help="Run roots (-o of `wtbench run`/`sweep`), one or more."
        ),
        out: Path = typer.Option(
            Path("report"), "--out", "-o", help="Folder to write (replaced when it holds an earlier report)."
        ),
        group_by: str = typer.Option(
            "method,configuration",
            "--group-by",
            help="Row keys, comma-separated, from method, configuration, preset, tag, seed.",
        ),
        protocol: str | None = typer.Option(
            None, "--protocol", help="Only this evaluation protocol (default: a table per protocol found)."
        ),
        image_width: int = typer.Option(320, "--image-width", help="Width of the viewer's images, pixels."),
        viewer_frames: int = typer.Option(
            24, "--viewer-frames", help="Test frames in each scene's viewer, evenly spaced; 0 for all."
        ),
        title: str = typer.Option("worldtree-bench results", "--title", help="Title of the pages."),
    ) -> None:
        import sys

        from benchmarks.reporting.results import GROUP_KEYS
        from benchmarks.reporting.tables import parse_list
        from benchmarks.reporting.webreport.site import ReportOptions, build_report

        keys = parse_list(group_by, "--group-by", GROUP_KEYS)
        opts = ReportOptions(keys, protocol, image_width, viewer_frames, title)
        notes = build_report(runs_dirs, out, opts, log=lambda s: print(s, file=sys.stderr))
        for note in notes:
            print(f"note: {note}", file=sys.stderr)
        print(f"wrote {out / 'index.html'}")
