"""End-to-end build with ground-truth poses (--poses): layout, counts, order, exact poses, verify."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from nvidia_ls.build import BuildConfig, build_scene
from nvidia_ls.manifest import verify_scene
from nvidia_ls.synth import read_gt_cameras
from worldtree.imageio import read_image
from worldtree.infra.hashing import sha256_file
from worldtree.scene import load_scene


def test_files_and_counts(built_gt):
    meta = json.loads((built_gt / "cameras.json").read_text())
    man = json.loads((built_gt / "manifest.json").read_text())
    assert len(sorted((built_gt / "images").glob("*.png"))) == 20
    assert len(sorted((built_gt / "gt_images").glob("v001_t*.png"))) == 20
    assert len(sorted((built_gt / "masks").glob("v001_t*.png"))) == 20
    assert (built_gt / "preview.png").is_file()
    assert np.load(built_gt / "poses_bounds.npy").shape == (12, 17)
    # 24 raw steps sampled down to 20: round(linspace(0, 23, 20)), first and last kept.
    expected = np.round(np.linspace(0, 23, 20)).astype(int).tolist()
    assert man["source_times"] == expected
    assert [f["source_time"] for f in meta["frames"]] == expected
    assert [f["source_time"] for f in meta["test_frames"]] == expected
    assert man["counts"] == {"frames": 20, "test_frames": 20, "masks": 20, "cameras": 12}


def test_pingpong_and_test_camera_never_trains(built_gt):
    meta = json.loads((built_gt / "cameras.json").read_text())
    cams = [f["camera"] for f in meta["frames"]]
    # Written out by hand: 2..12 then back down, period 20.
    assert cams == [2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3]
    assert 1 not in cams
    assert all(f["camera"] == 1 for f in meta["test_frames"])


def test_frames_are_the_raw_images(built_gt, synth_raw):
    meta = json.loads((built_gt / "cameras.json").read_text())
    for f in meta["frames"][:5] + meta["test_frames"][:3]:
        raw = read_image(synth_raw / "mv_images" / f"{f['source_time']:05d}" / f"cam{f['camera']:02d}.png")
        np.testing.assert_array_equal(read_image(built_gt / f["file"]), raw)


def test_load_scene_reproduces_gt_poses(built_gt, synth_raw):
    scene = load_scene(built_gt)
    Ks, w2cs = read_gt_cameras(synth_raw)
    assert scene.num_frames == 20 and scene.test_images.shape[0] == 20
    assert scene.test_masks is not None and scene.test_masks.shape == (20, 144, 256)
    assert (scene.width, scene.height) == (256, 144)
    for i in range(20):
        cam = int(scene.frame_cameras[i])
        np.testing.assert_allclose(scene.w2cs[i].numpy(), w2cs[cam - 1], atol=1e-5)
        np.testing.assert_allclose(scene.Ks[i].numpy(), Ks[cam - 1], atol=1e-4)
    np.testing.assert_allclose(scene.test_w2c.numpy(), w2cs[0], atol=1e-5)
    assert 0 < scene.near < scene.far
    gt_pb = np.load(synth_raw / "gt" / "poses_bounds.npy")
    np.testing.assert_allclose(np.load(built_gt / "poses_bounds.npy"), gt_pb, atol=1e-9)


def test_manifest_hashes_every_file(built_gt):
    man = json.loads((built_gt / "manifest.json").read_text())
    files = {p.relative_to(built_gt).as_posix() for p in built_gt.rglob("*") if p.is_file()}
    assert set(man["files"]) == files - {"manifest.json"}
    some = sorted(man["files"])[::17]
    assert all(man["files"][rel] == sha256_file(built_gt / rel) for rel in some)
    assert man["poses"]["method"] == "file" and man["masks"]["method"] == "background-median"
    assert set(man["timings_s"]) >= {"sfm", "undistort", "masks", "write"}


def test_verify_passes_then_fails_on_tampering(built_gt, tmp_path):
    assert verify_scene(built_gt) == []
    bad = tmp_path / "bad"
    shutil.copytree(built_gt, bad)
    img = bad / "images" / "00003.png"
    img.write_bytes(img.read_bytes()[:-10] + b"0123456789")
    (bad / "masks" / "v001_t005.png").unlink()
    meta = json.loads((bad / "cameras.json").read_text())
    meta["cameras"][4]["w2c"][0][0] = 2.0  # no longer a rotation
    (bad / "cameras.json").write_text(json.dumps(meta))
    problems = "\n".join(verify_scene(bad))
    assert "images/00003.png: checksum differs" in problems
    assert "masks/v001_t005.png: missing" in problems
    assert "mask count mismatch" in problems
    assert "camera 5: rotation not orthonormal" in problems
    assert "cameras.json: checksum differs" in problems


def test_verify_ignores_the_priors_cache_but_not_other_extra_files(built_gt, tmp_path):
    scene = tmp_path / "with_cache"
    shutil.copytree(built_gt, scene)
    # `wtbench prep` / `wtbench run` cache priors under SCENE/priors; `nvls gt-priors` writes SCENE/gt_priors.
    for rel in ("priors/x2/depth-0123/all.npz", "gt_priors/masks/00000.png"):
        (scene / rel).parent.mkdir(parents=True, exist_ok=True)
        (scene / rel).write_bytes(b"derived")
    assert verify_scene(scene) == []
    (scene / "images" / "stray.png").write_bytes(b"x")
    assert any("images/stray.png: not listed" in p for p in verify_scene(scene))


def test_verify_reports_count_mismatch(built_gt, tmp_path):
    bad = tmp_path / "bad2"
    shutil.copytree(built_gt, bad)
    (bad / "images" / "00019.png").unlink()
    problems = "\n".join(verify_scene(bad, check_hashes=False))
    assert "frame count mismatch" in problems and "images/00019.png: missing" in problems


def test_existing_output_needs_force(built_gt, synth_raw):
    cfg = BuildConfig(poses=synth_raw / "gt" / "poses_bounds.npy", frames=20)
    from worldtree.infra.errors import UserError

    with pytest.raises(UserError, match="--force"):
        build_scene(synth_raw, built_gt.parent, cfg)


def test_resize_scales_intrinsics(synth_raw, tmp_path):
    cfg = BuildConfig(poses=synth_raw / "gt" / "poses_bounds.npy", frames=4, size=(128, 72))
    scene = load_scene(build_scene(synth_raw, tmp_path, cfg))
    Ks, _ = read_gt_cameras(synth_raw)
    assert scene.images.shape[1:] == (72, 128, 3)
    # Half size: f halves, the centre moves to (W'-1)/2 (OpenCV pixel centres).
    np.testing.assert_allclose(scene.test_K.numpy()[0, 0], Ks[0][0, 0] / 2, rtol=1e-6)
    np.testing.assert_allclose(scene.test_K.numpy()[:2, 2], [63.5, 35.5], atol=1e-4)


def test_build_synthetic_scene_in_one_call(tmp_path):
    from nvidia_ls.demo import build_synthetic_scene
    from nvidia_ls.synth import SynthConfig

    raw, scene_dir = build_synthetic_scene(
        tmp_path, SynthConfig(cameras=5, steps=6, width=48, height=32), BuildConfig(frames=4)
    )
    scene = load_scene(scene_dir)
    _, w2cs = read_gt_cameras(raw)
    assert scene.num_frames == 4 and scene_dir == tmp_path / "scenes" / "Synth"
    assert scene.frame_cameras.tolist() == [2, 3, 4, 5]
    np.testing.assert_allclose(scene.w2cs[2].numpy(), w2cs[3], atol=1e-5)
