"""Small closed-form scenes shared by the priors tests (built once per session: they are deterministic)."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.fixtures.planar_scene import PlanarScene, PlanarSceneConfig


@pytest.fixture(scope="session")
def planar():
    """A moving textured square over a textured wall and floor: 8 frames at 160x96, exact ground truth."""
    sc = PlanarScene(PlanarSceneConfig(width=160, height=96, num_frames=8))
    return sc, sc.frames()


@pytest.fixture(scope="session")
def planar_static():
    """The same set with the square at rest: nothing moves, only the rig cameras change."""
    sc = PlanarScene(PlanarSceneConfig(width=160, height=96, num_frames=6, object_step=0.0, object_spin=0.0))
    return sc, sc.frames()


@pytest.fixture(scope="session")
def planar_u8(planar):
    sc, fr = planar
    return np.round(fr["rgb"] * 255).astype(np.uint8)
