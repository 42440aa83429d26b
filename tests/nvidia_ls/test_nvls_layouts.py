"""The three raw layouts (multi-view folders, per-camera folders, per-camera videos) and their detection."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from nvidia_ls.build import BuildConfig, build_scene
from nvidia_ls.layouts import open_raw
from nvidia_ls.synth import SynthConfig, write_raw_scene
from worldtree.imageio import read_image
from worldtree.scene import load_scene

SMALL = dict(cameras=4, steps=6, width=64, height=36, supersample=1)


def test_multiview_layout_detected(tiny_raw):
    raw = open_raw(tiny_raw)
    assert raw.layout == "multiview" and raw.cameras == [1, 2, 3, 4] and raw.times == list(range(6))
    assert (raw.width, raw.height) == (64, 36)


def test_dense_subfolder_and_scene_name(tiny_raw, tmp_path):
    root = tmp_path / "Balloon1"
    shutil.copytree(tiny_raw / "mv_images", root / "dense" / "mv_images")
    raw = open_raw(root / "dense")
    assert raw.layout == "multiview" and raw.root == root / "dense" / "mv_images"
    out = build_scene(
        root / "dense", tmp_path / "out", BuildConfig(poses=tiny_raw / "gt" / "poses_bounds.npy")
    )
    assert out.name == "Balloon1"
    assert open_raw(root).layout == "multiview"
    assert open_raw(root / "dense" / "mv_images").times == list(range(6))


@pytest.mark.parametrize("layout", ["camera_folders", "videos"])
def test_other_layouts_build_the_same_scene(layout, tiny_raw, tmp_path):
    raw_dir = write_raw_scene(tmp_path / "raw", SynthConfig(layout=layout, **SMALL))
    raw = open_raw(raw_dir)
    assert raw.layout == layout and raw.cameras == [1, 2, 3, 4] and len(raw.times) == 6
    scene = build_scene(raw_dir, tmp_path / "out", BuildConfig(poses=raw_dir / "gt" / "poses_bounds.npy"))
    meta = json.loads((scene / "cameras.json").read_text())
    assert [f["camera"] for f in meta["frames"]] == [2, 3, 4, 3, 2, 3]
    for f in meta["frames"]:
        ref = read_image(tiny_raw / "mv_images" / f"{f['source_time']:05d}" / f"cam{f['camera']:02d}.png")
        got = read_image(scene / f["file"])
        if layout == "camera_folders":
            np.testing.assert_array_equal(got, ref)  # lossless PNG end to end
        else:
            # mp4v is lossy: the decoded frame is close to the rendered one, and the right one.
            assert np.abs(got.astype(float) - ref).mean() < 12
    assert load_scene(scene).num_frames == 6


def test_no_layout_is_a_clear_error(tmp_path):
    from worldtree.infra.errors import UserError

    (tmp_path / "stuff").mkdir()
    with pytest.raises(UserError, match="no raw layout found"):
        open_raw(tmp_path)
