"""Fixtures shared by the `wtbench run` tests: a tiny scene, a cheap static quick preset, finished tiny runs, and
the hand-made run folders' writer."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from methods.registry import get_method


@pytest.fixture(scope="module")
def scene(tmp_path_factory, write_tiny_scene) -> Path:
    return write_tiny_scene(tmp_path_factory.mktemp("s") / "tiny")


@pytest.fixture
def small_quick(monkeypatch):
    """The static quick preset with few points and a checkpoint every 2 steps (the registry entry, patched)."""
    spec = get_method("static")
    quick = spec.presets["quick"]
    monkeypatch.setitem(
        spec.presets, "quick", lambda: dataclasses.replace(quick(), init_num_points=200, checkpoint_every=2)
    )


def _helper(name: str):
    """The module ``tests/benchmarks/<name>.py`` (the suite runs in importlib mode: helpers load by path)."""
    import importlib.util

    path = Path(__file__).with_name(f"{name}.py")
    spec = importlib.util.spec_from_file_location(f"wt_tests_{name}", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="session")
def api_runs(tmp_path_factory, write_tiny_scene) -> dict[str, Path]:
    """Finished tiny static, Base and WorldTree runs (tests/benchmarks/api_runs.py), made once per session."""
    return _helper("api_runs").make_runs(tmp_path_factory.mktemp("api_runs"), write_tiny_scene)


@pytest.fixture(scope="session")
def runs_fixture():
    """``tests/benchmarks/runs_fixture.py``: ``write_run`` writes a finished run folder in the real format."""
    return _helper("runs_fixture")
