"""Fixtures of the baseline tests: a tiny analytic scene folder (see scene_fixture.py)."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory, write_tiny_scene) -> Path:
    """A 64x36, 6-frame scene folder in the docs/scene_format.md layout."""
    return write_tiny_scene(tmp_path_factory.mktemp("scene") / "tiny")
