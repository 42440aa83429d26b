"""Test-camera masks: the background model against the synthetic ground truth, and imported masks."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from nvidia_ls.build import BuildConfig, build_scene
from nvidia_ls.masks import background_masks, import_masks
from worldtree.imageio import read_mask
from worldtree.infra.errors import UserError


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = (a | b).sum()
    return 1.0 if union == 0 else float((a & b).sum() / union)


def test_background_masks_match_ground_truth(built_sfm, synth_raw):
    meta = json.loads((built_sfm / "cameras.json").read_text())
    ious = []
    for f in meta["test_frames"]:
        est = read_mask(built_sfm / f["mask"])
        gt = read_mask(synth_raw / "gt" / "masks" / f"{f['source_time']:05d}" / "cam01.png")
        ious.append(_iou(est, gt))
    assert np.mean(ious) >= 0.8, ious
    assert min(ious) >= 0.6, ious


def test_mask_files_are_binary_uint8(built_gt):
    m = cv2.imread(str(built_gt / "masks" / "v001_t000.png"), cv2.IMREAD_UNCHANGED)
    assert m.dtype == np.uint8 and m.ndim == 2
    assert set(np.unique(m).tolist()) <= {0, 255}


def test_background_model_on_a_moving_square():
    # A bright square sliding over a textured background: the mask is the square, nothing else.
    rng = np.random.default_rng(0)
    bg = (rng.random((60, 80, 3)) * 120).astype(np.uint8)
    bg = cv2.GaussianBlur(bg, (5, 5), 0)
    frames, gts = [], []
    for t in range(12):
        img, gt = bg.copy(), np.zeros((60, 80), bool)
        x = 5 + 5 * t
        img[20:35, x : x + 15] = 230
        gt[20:35, x : x + 15] = True
        frames.append(img)
        gts.append(gt)
    masks = background_masks(np.stack(frames))
    assert all(_iou(m, g) > 0.9 for m, g in zip(masks, gts, strict=True))


def test_background_needs_three_frames():
    with pytest.raises(UserError, match="--masks"):
        background_masks(np.zeros((2, 8, 8, 3), np.uint8))


def test_imported_masks_equal_ground_truth(synth_raw, tmp_path):
    cfg = BuildConfig(poses=synth_raw / "gt" / "poses_bounds.npy", frames=6, masks=synth_raw / "gt" / "masks")
    scene = build_scene(synth_raw, tmp_path, cfg)
    meta = json.loads((scene / "cameras.json").read_text())
    man = json.loads((scene / "manifest.json").read_text())
    assert man["masks"]["method"] == "imported"
    for f in meta["test_frames"]:
        gt = read_mask(synth_raw / "gt" / "masks" / f"{f['source_time']:05d}" / "cam01.png")
        np.testing.assert_array_equal(read_mask(scene / f["mask"]), gt)


def test_imported_masks_flat_names_are_resized_nearest(tmp_path):
    d = tmp_path / "m"
    d.mkdir()
    big = np.zeros((20, 40), np.uint8)
    big[:, 20:] = 200  # right half set, grey level above half range
    for t in (3, 7):
        cv2.imwrite(str(d / f"{t:05d}.png"), big)
    out = import_masks(d, [3, 7], camera=1, width=8, height=4)
    assert out.shape == (2, 4, 8) and out.dtype == bool
    np.testing.assert_array_equal(out[0], np.tile([False] * 4 + [True] * 4, (4, 1)))


def test_imported_masks_authors_names_by_kept_index(tmp_path):
    # The authors' NVIDIA-LS masks are named v001_tXXX by kept-frame index, not by source time.
    d = tmp_path / "m"
    d.mkdir()
    for i in range(2):
        m = np.zeros((4, 8), np.uint8)
        m[:, i] = 255
        cv2.imwrite(str(d / f"v001_t{i:03d}.png"), m)
    out = import_masks(d, [10, 20], camera=1, width=8, height=4)
    assert out[0, :, 0].all() and not out[0, :, 1:].any()
    assert out[1, :, 1].all() and not out[1, :, [0, *range(2, 8)]].any()


def test_imported_masks_missing_is_one_line_error(synth_raw, tmp_path):
    masks = tmp_path / "masks"
    shutil.copytree(synth_raw / "gt" / "masks", masks)
    shutil.rmtree(masks / "00004")
    shutil.rmtree(masks / "00009")
    cfg = BuildConfig(poses=synth_raw / "gt" / "poses_bounds.npy", masks=masks)
    with pytest.raises(UserError) as e:
        build_scene(synth_raw, tmp_path / "out", cfg)
    msg = str(e.value)
    assert "\n" not in msg and "no mask for 2 of 24" in msg and "00004" in msg and "00009" in msg
    # Masks are checked before any frame is processed: nothing at all is written.
    assert not (tmp_path / "out").exists()
