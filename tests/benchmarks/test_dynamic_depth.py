"""The moving objects' depth against exact depth: known answers by construction."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from benchmarks.speed.dynamic_depth import frame_depth_errors, summarise

K = torch.tensor([[50.0, 0.0, 19.5], [0.0, 50.0, 14.5], [0.0, 0.0, 1.0]])


def _points_on_rays(depth_of_pixel, pixels, factor, scale, w2c):
    """World points (model units) seen at ``pixels`` at ``factor`` times the exact depth, for camera ``w2c``."""
    out = []
    R, t = w2c[:3, :3].double(), w2c[:3, 3].double()
    for u, v in pixels:
        z = depth_of_pixel[v, u] * factor * scale
        cam = torch.tensor([(u - 19.5) / 50.0 * z, (v - 14.5) / 50.0 * z, z], dtype=torch.float64)
        out.append(R.T @ (cam - t))
    return torch.stack(out).float()


@pytest.mark.parametrize("factor", [1.0, 1.5, 0.6])
def test_gaussians_at_a_known_factor_of_the_exact_depth(factor):
    H, W = 30, 40
    depth = np.full((H, W), 4.0, dtype=np.float32)
    depth[10:20, 10:20] = 2.0
    mask = np.zeros((H, W), dtype=bool)
    mask[10:20, 10:20] = True
    ang = 0.3
    w2c = torch.eye(4)
    w2c[:3, :3] = torch.tensor([[math.cos(ang), 0, math.sin(ang)], [0, 1, 0], [-math.sin(ang), 0, math.cos(ang)]])
    w2c[:3, 3] = torch.tensor([0.2, -0.1, 0.5])
    scale = 2.5  # model units per scene unit
    inside = [(u, v) for u in range(10, 20, 3) for v in range(10, 20, 3)]
    outside = [(2, 2), (35, 25)]  # on the static background: not compared
    pts = _points_on_rays(depth, inside + outside, factor, scale, w2c)
    behind = (w2c[:3, :3].T @ (torch.tensor([0.0, 0.0, -1.0]) - w2c[:3, 3]))[None]  # behind: ignored
    r = frame_depth_errors(torch.cat([pts, behind]), w2c, K, scale, depth, mask)
    assert r["n"] == len(inside)
    assert r["bias"] == pytest.approx(math.log(factor), abs=1e-5)
    assert r["error"] == pytest.approx(abs(math.log(factor)), abs=1e-5)
    assert r["inside"] == pytest.approx(len(inside) / (len(inside) + len(outside)))


def test_nothing_inside_and_the_summary_skip_empty_frames():
    depth = np.ones((8, 8), dtype=np.float32)
    r = frame_depth_errors(torch.zeros(0, 3), torch.eye(4), K, 1.0, depth, np.zeros((8, 8), dtype=bool))
    assert r["n"] == 0 and math.isnan(r["bias"]) and math.isnan(r["error"])
    s = summarise([{"bias": 0.2, "error": 0.3, "n": 5}, r, {"bias": 0.4, "error": 0.1, "n": 2}])
    assert s["frames_used"] == 2 and s["bias"] == pytest.approx(0.3) and s["error"] == pytest.approx(0.2)
    assert summarise([r])["frames_used"] == 0
