"""Imported priors at another resolution than the working one: tracks with ``image_size`` are rescaled,
masks and depth maps are resized (the --downscale of a run)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from worldtree.infra.errors import UserError
from worldtree.priors.config import DepthImportConfig
from worldtree.priors.imported import read_depth, read_masks, read_tracks

T, N = 4, 7


@pytest.fixture
def tracks():
    rng = np.random.default_rng(3)
    xy = np.stack([rng.uniform(0, 63, (T, N)), rng.uniform(0, 35, (T, N))], -1).astype(np.float32)
    xy[0, 0] = [-0.5, -0.5]  # the image's top-left edge
    xy[1, 1] = [63.5, 35.5]  # its bottom-right edge
    return xy, np.ones((T, N), bool)


@pytest.mark.parametrize("wh", [(32, 18), (16, 9), (128, 72)])
def test_tracks_with_image_size_are_rescaled(tmp_path, tracks, wh):
    xy, vis = tracks
    np.savez(tmp_path / "t.npz", tracks=xy, visibility=vis, image_size=np.array([64, 36]))
    got, visible = read_tracks(tmp_path / "t.npz", T, wh[1], wh[0])
    f = wh[0] / 64  # same factor along y (same aspect)
    # Closed form for pixel centres at integers; edges map to edges.
    np.testing.assert_allclose(got, (xy + 0.5) * f - 0.5, atol=1e-5)
    np.testing.assert_allclose(got[0, 0], [-0.5, -0.5], atol=1e-6)
    np.testing.assert_allclose(got[1, 1], [wh[0] - 0.5, wh[1] - 0.5], atol=1e-5)
    assert visible.all()


def test_tracks_same_size_or_without_image_size_unchanged(tmp_path, tracks):
    xy, vis = tracks
    np.savez(tmp_path / "same.npz", tracks=xy, visibility=vis, image_size=np.array([64, 36]))
    np.testing.assert_array_equal(read_tracks(tmp_path / "same.npz", T, 36, 64)[0], xy)
    np.savez(tmp_path / "plain.npz", tracks=xy, visibility=vis)
    # Without image_size the positions are taken as given (and points beyond 32x18 become invisible).
    got, visible = read_tracks(tmp_path / "plain.npz", T, 18, 32)
    np.testing.assert_array_equal(got, xy)
    assert not visible.all()


def test_pt_dict_image_size(tmp_path, tracks):
    xy, vis = tracks
    torch.save(
        {"tracks": torch.from_numpy(xy)[None], "visibility": torch.from_numpy(vis)[None],
         "image_size": torch.tensor([64, 36])},
        tmp_path / "t.pt",
    )  # fmt: skip
    got, _ = read_tracks(tmp_path / "t.pt", T, 18, 32)
    np.testing.assert_allclose(got, (xy + 0.5) / 2 - 0.5, atol=1e-5)


def test_tracks_other_aspect_or_bad_size_refused(tmp_path, tracks):
    xy, vis = tracks
    np.savez(tmp_path / "t.npz", tracks=xy, visibility=vis, image_size=np.array([64, 36]))
    with pytest.raises(UserError, match="image_size 64x36 has another aspect ratio than the 32x24 frames"):
        read_tracks(tmp_path / "t.npz", T, 24, 32)
    np.savez(tmp_path / "b.npz", tracks=xy, visibility=vis, image_size=np.array([64, 36, 3]))
    with pytest.raises(UserError, match=r"image_size \[64, 36, 3\]; expected \[W, H\]"):
        read_tracks(tmp_path / "b.npz", T, 36, 64)


def test_masks_and_depth_are_resized_to_the_working_size(tmp_path):
    rng = np.random.default_rng(0)
    (tmp_path / "m").mkdir()
    (tmp_path / "d").mkdir()
    masks = np.zeros((T, 36, 64), bool)
    depth = np.empty((T, 36, 64), np.float32)
    for t in range(T):
        masks[t, 10:20, 8 * t : 8 * t + 16] = True  # even-aligned blocks: exact under a 2x reduction
        depth[t] = 1.0 + rng.random((36, 64))
        cv2.imwrite(str(tmp_path / "m" / f"{t:05d}.png"), masks[t].astype(np.uint8) * 255)
        np.save(tmp_path / "d" / f"{t:05d}.npy", depth[t])
    got_m = read_masks(tmp_path / "m", T, 18, 32)
    assert got_m.shape == (T, 18, 32)
    np.testing.assert_array_equal(got_m, masks[:, ::2, ::2])
    got_d = read_depth(tmp_path / "d", T, 18, 32, DepthImportConfig())
    assert got_d.shape == (T, 18, 32)
    # INTER_AREA at an exact factor 2 is the mean of each 2x2 block.
    np.testing.assert_allclose(got_d, depth.reshape(T, 18, 2, 32, 2).mean(axis=(2, 4)), rtol=1e-5)
