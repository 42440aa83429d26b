"""What a method declares besides its config and presets: its own command-line options, its sweep grids, and
the first stages another run may lend it.

A :class:`~methods.registry.MethodSpec` lists them (``options``, ``grids``, ``shared_root``); `wtbench run` and
`wtbench sweep` read them from the spec and know no method's vocabulary. An option is a top-level config field: its type parses
the value (as ``--set`` does) and the string literal under the field is its help. A grid is a named list of
:class:`GridPoint` (the options and common overrides of each run).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class MethodOption:
    """A config field offered as an option of its own: ``chain_length`` -> ``--chain-length``."""

    field: str
    """Top-level config field; its annotation parses the value, the string literal under it is the help. A
    ``bool`` field is a flag that turns it on."""
    tag: str
    """Part of the run-folder name: ``-<tag><value>`` (a flag: ``-<tag>`` when given)."""


@dataclass(frozen=True)
class GridPoint:
    """One configuration of a grid: a label, the method options it sets (``RunRequest.options``, ablations as
    ``{"ablate": [...]}``) and the common fields it overrides (``RunRequest.overrides``: steps, seed, downscale)."""

    label: str
    options: dict[str, Any] = field(default_factory=dict)
    overrides: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class SharedRoot:
    """The first stages of a method that another run may lend it (``wtbench run --root-from RUN``), instead of
    training them again: their checkpoints, linked into the new run, make it resume after them.

    Sound only where nothing those stages read may differ between the two runs: the configs must agree on
    every field they both have except ``free_fields`` (read only by later stages), and on the ablations in
    ``root_ablations``; CPU runs are deterministic (``worldtree.infra.determinism``), so the run is the one it
    would have trained itself."""

    checkpoints: tuple[str, ...]
    """Names under the run's ``checkpoints/`` folder (files or folders) that hold those stages."""
    stages: tuple[str, ...]
    """The method's stage names (its stage ledger) whose time the lent checkpoints stand for."""
    methods: tuple[str, ...]
    """Methods whose runs may lend them (their first stages are these, with the same checkpoints)."""
    free_fields: tuple[str, ...] = ()
    """Top-level config fields the lending run may set otherwise (read only after these stages)."""
    root_ablations: tuple[str, ...] = ()
    """Ablations that change these stages (the two runs must agree on them; others may differ)."""
    ledger: str = ""
    """The method's stage ledger under ``checkpoints/`` (JSON with ``stages_s`` and ``stages_cpu_s``), where
    the lending run's seconds for ``stages`` are read; empty: none kept."""


@dataclass(frozen=True)
class Grid:
    """A named grid of a method: ``wtbench sweep --grid NAME``."""

    description: str
    """One line shown in ``wtbench sweep --help``."""
    points: Callable[[], list[GridPoint]]
    """The grid's configurations."""
