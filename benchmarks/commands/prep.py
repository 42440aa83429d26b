"""`wtbench prep`: Compute and cache 2D priors (flow, tracks, depth, dynamic masks) for a scene."""

from __future__ import annotations

import typer

from worldtree.errors import UserError


def register(app: typer.Typer) -> None:
    @app.command(
        "prep",
        help="Compute and cache 2D priors (flow, tracks, depth, dynamic masks) for a scene. (not yet available)",
    )
    def _cmd() -> None:
        raise UserError("`wtbench prep` is not available yet in this version (tracked as issue 5)")
