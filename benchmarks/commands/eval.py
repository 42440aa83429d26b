"""`wtbench eval`: Score rendered frames against ground truth under a named protocol; write CSV + JSON."""

from __future__ import annotations

from pathlib import Path

import typer

PROTOCOL_HELP = (
    "worldtree (default): the authors' NVIDIA protocol, quirks included; "
    "dycheck: DyCheck / Shape of Motion masked metrics. Formulas: docs/evaluation.md"
)


def _fmt(v) -> str:
    import math

    v = float(v)
    if math.isnan(v):
        return ""
    return "inf" if math.isinf(v) else f"{v:.4f}"


def register(app: typer.Typer) -> None:
    @app.command(
        "eval", help="Score rendered frames against ground truth under a named protocol; write CSV + JSON."
    )
    def eval_cmd(
        pred_dir: Path = typer.Argument(
            ..., help="Folder of predicted frames (PNG/JPG), paired to --gt by file stem."
        ),
        gt: Path = typer.Option(..., "--gt", help="Folder of ground-truth frames."),
        masks: Path | None = typer.Option(
            None, "--masks", help="Folder of masks (white = scored), one per frame; fills the masked columns."
        ),
        protocol: str = typer.Option("worldtree", "--protocol", help=PROTOCOL_HELP),
        out: Path | None = typer.Option(
            None,
            "--out",
            help="CSV to write (default: metrics.csv beside PRED_DIR); the JSON record goes beside it.",
        ),
        lpips_weights: Path | None = typer.Option(
            None,
            "--lpips-weights",
            help="Folder with alexnet-owt-7be5be79.pth and alex.pth (else $WTBENCH_LPIPS_WEIGHTS, then the user "
            "cache; see `wtbench weights show`).",
        ),
        device: str = typer.Option("auto", "--device", help="auto, cpu, cuda or cuda:N."),
    ) -> None:
        import warnings

        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
        from rich.table import Table

        from benchmarks.evaluation.evaluate import (
            COLUMNS,
            EvalWarning,
            evaluate_folder,
            pair_files,
            write_result,
        )
        from benchmarks.evaluation.metrics import get_protocol

        get_protocol(protocol)  # fail on a bad name before reading anything
        out_csv = out if out is not None else pred_dir.resolve().parent / "metrics.csv"
        if out_csv.suffix.lower() != ".csv":
            from worldtree.infra.errors import UserError

            raise UserError(f"--out {out_csv}: the table is written as CSV; give a file name ending in .csv")
        from worldtree.infra.output_paths import check_output_file

        # Before the scoring, not after it: the CSV and its JSON record beside it must be writable.
        check_output_file(out_csv, "--out")
        check_output_file(out_csv.with_suffix(".json"), "--out")
        err = Console(stderr=True)
        n = len(pair_files(pred_dir, gt, masks))
        with (
            warnings.catch_warnings(record=True) as caught,
            Progress(
                TextColumn("scoring"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeElapsedColumn(),
                console=err,
                transient=True,
            ) as bar,
        ):
            warnings.simplefilter("always", EvalWarning)
            task = bar.add_task("eval", total=n)
            res = evaluate_folder(
                pred_dir,
                gt,
                masks,
                protocol=protocol,
                lpips_weights=lpips_weights,
                device=device,
                progress=lambda k: bar.advance(task, k),
            )
        for w in caught:
            if issubclass(w.category, EvalWarning):
                err.print(f"[yellow]warning:[/yellow] {w.message}", highlight=False, soft_wrap=True)
            else:
                warnings.showwarning(w.message, w.category, w.filename, w.lineno)
        csv_path, json_path = write_result(res, out_csv)
        table = Table(title=f"{protocol} protocol, mean of {n} frames")
        for c in COLUMNS:
            table.add_column(c, justify="right")
        row = res.mean
        table.add_row(str(row["frame"]), *(_fmt(row[c]) for c in COLUMNS[1:]))
        Console().print(table)
        print(f"wrote {csv_path} and {json_path}")
