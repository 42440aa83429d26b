"""LLFF conversions (column order, round trips) and frame sampling / ping-pong order."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nvidia_ls.llff import llff_to_opencv, opencv_to_llff
from nvidia_ls.sampling import pingpong, sample_times, training_cameras
from worldtree.infra.errors import UserError


def test_llff_columns_by_hand():
    # Camera at (1, 2, 3) with OpenCV axes = world axes: c2w = [I | c].
    w2c = np.eye(4)
    w2c[:3, 3] = -np.array([1.0, 2.0, 3.0])
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    row = opencv_to_llff(w2c[None], K[None], 48, 64, np.array([[0.5, 9.0]]))[0]
    mat = row[:15].reshape(3, 5)
    np.testing.assert_allclose(mat[:, 0], [0, 1, 0])  # down = OpenCV +y
    np.testing.assert_allclose(mat[:, 1], [1, 0, 0])  # right = OpenCV +x
    np.testing.assert_allclose(mat[:, 2], [0, 0, -1])  # back = -forward
    np.testing.assert_allclose(mat[:, 3], [1, 2, 3])
    np.testing.assert_allclose(mat[:, 4], [48, 64, 100])
    np.testing.assert_allclose(row[15:], [0.5, 9.0])


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=6, max_size=6), st.floats(50, 500))
def test_llff_round_trip(params, f):
    R = cv2.Rodrigues(np.array(params[:3]))[0]
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = params[3:]
    K = np.array([[f, 0, 63.5], [0, f, 35.5], [0, 0, 1]])
    pb = opencv_to_llff(w2c[None], K[None], 72, 128, np.array([[1.0, 5.0]]))
    Ks, w2cs, bounds = llff_to_opencv(pb)
    np.testing.assert_allclose(w2cs[0], w2c, atol=1e-9)
    np.testing.assert_allclose(Ks[0], K, atol=1e-9)
    # Loading for half-size images halves f and centres the principal point at (W'-1)/2.
    Ks2, _, _ = llff_to_opencv(pb, 64, 36)
    np.testing.assert_allclose(Ks2[0], [[f / 2, 0, 31.5], [0, f / 2, 17.5], [0, 0, 1]], atol=1e-9)


def test_pingpong_12_cameras_period_20():
    train = training_cameras(list(range(1, 13)), 1)
    order = pingpong(train, 45)
    assert order[:21] == [2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2]
    assert order[20:40] == order[:20] and order[40:] == order[:5]


def test_pingpong_edge_cases():
    assert pingpong([5], 3) == [5, 5, 5]
    assert pingpong([2, 3], 5) == [2, 3, 2, 3, 2]
    assert training_cameras([1, 2, 3, 4], 2) == [1, 3, 4]
    with pytest.raises(UserError):
        training_cameras([1], 1)
    with pytest.raises(UserError, match="--test-camera 7"):
        training_cameras([1, 2, 3], 7)


@given(st.integers(1, 400), st.integers(1, 200))
def test_sample_times_uniform_and_distinct(n, frames):
    times = list(range(100, 100 + 3 * n, 3))
    kept = sample_times(times, frames)
    assert len(kept) == min(n, frames)
    assert kept == sorted(set(kept)) and set(kept) <= set(times)
    assert kept[0] == times[0]
    if min(n, frames) > 1:
        assert kept[-1] == times[-1]
    if n > frames > 1:
        gaps = np.diff([times.index(k) for k in kept])
        assert gaps.max() - gaps.min() <= 1  # uniform up to rounding
