"""Bad raw input: each case is a one-line UserError naming the fix, and nothing is left half-written."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from nvidia_ls.build import BuildConfig, build_scene
from worldtree.infra.errors import UserError


@pytest.fixture
def raw(tiny_raw, tmp_path) -> Path:
    dst = tmp_path / "Raw"
    shutil.copytree(tiny_raw, dst)
    return dst


def _cfg(raw: Path, **kw) -> BuildConfig:
    return BuildConfig(poses=raw / "gt" / "poses_bounds.npy", **kw)


def _fails(raw: Path, out: Path, cfg: BuildConfig, match: str) -> str:
    with pytest.raises(UserError, match=match) as e:
        build_scene(raw, out, cfg)
    msg = str(e.value)
    assert "\n" not in msg
    # Nothing is left: no scene, no temporary folder, not even the -o folder the build made.
    assert not out.exists(), sorted(p.name for p in out.iterdir())
    return msg


def test_missing_camera(raw, tmp_path):
    for d in (raw / "mv_images").iterdir():
        (d / "cam03.png").unlink()
    _fails(raw, tmp_path / "out", _cfg(raw), "missing cameras cam03")


def test_missing_last_camera_with_num_cameras(raw, tmp_path):
    for d in (raw / "mv_images").iterdir():
        (d / "cam04.png").unlink()
    _fails(raw, tmp_path / "out", _cfg(raw, num_cameras=4), "missing cameras cam04")


def test_time_steps_missing_for_some_cameras_warns_and_uses_common(raw, tmp_path):
    (raw / "mv_images" / "00002" / "cam02.png").unlink()
    (raw / "mv_images" / "00004" / "cam04.png").unlink()
    notes = []
    scene = build_scene(raw, tmp_path / "out", _cfg(raw), log=notes.append)
    assert any("2 time steps (2, 4) lack some cameras" in n for n in notes)
    import json

    man = json.loads((scene / "manifest.json").read_text())
    assert man["source_times"] == [0, 1, 3, 5]
    assert any("lack some cameras" in w for w in man["warnings"])


def test_camera_with_another_image_size(raw, tmp_path):
    for p in (raw / "mv_images").rglob("cam02.png"):
        cv2.imwrite(str(p), np.zeros((40, 70, 3), np.uint8))
    msg = _fails(raw, tmp_path / "out", _cfg(raw), "same image size")
    assert "cam02.png" in msg and "70x40" in msg


def test_one_frame_of_another_size(raw, tmp_path):
    # cam02 supplies training frame 4 (ping-pong 2, 3, 4, 3, 2, 3): that frame is read and checked.
    p = raw / "mv_images" / "00004" / "cam02.png"
    cv2.imwrite(str(p), np.zeros((40, 70, 3), np.uint8))
    msg = _fails(raw, tmp_path / "out", _cfg(raw), "same image size")
    assert "00004/cam02.png" in msg


def test_truncated_png(raw, tmp_path):
    p = raw / "mv_images" / "00004" / "cam02.png"
    p.write_bytes(p.read_bytes()[:60])
    _fails(raw, tmp_path / "out", _cfg(raw), "cam02.png: cannot decode")


def test_truncated_jpeg(tmp_path):
    from nvidia_ls.synth import SynthConfig, write_raw_scene

    raw = write_raw_scene(
        tmp_path / "J", SynthConfig(cameras=3, steps=4, width=48, height=32, image_ext="jpg")
    )
    p = raw / "mv_images" / "00001" / "cam03.jpg"  # ping-pong 2, 3, 2, 3: frame 1 is cam03
    p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])
    _fails(raw, tmp_path / "out", _cfg(raw), "cam03.jpg: truncated JPEG")


def test_fewer_frames_than_requested_warns_and_keeps_all(raw, tmp_path):
    notes = []
    scene = build_scene(raw, tmp_path / "out", _cfg(raw, frames=50), log=notes.append)
    assert any("only 6 time steps" in n and "--frames 50" in n for n in notes)
    assert len(list((scene / "images").glob("*.png"))) == 6


def test_sfm_failing_everywhere(raw, tmp_path):
    for p in (raw / "mv_images").rglob("*.png"):
        cv2.imwrite(str(p), np.full((36, 64, 3), 128, np.uint8))  # featureless
    msg = _fails(raw, tmp_path / "out", BuildConfig(sfm_tries=2), "SfM registered at most")
    assert "--poses" in msg


@pytest.mark.parametrize("shape", [(3, 17), (4, 15), (68,)])
def test_poses_file_of_wrong_shape(raw, tmp_path, shape):
    bad = tmp_path / "pb.npy"
    np.save(bad, np.zeros(shape))
    _fails(raw, tmp_path / "out", BuildConfig(poses=bad), r"expected \(4, 17\)")


def test_poses_file_not_rotations(raw, tmp_path):
    pb = np.load(raw / "gt" / "poses_bounds.npy")
    pb[1, 0] = 3.0
    bad = tmp_path / "pb.npy"
    np.save(bad, pb)
    _fails(raw, tmp_path / "out", BuildConfig(poses=bad), "not orthonormal")


def test_test_camera_outside_rig(raw, tmp_path):
    _fails(raw, tmp_path / "out", _cfg(raw, test_camera=9), "--test-camera 9")


def test_masks_missing_for_some_frames(raw, tmp_path):
    shutil.rmtree(raw / "gt" / "masks" / "00005")
    _fails(raw, tmp_path / "out", _cfg(raw, masks=raw / "gt" / "masks"), "no mask for 1 of 6")


def test_other_test_camera_pingpongs_the_rest(raw, tmp_path):
    import json

    scene = build_scene(raw, tmp_path / "out", _cfg(raw, test_camera=3))
    meta = json.loads((scene / "cameras.json").read_text())
    assert [f["camera"] for f in meta["frames"]] == [1, 2, 4, 2, 1, 2]
    assert meta["test_camera"] == 3
