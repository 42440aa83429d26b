"""Fixtures of the baseline tests: a tiny analytic scene folder (see scene_fixture.py)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest


def load_scene_fixture_module():
    """Import tests/baselines/scene_fixture.py by path (tests run with --import-mode=importlib)."""
    path = Path(__file__).with_name("scene_fixture.py")
    spec = importlib.util.spec_from_file_location("wt_tests_scene_fixture", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """A 64x36, 6-frame scene folder in the docs/scene_format.md layout."""
    return load_scene_fixture_module().write_tiny_scene(tmp_path_factory.mktemp("scene") / "tiny")


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Tiny images train several times faster on one thread than on two busy shared cores."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
