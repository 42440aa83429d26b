"""Suite-wide settings: the suite runs as 2 pytest-xdist workers on 2 cores, so each uses one torch thread
(more threads per worker oversubscribe the cores and make small tensor ops many times slower)."""

from __future__ import annotations

import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Every test starts and ends on one thread: runs and trainers set torch's thread count from their config."""
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def deterministic_kernels_off():
    """Every test starts and ends with torch's deterministic kernels off (torch's default): a CPU run switches
    them on for its whole process (worldtree.infra.determinism), which would otherwise carry into later tests."""
    torch.use_deterministic_algorithms(False)
    yield
    torch.use_deterministic_algorithms(False)


@pytest.fixture(scope="session")
def write_tiny_scene():
    """``write_tiny_scene(root, width=64, height=36, frames=6, test_on_rig=False) -> Path`` from
    tests/methods/scene_fixture.py (imported by path: the suite runs with --import-mode=importlib, so test folders
    are not packages)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).parent / "methods" / "scene_fixture.py"
    spec = importlib.util.spec_from_file_location("wt_tests_scene_fixture", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.write_tiny_scene
