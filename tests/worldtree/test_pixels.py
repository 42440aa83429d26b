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
