"""benchmarks.speed.photometric_step's variants switch exactly the two compiled motion kernels."""

from __future__ import annotations

import torch

from benchmarks.speed.photometric_step import _variants
from worldtree.motion import regularizers, skinning


def test_variants_take_the_tensor_versions_or_the_kernels():
    v = _variants()
    assert list(v) == ["tensor", "relative", "compiled"]
    g = torch.Generator().manual_seed(0)
    pos, quat = torch.randn(5, 3, 3, generator=g), torch.randn(5, 3, 4, generator=g)
    want = (*regularizers.velocity_losses(pos, quat), *regularizers.acceleration_losses(pos, quat))
    for name in ("tensor", "relative"):
        got = v[name][1](pos, quat)
        assert all(torch.equal(a, b) for a, b in zip(got, want, strict=True))
    assert v["tensor"][0](pos) is None  # no compiled ops: relative_dual's tensor version
    assert v["relative"][0] is skinning._relative_ops and v["compiled"][0] is skinning._relative_ops
    assert v["compiled"][1] is regularizers.smoothness_losses
