"""LPIPS architecture and arithmetic with random weights, against an independent numpy implementation."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from numpy.lib.stride_tricks import sliding_window_view

from benchmarks.evaluation.lpips import LPIPS, AlexNetFeatures, random_state_dicts

# torchvision's AlexNet `features` (conv index -> weight shape), and its output sizes for a 224x224 input.
TV_SHAPES = {
    0: (64, 3, 11, 11),
    3: (192, 64, 5, 5),
    6: (384, 192, 3, 3),
    8: (256, 384, 3, 3),
    10: (256, 256, 3, 3),
}
TV_RELU_SIZES_224 = [(64, 55, 55), (192, 27, 27), (384, 13, 13), (256, 13, 13), (256, 13, 13)]


def test_shapes_match_torchvision_alexnet_and_lpips_heads():
    m = LPIPS()
    for i, shape in TV_SHAPES.items():
        assert tuple(m.net.convs[str(i)].weight.shape) == shape
        assert tuple(m.net.convs[str(i)].bias.shape) == (shape[0],)
    assert [tuple(lin.weight.shape) for lin in m.lins] == [(1, c, 1, 1) for c in (64, 192, 384, 256, 256)]
    feats = m.net(torch.zeros(1, 3, 224, 224))
    assert [tuple(f.shape[1:]) for f in feats] == TV_RELU_SIZES_224


def test_torchvision_format_state_dict_loads_from_file(tmp_path):
    alex, lin = random_state_dicts()
    torch.save(alex, tmp_path / "alexnet.pth")
    torch.save(lin, tmp_path / "alex.pth")
    m = LPIPS.from_state_dicts(
        torch.load(tmp_path / "alexnet.pth", weights_only=True),
        torch.load(tmp_path / "alex.pth", weights_only=True),
    )
    assert torch.equal(m.net.convs["6"].weight, alex["features.6.weight"])
    assert torch.equal(m.lins[3].weight, lin["lin3.model.1.weight"])


@pytest.mark.parametrize("bad", ["missing", "shape", "extra"])
def test_bad_state_dicts_are_refused(bad):
    alex, lin = random_state_dicts()
    if bad == "missing":
        del alex["features.8.bias"]
    elif bad == "shape":
        alex["features.3.weight"] = torch.zeros(192, 64, 3, 3)
    else:
        lin["lin5.model.1.weight"] = torch.zeros(1, 8, 1, 1)
    with pytest.raises(ValueError):
        LPIPS.from_state_dicts(alex, lin)
    with pytest.raises(ValueError):
        AlexNetFeatures().load_torchvision_state_dict({"features.0.weight": torch.zeros(64, 3, 11, 11)})


# ------------------------------------------------------------------ independent numpy LPIPS (tiny images)


def np_conv(x, w, b, stride, pad):
    """x [C, H, W], w [O, C, k, k] -> [O, H', W'] by explicit windows (cross-correlation, zero padding)."""
    x = np.pad(x, ((0, 0), (pad, pad), (pad, pad)))
    k = w.shape[-1]
    win = sliding_window_view(x, (k, k), axis=(1, 2))[:, ::stride, ::stride]  # [C, H', W', k, k]
    return np.einsum("chwij,ocij->ohw", win, w) + b[:, None, None]


def np_maxpool(x):
    return sliding_window_view(x, (3, 3), axis=(1, 2))[:, ::2, ::2].max(axis=(-1, -2))


def np_lpips_layers(x0, x1, alex, lin):
    """Per-layer LPIPS maps [H_l, W_l] for [3, H, W] inputs in [-1, 1]."""
    shift = np.array([-0.030, -0.088, -0.188])[:, None, None]
    scale = np.array([0.458, 0.448, 0.450])[:, None, None]
    p = {k: v.double().numpy() for k, v in alex.items()}

    def feats(x):
        x = (x - shift) / scale
        r1 = np.maximum(np_conv(x, p["features.0.weight"], p["features.0.bias"], 4, 2), 0)
        r2 = np.maximum(np_conv(np_maxpool(r1), p["features.3.weight"], p["features.3.bias"], 1, 2), 0)
        r3 = np.maximum(np_conv(np_maxpool(r2), p["features.6.weight"], p["features.6.bias"], 1, 1), 0)
        r4 = np.maximum(np_conv(r3, p["features.8.weight"], p["features.8.bias"], 1, 1), 0)
        r5 = np.maximum(np_conv(r4, p["features.10.weight"], p["features.10.bias"], 1, 1), 0)
        return [r1, r2, r3, r4, r5]

    out = []
    for i, (a, b) in enumerate(zip(feats(x0), feats(x1), strict=True)):
        a = a / (np.sqrt((a**2).sum(0, keepdims=True)) + 1e-10)
        b = b / (np.sqrt((b**2).sum(0, keepdims=True)) + 1e-10)
        w = lin[f"lin{i}.model.1.weight"].double().numpy()[0, :, 0, 0]
        out.append(np.einsum("c,chw->hw", w, (a - b) ** 2))
    return out


def np_bilinear(m, h, w):
    """Half-pixel bilinear resize (align_corners=False), edges clamped."""

    def coords(n_out, n_in):
        s = (np.arange(n_out) + 0.5) * n_in / n_out - 0.5
        s = np.clip(s, 0, None)
        i0 = np.minimum(np.floor(s).astype(int), n_in - 1)
        i1 = np.minimum(i0 + 1, n_in - 1)
        return i0, i1, s - i0

    y0, y1, fy = coords(h, m.shape[0])
    x0, x1, fx = coords(w, m.shape[1])
    top = m[y0][:, x0] * (1 - fx) + m[y0][:, x1] * fx
    bot = m[y1][:, x0] * (1 - fx) + m[y1][:, x1] * fx
    return top * (1 - fy[:, None]) + bot * fy[:, None]


@pytest.fixture(scope="module")
def model_and_weights():
    alex, lin = random_state_dicts(seed=1)
    return LPIPS.from_state_dicts(alex, lin), alex, lin


def test_lpips_matches_numpy_reference(model_and_weights):
    m, alex, lin = model_and_weights
    g = torch.Generator().manual_seed(3)
    x0 = torch.rand(2, 3, 67, 75, generator=g) * 2 - 1
    x1 = (x0 + 0.3 * torch.randn(2, 3, 67, 75, generator=g)).clamp(-1, 1)
    got = m.distance(x0, x1)
    got_map = m.distance_map(x0, x1)
    assert got_map.shape == (2, 67, 75)
    for b in range(2):
        layers = np_lpips_layers(x0[b].double().numpy(), x1[b].double().numpy(), alex, lin)
        ref = sum(layer.mean() for layer in layers)
        assert got[b].item() == pytest.approx(ref, rel=1e-4)
        ref_map = sum(np_bilinear(layer, 67, 75) for layer in layers)
        np.testing.assert_allclose(got_map[b].numpy(), ref_map, rtol=1e-4, atol=1e-6)


def test_lpips_of_identical_images_is_zero_and_symmetric(model_and_weights):
    m, _, _ = model_and_weights
    g = torch.Generator().manual_seed(4)
    x = torch.rand(1, 3, 64, 64, generator=g) * 2 - 1
    y = torch.rand(1, 3, 64, 64, generator=g) * 2 - 1
    assert m.distance(x, x).item() == 0.0
    assert torch.all(m.distance_map(x, x) == 0)
    assert m.distance(x, y).item() == pytest.approx(m.distance(y, x).item(), rel=1e-6)
    assert m.distance(x, y).item() > 0  # non-negative heads, different images
