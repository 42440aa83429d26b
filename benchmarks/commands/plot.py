"""`wtbench plot`: Plot speed against error for finished runs, Pareto front marked."""

from __future__ import annotations

import typer

from worldtree.errors import UserError


def register(app: typer.Typer) -> None:
    @app.command(
        "plot", help="Plot speed against error for finished runs, Pareto front marked. (not yet available)"
    )
    def _cmd() -> None:
        raise UserError("`wtbench plot` is not available yet in this version (tracked as issue 7)")
