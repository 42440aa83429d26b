"""`wtbench sweep`: Run a grid of configurations (ablations, depths, chain lengths) over scenes."""

from __future__ import annotations

import typer

from worldtree.errors import UserError


def register(app: typer.Typer) -> None:
    @app.command(
        "sweep",
        help="Run a grid of configurations (ablations, depths, chain lengths) over scenes. (not yet available)",
    )
    def _cmd() -> None:
        raise UserError("`wtbench sweep` is not available yet in this version (tracked as issue 7)")
