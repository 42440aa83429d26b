"""`wtbench`: evaluate, train and compare 4D reconstruction methods.

Each command lives in its own module under :mod:`benchmarks.commands` and registers itself here; heavy
imports (torch, the trainer) stay inside the command functions so that ``--help`` is instant.
"""

from __future__ import annotations

import importlib

import typer

from worldtree.cli_runner import run_cli

COMMAND_MODULES = (
    "eval",
    "weights",
    "prep",
    "run",
    "sweep",
    "table",
    "plot",
    "video",
    "report",
    "demo",
    "view",
    "export",
)

app = typer.Typer(
    name="wtbench",
    help="Benchmark 4D reconstruction from monocular video: score renders, run methods, export tables.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

for _name in COMMAND_MODULES:
    importlib.import_module(f"benchmarks.commands.{_name}").register(app)


def main() -> None:
    """Console-script entry point."""
    from worldtree import openmp_policy

    openmp_policy.configure()  # before torch is imported: OpenMP threads sleep on an oversubscribed machine
    run_cli(app)


if __name__ == "__main__":
    main()
