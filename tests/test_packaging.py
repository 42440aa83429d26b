"""What the installed distribution holds: the packages pyproject.toml's ``[tool.setuptools.packages.find]``
selects, found the way setuptools finds them. ``benchmarks.speed`` (measurement and proof scripts, run from a
clone as ``python -m benchmarks.speed.NAME``) is not among them."""

from __future__ import annotations

from pathlib import Path

import pytest

setuptools = pytest.importorskip("setuptools")
try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    tomllib = pytest.importorskip("tomli")

ROOT = Path(__file__).resolve().parents[1]


def _find() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]


def test_speed_scripts_are_not_distributed():
    find = _find()
    packages = setuptools.find_packages(str(ROOT), include=find["include"], exclude=find.get("exclude", ()))
    assert "benchmarks" in packages and "benchmarks.commands" in packages
    assert not [p for p in packages if p == "benchmarks.speed" or p.startswith("benchmarks.speed.")]


def test_speed_exclusion_is_not_vacuous():
    """The scripts are still a package of the clone (without the exclusion setuptools would ship them)."""
    assert "benchmarks.speed" in setuptools.find_packages(str(ROOT), include=_find()["include"])
