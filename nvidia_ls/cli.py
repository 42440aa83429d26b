"""`nvls`: build, check and describe NVIDIA-LS scenes; generate synthetic raw rigs."""

from __future__ import annotations

import typer

from worldtree.errors import UserError, run_cli

app = typer.Typer(
    name="nvls",
    help="Build the NVIDIA-LS benchmark from raw multi-view captures of a static camera rig.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _todo(name: str) -> None:
    raise UserError(f"`nvls {name}` is not available yet in this version (tracked as issue 3)")


@app.command(help="Turn one raw scene into an NVIDIA-LS scene folder.")
def build() -> None:
    _todo("build")


@app.command(help="Write a synthetic raw 12-camera scene with ground-truth poses and masks.")
def synth() -> None:
    _todo("synth")


@app.command(help="Re-check a built scene against its manifest; exit non-zero listing problems.")
def verify() -> None:
    _todo("verify")


@app.command(help="Print a summary of a built scene.")
def info() -> None:
    _todo("info")


def main() -> None:
    """Console-script entry point."""
    run_cli(app)


if __name__ == "__main__":
    main()
