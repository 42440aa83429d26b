"""Static baseline: interrupted + resumed training (with densification between checkpoints) gives bit-identical
Gaussians and Adam state to an uninterrupted run of the same seed, on the CPU."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from methods.static3dgs import StaticConfig, StaticGaussians, load_points
from worldtree.checkpoint import list_checkpoints, seed_everything
from worldtree.infra.errors import UserError
from worldtree.scene import load_scene
from worldtree.strategy import DensifyStrategy
from worldtree.trainer import TrainContext


def _cfg() -> StaticConfig:
    return StaticConfig(
        steps=24,
        init_num_points=150,
        strategy=DensifyStrategy(
            refine_start=4, refine_stop=20, refine_every=4, reset_every=12, grow_grad2d=1e-5
        ),
        checkpoint_every=8,
        sh_degree=2,
        sh_increase_every=6,  # SH degree changes during the run, across the interruption
    )


class _Interrupt(StaticGaussians):
    def training_step(self, step):
        if step == 14:
            raise KeyboardInterrupt
        return super().training_step(step)


def _build(cls, scene):
    seed_everything(0)
    return cls(_cfg(), scene, torch.device("cpu"))


def test_resume_bit_identical_with_densification(tiny_scene, tmp_path):
    scene = load_scene(tiny_scene, downscale=2)
    ref = _build(StaticGaussians, scene)
    n0 = len(ref.gaussians)
    ref.fit(TrainContext(checkpoint_dir=tmp_path / "ref", progress=False))
    assert len(ref.gaussians) != n0

    broken = _build(_Interrupt, scene)
    with pytest.raises(KeyboardInterrupt):
        broken.fit(TrainContext(checkpoint_dir=tmp_path / "run", progress=False))
    assert list_checkpoints(tmp_path / "run")[-1][0] == 8
    seed_everything(123)  # the checkpoint, not the process state, must decide what follows
    resumed = StaticGaussians(_cfg(), scene, torch.device("cpu"))
    summary = resumed.fit(TrainContext(checkpoint_dir=tmp_path / "run", progress=False))
    assert summary.start_step == 8 and summary.end_step == 24
    for k, v in ref.gaussians.params.items():
        assert torch.equal(resumed.gaussians.params[k].detach(), v.detach()), k
    for k in ref.optimizer.names:
        a = ref.optimizer.optimizer.state[ref.gaussians.params[k]]
        b = resumed.optimizer.optimizer.state[resumed.gaussians.params[k]]
        assert torch.equal(a["exp_avg"], b["exp_avg"]) and torch.equal(a["exp_avg_sq"], b["exp_avg_sq"]), k


def test_sfm_points_file(tiny_scene, tmp_path):
    import shutil

    root = tmp_path / "withpts"
    shutil.copytree(tiny_scene, root)
    pts = np.random.default_rng(0).random((40, 6)).astype(np.float32)
    np.save(root / "points3d.npy", pts)
    xyz, rgb = load_points(root)
    assert xyz.shape == (40, 3) and rgb.shape == (40, 3)
    model = StaticGaussians(
        dataclasses.replace(_cfg(), init="sfm"), load_scene(root, downscale=2), torch.device("cpu")
    )
    assert len(model.gaussians) == 40
    torch.testing.assert_close(model.gaussians.means.detach(), torch.from_numpy(pts[:, :3]))
    np.save(root / "points3d.npy", np.zeros((5, 4), np.float32))
    with pytest.raises(UserError, match="points3d.npy"):
        load_points(root)
    with pytest.raises(UserError, match="init=sfm"):
        StaticGaussians(
            dataclasses.replace(_cfg(), init="sfm"), load_scene(tiny_scene, downscale=2), torch.device("cpu")
        )
