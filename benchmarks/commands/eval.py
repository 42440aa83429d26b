"""`wtbench eval`: Score rendered frames against ground truth under a named protocol; write CSV + JSON."""

from __future__ import annotations

import typer

from worldtree.errors import UserError


def register(app: typer.Typer) -> None:
    @app.command(
        "eval",
        help="Score rendered frames against ground truth under a named protocol; write CSV + JSON. (not yet available)",
    )
    def _cmd() -> None:
        raise UserError("`wtbench eval` is not available yet in this version (tracked as issue 2)")
