"""`wtbench weights`: Show, install or download the LPIPS weight files."""

from __future__ import annotations

import typer

from worldtree.errors import UserError


def register(app: typer.Typer) -> None:
    @app.command("weights", help="Show, install or download the LPIPS weight files. (not yet available)")
    def _cmd() -> None:
        raise UserError("`wtbench weights` is not available yet in this version (tracked as issue 2)")
