"""worldtree.pixels: frames held as uint8, compared as float in [0, 1]."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from worldtree.pixels import as_uint8, unit_float


def test_unit_float_divides_uint8_by_255_and_keeps_float():
    u8 = torch.arange(256, dtype=torch.uint8).reshape(4, 8, 8)
    f = unit_float(u8)
    assert f.dtype == torch.float32
    np.testing.assert_array_equal(
        f.numpy(), np.arange(256, dtype=np.float32).reshape(4, 8, 8) / np.float32(255)
    )
    x = torch.rand(3, 2, 2, 3)
    assert unit_float(x) is x  # float input: unchanged, no copy
    assert u8[-1, -1, -1] == 255  # the uint8 input is not modified in place


def test_round_trip_is_exact_for_every_8_bit_value():
    u8 = torch.arange(256, dtype=torch.uint8)
    assert torch.equal(as_uint8(unit_float(u8)), u8)
    assert as_uint8(u8) is u8


def test_as_uint8_clamps_and_rounds():
    x = torch.tensor([-0.5, 0.0, 0.4 / 255, 0.6 / 255, 1.0, 1.7, float("nan")])
    got = as_uint8(x[:-1])
    assert got.tolist() == [0, 0, 0, 1, 255, 255]


def test_unit_float_refuses_other_integer_types():
    with pytest.raises(TypeError, match="uint8"):
        unit_float(torch.zeros(2, dtype=torch.int64))


def test_numpy_twin_rounds_as_the_torch_one():
    # worldtree.imageio.as_uint8_array is what the OpenCV code uses; both must give the same levels, here on
    # every level's centre, the half-way points between levels (0.5 / 255 apart) and out-of-range values.
    from worldtree.imageio import as_uint8_array

    levels = np.arange(256, dtype=np.float32) / np.float32(255)
    halves = (np.arange(255, dtype=np.float32) + np.float32(0.5)) / np.float32(255)
    x = np.concatenate([levels, halves, np.array([-0.5, 1.7], np.float32)])
    np.testing.assert_array_equal(as_uint8_array(x), as_uint8(torch.from_numpy(x)).numpy())
    np.testing.assert_array_equal(as_uint8_array(levels), np.arange(256))  # exact on k / 255
    # float64 input is rounded in float64 (the callers' precision), NaN reads as 0, uint8 is returned as is.
    assert as_uint8_array(np.array([0.6 / 255, np.nan, np.inf, -np.inf])).tolist() == [1, 0, 255, 0]
    u8 = np.arange(256, dtype=np.uint8)
    assert as_uint8_array(u8) is u8
    with pytest.raises(TypeError, match="uint8"):
        as_uint8_array(np.zeros(2, dtype=np.int64))
