"""`wtbench plot`: speed against error for finished runs, one point per configuration, Pareto front marked."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command(
        "plot",
        help=(
            "Plot speed against error for finished runs: one point per configuration (mean over the scenes "
            "every configuration has), one panel per error metric, the Pareto front marked. Format: "
            "docs/tables.md."
        ),
    )
    def _cmd(
        runs_dirs: list[Path] = typer.Argument(..., help="Run roots (-o of `wtbench run`), one or more."),
        out: Path = typer.Option(
            Path("speed_vs_error.png"), "--out", "-o", help="Image to write (.png, .pdf or .svg)."
        ),
        x: str = typer.Option(
            "wall_time_s",
            "--x",
            help="Cost metrics on the x axis, comma-separated: one panel per (x, y) pair, e.g. wall_time_s,n_gaussians (cpu_time_s: CPU seconds, steadier than wall time on a busy machine).",
        ),
        y: str | None = typer.Option(
            None,
            "--y",
            help="Error metrics, comma-separated, one panel each (default: mavge,lpips, falling back to "
            "mmse,mse = 10^(-PSNR/10) when LPIPS is missing).",
        ),
        group_by: str = typer.Option(
            "method,configuration",
            "--group-by",
            help="Point keys, comma-separated, from method, configuration, preset, tag, seed.",
        ),
        protocol: str | None = typer.Option(
            None, "--protocol", help="Evaluation protocol to use when the runs were scored under several."
        ),
    ) -> None:
        import sys

        from benchmarks.reporting.plots import (
            AXIS_METRICS,
            DEFAULT_Y,
            draw,
            make_panel,
            resolve_y,
            with_derived,
        )
        from benchmarks.reporting.results import GROUP_KEYS, collect_runs, select
        from benchmarks.reporting.tables import parse_list
        from worldtree.infra.output_paths import check_output_file

        check_output_file(out, "-o")
        keys = parse_list(group_by, "--group-by", GROUP_KEYS)
        wanted = parse_list(y, "--y", AXIS_METRICS)
        xs = parse_list(x, "--x", AXIS_METRICS)
        found = collect_runs(runs_dirs)
        long = with_derived(select(found.long, protocol))
        notes = list(found.notes)
        panels = []
        for default in wanted or DEFAULT_Y:
            name, why = resolve_y(long, default if wanted else None, default)
            notes += why
            for xm in xs:
                if any(p.y == name and p.x == xm for p in panels):
                    continue  # two defaults fell back to the same metric
                panel = make_panel(long, xm, name, keys)
                notes += [n for n in panel.notes if n not in notes]
                panels.append(panel)
        draw(panels, out)
        for note in notes:
            print(f"note: {note}", file=sys.stderr)
        for p in panels:
            print(f"{p.x} vs {p.y} (mean over {', '.join(p.scenes)}):")
            for _, r in p.points.iterrows():
                star = "*" if r["pareto"] else " "
                print(f"  {star} {r['label']:50s} {r['x']:>10.4g} {r['y']:>10.4g}")
        print("(* on the Pareto front)")
        print(f"wrote {out}", file=sys.stderr)
