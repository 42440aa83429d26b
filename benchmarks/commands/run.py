"""`wtbench run`: Train a method on a scene, render the test camera and score it."""

from __future__ import annotations

import typer

from worldtree.errors import UserError


def register(app: typer.Typer) -> None:
    @app.command(
        "run", help="Train a method on a scene, render the test camera and score it. (not yet available)"
    )
    def _cmd() -> None:
        raise UserError("`wtbench run` is not available yet in this version (tracked as issue 4)")
