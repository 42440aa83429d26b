"""benchmarks.speed.photometric_step's variants switch exactly the two compiled motion kernels."""

from __future__ import annotations

import torch

from benchmarks.speed.photometric_step import _variants
from worldtree.motion import regularizers, skinning


def test_variants_take_the_tensor_versions_or_the_kernels():
    v = _variants()
    assert list(v) == ["tensor", "relative", "compiled"]
    assert v["tensor"][1] is regularizers._smoothness_tensor and v["relative"][1] is regularizers._smoothness_tensor
    assert v["tensor"][0](torch.zeros(2, 4)) is None  # no compiled ops: relative_dual's tensor version
    assert v["relative"][0] is skinning._relative_ops and v["compiled"][0] is skinning._relative_ops
    assert v["compiled"][1] is regularizers.smoothness_losses
