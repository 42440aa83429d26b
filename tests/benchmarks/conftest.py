"""Fixtures shared by the `wtbench run` tests: a tiny scene and a cheap static quick preset."""

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
