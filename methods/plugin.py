"""What a method declares besides its config and presets: its own command-line options and its sweep grids.

A :class:`~methods.registry.MethodSpec` lists them (``options``, ``grids``); `wtbench run` and `wtbench sweep`
read them from the spec and know no method's vocabulary. An option is a top-level config field: its type parses
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
class Grid:
    """A named grid of a method: ``wtbench sweep --grid NAME``."""

    description: str
    """One line shown in ``wtbench sweep --help``."""
    points: Callable[[], list[GridPoint]]
    """The grid's configurations."""
