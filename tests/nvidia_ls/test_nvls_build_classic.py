"""`nvls build --protocol classic`: the 12-frame protocol of DynamicNeRF / NSFF / MoSca (frame t from rig camera
t, the test view frame 0's camera at every time), checked on the synthetic rig against its raw images."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from nvidia_ls.build import BuildConfig, build_scene
from nvidia_ls.manifest import verify_scene
from worldtree.imageio import read_image
from worldtree.infra.errors import SettingError
from worldtree.scene import load_scene


@pytest.fixture(scope="module")
def classic(synth_raw, tmp_path_factory):
    out = tmp_path_factory.mktemp("classic")
    return build_scene(
        synth_raw, out, BuildConfig(poses=synth_raw / "gt" / "poses_bounds.npy", protocol="classic")
    )


def test_frame_t_is_camera_t_at_time_t(classic, synth_raw):
    meta = json.loads((classic / "cameras.json").read_text())
    # 12 cameras: 12 frames (not --frames' 160), the first 12 time steps, cameras 1..12 in order.
    assert [(f["camera"], f["source_time"]) for f in meta["frames"]] == [(c, c - 1) for c in range(1, 13)]
    assert [(f["camera"], f["source_time"]) for f in meta["test_frames"]] == [(1, t) for t in range(12)]
    for f in meta["frames"] + meta["test_frames"]:
        raw = read_image(synth_raw / "mv_images" / f"{f['source_time']:05d}" / f"cam{f['camera']:02d}.png")
        np.testing.assert_array_equal(read_image(classic / f["file"]), raw)
    # The test view at t = 0 is training frame 0 (the same image and the same camera).
    np.testing.assert_array_equal(read_image(classic / meta["frames"][0]["file"]),
                                  read_image(classic / meta["test_frames"][0]["file"]))  # fmt: skip
    scene = load_scene(classic)
    assert torch.equal(scene.test_w2c, scene.w2cs[0]) and torch.equal(scene.test_K, scene.Ks[0])


def test_verify_accepts_it_and_catches_a_wrong_order(classic, tmp_path):
    assert verify_scene(classic) == []
    man = json.loads((classic / "manifest.json").read_text())
    assert man["protocol"] == "classic" and man["train_cameras"][0] == 1
    bad = tmp_path / "bad"
    shutil.copytree(classic, bad)
    meta = json.loads((bad / "cameras.json").read_text())
    meta["frames"][3]["camera"], meta["frames"][4]["camera"] = 5, 4
    (bad / "cameras.json").write_text(json.dumps(meta))
    assert any("classic order" in p for p in verify_scene(bad, check_hashes=False))


def test_another_test_camera_starts_the_order_and_frames_caps_it(synth_raw, tmp_path):
    out = build_scene(synth_raw, tmp_path, BuildConfig(poses=synth_raw / "gt" / "poses_bounds.npy",
                                                       protocol="classic", test_camera=11, frames=4))  # fmt: skip
    meta = json.loads((out / "cameras.json").read_text())
    assert [f["camera"] for f in meta["frames"]] == [11, 12, 1, 2]
    assert [f["source_time"] for f in meta["frames"]] == [0, 1, 2, 3]
    assert verify_scene(out) == []


def test_an_unknown_protocol_is_refused():
    with pytest.raises(SettingError, match="protocol"):
        BuildConfig(protocol="short").check()
