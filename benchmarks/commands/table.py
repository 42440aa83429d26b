"""`wtbench table`: Export finished runs to long/wide CSV, markdown or LaTeX tables."""

from __future__ import annotations

import typer

from worldtree.errors import UserError


def register(app: typer.Typer) -> None:
    @app.command(
        "table", help="Export finished runs to long/wide CSV, markdown or LaTeX tables. (not yet available)"
    )
    def _cmd() -> None:
        raise UserError("`wtbench table` is not available yet in this version (tracked as issue 7)")
