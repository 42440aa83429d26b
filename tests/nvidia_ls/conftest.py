"""Shared fixtures of the nvls tests: small synthetic raw rigs and scenes built from them (session-scoped)."""

from __future__ import annotations

import numpy as np
import pytest

from nvidia_ls.build import BuildConfig, build_scene
from nvidia_ls.gt_priors import camera_centres, umeyama
from nvidia_ls.synth import SynthConfig, write_raw_scene

# The end-to-end rig: 12 cameras, enough time steps for a background model, small enough for CI.
E2E_SYNTH = SynthConfig(cameras=12, steps=24, width=256, height=144, seed=0)


@pytest.fixture(scope="session")
def synth_raw(tmp_path_factory):
    """The raw synthetic capture (multi-view layout) with its ground truth under gt/."""
    return write_raw_scene(tmp_path_factory.mktemp("raw") / "Synth", E2E_SYNTH)


@pytest.fixture(scope="session")
def built_gt(synth_raw, tmp_path_factory):
    """Scene built with the ground-truth poses (--poses), background-model masks."""
    out = tmp_path_factory.mktemp("built_gt")
    return build_scene(synth_raw, out, BuildConfig(poses=synth_raw / "gt" / "poses_bounds.npy", frames=20))


@pytest.fixture(scope="session")
def built_sfm(synth_raw, tmp_path_factory):
    """Scene built end to end: SfM poses, background-model masks, all time steps."""
    out = tmp_path_factory.mktemp("built_sfm")
    return build_scene(synth_raw, out, BuildConfig())


@pytest.fixture(scope="session")
def tiny_raw(tmp_path_factory):
    """A 4-camera, 6-step, 64x36 capture for layout and bad-input tests (copy it before changing it)."""
    return write_raw_scene(
        tmp_path_factory.mktemp("tiny") / "Tiny",
        SynthConfig(cameras=4, steps=6, width=64, height=36, supersample=1),
    )


def pose_errors(w2c_est: np.ndarray, w2c_gt: np.ndarray, look_depth: float) -> tuple[float, float]:
    """Max rotation error (deg) and max centre error relative to the rig's extent, after a Sim(3) alignment.

    A rig's centres are nearly coplanar, so the alignment also uses one point per camera ``look_depth`` (GT
    units) along its optical axis; that pins down the rotation about the rig plane.
    """
    c_e, c_g = camera_centres(w2c_est), camera_centres(w2c_gt)
    s0, _, _ = umeyama(c_e, c_g)
    z_e, z_g = w2c_est[:, 2, :3], w2c_gt[:, 2, :3]  # optical axes in world coordinates (third rows)
    src = np.concatenate([c_e, c_e + look_depth / s0 * z_e])
    dst = np.concatenate([c_g, c_g + look_depth * z_g])
    s, R, t = umeyama(src, dst)
    aligned = (s * (R @ c_e.T)).T + t
    extent = max(np.linalg.norm(p - q) for p in c_g for q in c_g)
    trans = float(np.linalg.norm(aligned - c_g, axis=1).max() / extent)
    rot = 0.0
    for we, wg in zip(w2c_est, w2c_gt, strict=True):
        Rrel = wg[:3, :3].T @ (we[:3, :3] @ R.T)
        rot = max(rot, float(np.degrees(np.arccos(np.clip((np.trace(Rrel) - 1) / 2, -1, 1)))))
    return rot, trans
