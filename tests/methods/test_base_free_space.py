"""The Base method's guards against a depth that measures moving objects: an imported depth's pixels that float
in front of the scene left out (``_drop_floating_depth``), and the static floater removal only with such a
depth (``BaseConfig.photometric_config``)."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import torch

from methods.base import BaseConfig, _drop_floating_depth, prior_use
from tests.worldtree.stages.test_stages_photometric import scene
from worldtree.priors import PriorsConfig


def test_the_classical_depth_switches_the_removal_off_for_every_fit():
    classical = BaseConfig()
    assert classical.photometric.floater_every > 0
    assert classical.photometric_config().floater_every == 0
    assert "photometric.floater_every" in classical.ignored_settings()
    imported = dataclasses.replace(classical, priors=PriorsConfig(depth_source="/some/depth"))
    assert imported.photometric_config().floater_every == classical.photometric.floater_every
    assert "photometric.floater_every" not in imported.ignored_settings()
    use = prior_use(imported, {"depth": "imported:/some/depth"})["depth"]["used_in"]["photometric"]
    assert "photometric.floater_every" in use
    assert "photometric.floater_every" not in prior_use(classical, {})["depth"]["used_in"]["photometric"]


def _state(depth_source: str):
    imgs, depth, Ks, w2cs, *_ = scene()
    T, H, W = depth.shape
    depth = torch.full_like(depth, 4.2)  # a wall: the scene's own moving object is not in this depth
    mask = torch.zeros(T, H, W, dtype=torch.bool)
    depth[1, 10:16, 30:38] = 1.2  # a near object in frame 1 that no mask holds: floats in front
    depth[3, 10:16, 4:12] = 1.2  # the same in frame 3, inside its mask: the moving object's own depth
    mask[3, 10:16, 4:12] = True
    base = BaseConfig()
    on = dataclasses.replace(base.depth_free_space, enabled=True)  # off by default
    cfg = dataclasses.replace(base, priors=PriorsConfig(depth_source=depth_source), depth_free_space=on)
    return SimpleNamespace(
        cfg=cfg,
        depth=depth,
        scene=SimpleNamespace(Ks=Ks),
        w2cs=w2cs,
        P={"epi_mask": mask, "depth_conf": torch.ones(T, H, W)},
        info={},
    )


def test_an_imported_depth_loses_its_floating_pixels_outside_the_masks_only():
    s = _state("/imported/depth")
    before = s.depth.clone()
    _drop_floating_depth(s)
    assert bool((s.depth[1, 10:16, 30:38] == 0).all()) and bool(
        (s.P["depth_conf"][1, 10:16, 30:38] == 0).all()
    )
    assert torch.equal(s.depth[3], before[3])  # inside the mask: kept
    changed = s.depth != before
    changed[1, 10:16, 30:38] = False
    assert not bool(changed.any())  # nothing else touched
    assert 0 < s.info["depth_free_space"]["dropped_fraction"] < 0.05


def test_the_classical_depth_and_a_switched_off_check_are_left_as_they_are():
    s = _state("classical")
    before = s.depth.clone()
    _drop_floating_depth(s)
    assert torch.equal(s.depth, before) and "depth_free_space" not in s.info
    assert not BaseConfig().depth_free_space.enabled  # the default
    s = _state("/imported/depth")
    s.cfg = dataclasses.replace(s.cfg, depth_free_space=BaseConfig().depth_free_space)
    before = s.depth.clone()
    _drop_floating_depth(s)
    assert torch.equal(s.depth, before)
