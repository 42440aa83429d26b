"""`wtbench demo`: Run the whole pipeline on a generated scene (the README's main job)."""

from __future__ import annotations

import typer

from worldtree.errors import UserError


def register(app: typer.Typer) -> None:
    @app.command(
        "demo",
        help="Run the whole pipeline on a generated scene (the README's main job). (not yet available)",
    )
    def _cmd() -> None:
        raise UserError("`wtbench demo` is not available yet in this version (tracked as issue 2)")
