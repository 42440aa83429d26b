"""`wtbench table`: export finished runs to a long CSV and a wide CSV, markdown or LaTeX table."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command(
        "table",
        help=(
            "Export finished runs: a wide table (one row per configuration, per-scene and mean columns per "
            "metric, best/second/third marked in markdown and LaTeX) to -o and the long table (one row per "
            "run and metric) beside it as <stem>_long.csv. Format: docs/tables.md."
        ),
    )
    def _cmd(
        runs_dirs: list[Path] = typer.Argument(..., help="Run roots (-o of `wtbench run`), one or more."),
        out: Path | None = typer.Option(
            None, "--out", "-o", help="Wide table to write; the long table goes beside it as <stem>_long.csv."
        ),
        group_by: str = typer.Option(
            "method,configuration",
            "--group-by",
            help="Row keys, comma-separated, from method, configuration, preset, tag, seed.",
        ),
        metrics: str | None = typer.Option(
            None, "--metrics", help="Metrics to show, comma-separated (default: every metric with a value)."
        ),
        fmt: str | None = typer.Option(
            None,
            "--format",
            help="csv, markdown or latex (default: from the suffix of -o; .md, .tex, else csv).",
        ),
        protocol: str | None = typer.Option(
            None, "--protocol", help="Evaluation protocol to show when the runs were scored under several."
        ),
        mean_only: bool = typer.Option(False, "--mean-only", help="Only the mean column of each metric."),
    ) -> None:
        export_tables(runs_dirs, out, group_by, metrics, fmt, protocol, mean_only)


def export_tables(
    runs_dirs: list[Path],
    out: Path | None,
    group_by: str = "method,configuration",
    metrics: str | None = None,
    fmt: str | None = None,
    protocol: str | None = None,
    mean_only: bool = False,
) -> None:
    """Collect finished runs, print the wide table, and write it to ``out`` with the long table beside it."""
    import sys

    from benchmarks.reporting.results import GROUP_KEYS, METRICS, collect_runs, select
    from benchmarks.reporting.tables import build_wide, format_for, parse_list, render
    from worldtree.infra.atomic import atomic_write_text
    from worldtree.infra.output_paths import check_output_file

    keys = parse_list(group_by, "--group-by", GROUP_KEYS)
    chosen = parse_list(metrics, "--metrics", METRICS)
    fmt = format_for(out, fmt)
    if out is not None:
        check_output_file(out, "-o")
        check_output_file(out.with_name(f"{out.stem}_long.csv"), "-o")
    found = collect_runs(runs_dirs)
    long = select(found.long, protocol)
    table = build_wide(long, keys, chosen, mean_only=mean_only)
    text = render(table, fmt)
    if out is not None:
        long_path = out.with_name(f"{out.stem}_long.csv")
        atomic_write_text(long_path, long.to_csv(index=False, na_rep="", float_format="%.10g"))
        atomic_write_text(out, text)
    for note in found.notes + table.notes:
        print(f"note: {note}", file=sys.stderr)
    print(text if fmt != "csv" else render(table, "markdown"), end="")
    if out is not None:
        print(f"wrote {out} and {long_path}", file=sys.stderr)
