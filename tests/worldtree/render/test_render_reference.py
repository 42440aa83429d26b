"""The PyTorch reference rasterizer against an independent brute-force per-pixel oracle (no tiles)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.utils.checkpoint
from scipy.spatial.transform import Rotation

from worldtree.render import rasterize


def _oracle(p, width, height, near=0.01, eps2d=0.3):
    """Loop over every pixel and every Gaussian in float64 numpy, compositing sequentially.

    Independent of the package's code: rotation from scipy, covariance as J W S W^T J^T, and the tile rule
    spelled per pixel (a Gaussian reaches pixel (i, j) iff the pixel's 16x16 tile meets its bounding square).
    """
    g = {k: v.detach().numpy().astype(np.float64) for k, v in p.items()}
    K, w2c = g["K"], g["w2c"]
    W, t = w2c[:3, :3], w2c[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    gauss = []
    for m, q, ls, o, c in zip(
        g["means"], g["quats"], g["log_scales"], g["opacities"], g["colors"], strict=True
    ):
        x, y, z = W @ m + t
        if z <= near:
            continue
        Rq = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()  # scipy is scalar-last
        S = Rq @ np.diag(np.exp(2 * ls)) @ Rq.T
        # The Jacobian is taken at the direction clamped to 1.3x the half field of view (3DGS rule).
        mx = 0.3 * width / (2 * fx)
        my = 0.3 * height / (2 * fy)
        xc = z * np.clip(x / z, -(cx + 0.5) / fx - mx, (width - 0.5 - cx) / fx + mx)
        yc = z * np.clip(y / z, -(cy + 0.5) / fy - my, (height - 0.5 - cy) / fy + my)
        J = np.array([[fx / z, 0, -fx * xc / z**2], [0, fy / z, -fy * yc / z**2]])
        cov = J @ W @ S @ W.T @ J.T + eps2d * np.eye(2)
        det = np.linalg.det(cov)
        mid = 0.5 * np.trace(cov)
        r = math.ceil(3 * math.sqrt(mid + math.sqrt(max(0.1, mid * mid - det))))
        u, v = fx * x / z + cx, fy * y / z + cy
        tiles_x = range(max(0, math.floor((u + 0.5 - r) / 16)), math.ceil((u + 0.5 + r) / 16))
        tiles_y = range(max(0, math.floor((v + 0.5 - r) / 16)), math.ceil((v + 0.5 + r) / 16))
        gauss.append((z, np.array([u, v]), np.linalg.inv(cov), o, c, tiles_x, tiles_y))
    gauss.sort(key=lambda e: e[0])
    rgb = np.zeros((height, width, 3))
    alpha = np.zeros((height, width))
    depth = np.zeros((height, width))
    for i in range(height):
        for j in range(width):
            T, C, D = 1.0, np.zeros(3), 0.0
            for z, mu, conic, o, c, tx, ty in gauss:
                if j // 16 not in tx or i // 16 not in ty:
                    continue
                d = np.array([j, i]) - mu
                power = -0.5 * d @ conic @ d
                a = min(0.99, o * math.exp(power))
                if power > 0 or a < 1 / 255:
                    continue
                if T * (1 - a) < 1e-4:
                    break
                C += a * T * c
                D += a * T * z
                T *= 1 - a
            rgb[i, j] = C + T * g["background"]
            alpha[i, j] = 1 - T
            depth[i, j] = D
    return rgb, alpha, depth


@pytest.mark.parametrize(
    "seed,size,log_scale",
    [(0, (40, 35), -2.0), (1, (23, 37), -1.5), (2, (33, 17), -2.5), (4, (50, 20), -1.0)],
)
def test_reference_matches_bruteforce(make_scene, seed, size, log_scale):
    p, w, h = make_scene(n=25, width=size[0], height=size[1], seed=seed, log_scale=log_scale)
    out = rasterize(width=w, height=h, backend="reference", **p)
    rgb, alpha, depth = _oracle(p, w, h)
    assert out.rgb.shape == (h, w, 3)
    assert out.alpha.mean() > 0.1  # the scene really covers the image
    np.testing.assert_allclose(out.rgb.detach().numpy(), rgb, atol=1e-9)
    np.testing.assert_allclose(out.alpha.detach().numpy(), alpha, atol=1e-9)
    np.testing.assert_allclose(out.depth.detach().numpy(), depth, atol=1e-8)


def test_reference_float32_close_to_oracle(make_scene):
    p, w, h = make_scene(n=25, seed=3, dtype=torch.float32)
    out = rasterize(width=w, height=h, backend="reference", **p)
    rgb, _, depth = _oracle(p, w, h)
    np.testing.assert_allclose(out.rgb.detach().numpy(), rgb, atol=2e-5)
    np.testing.assert_allclose(out.depth.detach().numpy(), depth, atol=1e-4)


def test_saturation_stops_compositing():
    """Many opaque layers: T must stop just above 1e-4 and the front colour dominate."""
    n = 40
    dt = torch.float64
    means = torch.zeros(n, 3, dtype=dt)
    means[:, 2] = torch.linspace(2.0, 3.0, n, dtype=dt)
    colors = torch.zeros(n, 3, dtype=dt)
    colors[0] = torch.tensor([1.0, 0, 0], dtype=dt)
    K = torch.tensor([[20.0, 0, 4.0], [0, 20.0, 4.0], [0, 0, 1]], dtype=dt)
    out = rasterize(
        means,
        torch.tensor([[1.0, 0, 0, 0]], dtype=dt).repeat(n, 1),
        torch.full((n, 3), 0.0, dtype=dt),
        torch.full((n,), 0.95, dtype=dt),
        colors,
        K,
        torch.eye(4, dtype=dt),
        9,
        9,
        backend="reference",
    )
    # At the centre pixel every layer has alpha 0.95: T = 0.05^3 = 1.25e-4 after three layers; a fourth would
    # leave 6.25e-6 < 1e-4, so compositing stops there.
    assert float(1 - out.alpha[4, 4]) == pytest.approx(0.05**3, rel=1e-9)
    assert float(out.rgb[4, 4, 0]) == pytest.approx(0.95, rel=1e-9)
    assert float(out.depth[4, 4]) == pytest.approx(sum(0.95 * 0.05**k * float(means[k, 2]) for k in range(3)))


def test_recomputed_chunks_give_the_same_gradients(make_scene, monkeypatch):
    """Large frames recompute chunks in backward (checkpointing); forcing it must not change anything."""
    from worldtree.render import reference

    p, w, h = make_scene(n=60, width=50, height=40, seed=11)
    keys = ("means", "quats", "log_scales", "opacities", "colors", "w2c", "background")
    grads = []
    calls = []

    def counting_checkpoint(fn, *args, **kw):
        calls.append(1)
        return torch.utils.checkpoint.checkpoint(fn, *args, **kw)

    monkeypatch.setattr(reference, "checkpoint", counting_checkpoint)
    for limit in (reference.CHECKPOINT_ELEMENTS, 0):
        monkeypatch.setattr(reference, "CHECKPOINT_ELEMENTS", limit)
        monkeypatch.setattr(reference, "CHUNK_ELEMENTS", 256 * 64)  # several chunks
        for k in keys:
            p[k].grad = None
        out = rasterize(width=w, height=h, backend="reference", **p)
        (out.rgb.sum() + out.depth.sum()).backward()
        grads.append([p[k].grad.clone() for k in keys])
    assert len(calls) > 1  # only the second render recomputed, in several chunks
    for a, b in zip(*grads, strict=True):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12)
