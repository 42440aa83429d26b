"""Lifting 2D tracks to 3D and filling their gaps, against closed forms, scipy and numpy references."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import map_coordinates
from scipy.spatial.transform import Rotation

from worldtree.motion.lift import fill_gaps, lift_tracks, sample_depth

f64 = torch.float64


def cameras(T: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    Ks = np.zeros((T, 3, 3))
    w2cs = np.zeros((T, 4, 4))
    for t in range(T):
        fx, fy = rng.uniform(200, 400, size=2)
        Ks[t] = [[fx, 0, rng.uniform(20, 40)], [0, fy, rng.uniform(15, 30)], [0, 0, 1]]
        w2cs[t, :3, :3] = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        w2cs[t, :3, 3] = rng.normal(size=3)
        w2cs[t, 3, 3] = 1.0
    return Ks, w2cs


def test_lift_recovers_points_on_fronto_parallel_planes(device):
    """Each frame sees a plane at constant depth z_t: the lifted point is exactly c2w (z_t K^-1 (u, v, 1))."""
    rng = np.random.default_rng(0)
    T, N, H, W = 4, 50, 48, 64
    Ks, w2cs = cameras(T, rng)
    z = rng.uniform(1.0, 5.0, size=T)
    depths = np.broadcast_to(z[:, None, None], (T, H, W)).copy()
    uv = np.stack([rng.uniform(-0.5, W - 0.51, size=(T, N)), rng.uniform(-0.5, H - 0.51, size=(T, N))], -1)
    expect = np.zeros((T, N, 3))
    for t in range(T):
        fx, fy, cx, cy = Ks[t, 0, 0], Ks[t, 1, 1], Ks[t, 0, 2], Ks[t, 1, 2]
        x_cam = np.stack(
            [(uv[t, :, 0] - cx) / fx * z[t], (uv[t, :, 1] - cy) / fy * z[t], np.full(N, z[t])], -1
        )
        c2w = np.linalg.inv(w2cs[t])
        expect[t] = x_cam @ c2w[:3, :3].T + c2w[:3, 3]
    vis = torch.ones(T, N, dtype=torch.bool, device=device)
    pts, valid = lift_tracks(
        torch.tensor(uv, device=device),
        vis,
        torch.tensor(depths, device=device),
        torch.tensor(Ks, device=device),
        torch.tensor(w2cs, device=device),
    )
    assert valid.all()
    np.testing.assert_allclose(pts.cpu().numpy(), expect, atol=1e-9)
    # Reproject: the lifted points land on their pixels at their depth.
    for t in range(T):
        cam = expect[t] @ w2cs[t, :3, :3].T + w2cs[t, :3, 3]
        proj = cam @ Ks[t].T
        np.testing.assert_allclose(proj[:, :2] / proj[:, 2:], uv[t], atol=1e-9)


def test_sample_depth_bilinear_matches_scipy():
    rng = np.random.default_rng(1)
    T, N, H, W = 3, 200, 9, 13
    depth = rng.uniform(1, 2, size=(T, H, W))
    uv = np.stack([rng.uniform(0, W - 1, size=(T, N)), rng.uniform(0, H - 1, size=(T, N))], -1)
    z, ok = sample_depth(torch.tensor(depth), torch.tensor(uv))
    assert ok.all()
    for t in range(T):
        ref = map_coordinates(depth[t], [uv[t, :, 1], uv[t, :, 0]], order=1)
        np.testing.assert_allclose(z[t].numpy(), ref, atol=1e-12)


def test_sample_depth_border_nearest_and_invalid_pixels():
    H, W = 4, 5
    depth = torch.arange(1, H * W + 1, dtype=f64).reshape(1, H, W)
    depth[0, 2, 2] = 0.0  # missing depth
    depth[0, 0, 4] = float("nan")
    uv = torch.tensor(
        [
            [
                [-0.4, -0.4],  # half-pixel border: edge pixel repeated -> depth[0, 0]
                [-0.6, 1.0],  # outside
                [W - 0.5, 1.0],  # outside (area is half-open)
                [2.5, 2.0],  # touches the missing pixel with weight 0.5 -> invalid
                [2.0, 1.0],  # integer position next to the missing pixel: weight 0 there -> valid
                [3.5, 0.0],  # touches the NaN pixel -> invalid
                [1.25, 0.5],  # regular
            ]
        ],
        dtype=f64,
    )
    z, ok = sample_depth(depth, uv)
    assert ok.tolist() == [[True, False, False, False, True, False, True]]
    assert z[0, 0] == depth[0, 0, 0]
    assert z[0, 4] == depth[0, 1, 2]
    expect = 0.5 * (0.75 * depth[0, 0, 1] + 0.25 * depth[0, 0, 2]) + 0.5 * (
        0.75 * depth[0, 1, 1] + 0.25 * depth[0, 1, 2]
    )
    assert torch.isclose(z[0, 6], expect)
    assert torch.all(z[~ok] == 0)
    zn, okn = sample_depth(depth, uv, mode="nearest")
    assert okn.tolist() == [[True, False, False, True, True, False, True]]  # (3.5, 0) -> pixel (0, 4), NaN
    # nearest of (2.5, 2.0) is column 3 (x = j - 0.5 belongs to pixel j), row 2.
    assert zn[0, 3] == depth[0, 2, 3] and zn[0, 6] == depth[0, 1, 1]
    with pytest.raises(ValueError):
        sample_depth(depth, uv, mode="cubic")


def test_lift_marks_invisible_and_bad_depth_invalid():
    T, H, W = 2, 6, 6
    depths = torch.ones(T, H, W, dtype=f64)
    depths[1] = -1.0
    Ks = torch.eye(3, dtype=f64).expand(T, 3, 3)
    w2cs = torch.eye(4, dtype=f64).expand(T, 4, 4)
    tracks = torch.full((T, 3, 2), 2.0, dtype=f64)
    tracks[0, 2] = float("nan")
    vis = torch.tensor([[True, False, True], [True, True, True]])
    pts, valid = lift_tracks(tracks, vis, depths, Ks, w2cs)
    assert valid.tolist() == [[True, False, False], [False, False, False]]
    assert torch.isfinite(pts).all() and torch.all(pts[~valid] == 0)
    np.testing.assert_allclose(pts[0, 0].numpy(), [2.0, 2.0, 1.0])


def test_fill_gaps_matches_numpy_interp():
    rng = np.random.default_rng(2)
    T, N = 20, 40
    pts = rng.normal(size=(T, N, 3))
    valid = rng.uniform(size=(T, N)) < 0.4
    valid[:, 0] = False  # never observed
    valid[:, 1] = True  # always observed
    pts_in = np.where(valid[..., None], pts, np.nan)  # whatever sits in gaps must not leak
    filled, observed = fill_gaps(torch.tensor(pts_in), torch.tensor(valid))
    assert torch.equal(observed, torch.tensor(valid))
    out = filled.numpy()
    assert np.all(out[:, 0] == 0.0)
    for n in range(1, N):
        idx = np.nonzero(valid[:, n])[0]
        for c in range(3):
            ref = np.interp(np.arange(T), idx, pts[idx, n, c])  # np.interp holds the end values
            np.testing.assert_allclose(out[:, n, c], ref, atol=1e-12)


def test_fill_gaps_small_hand_case_and_gradient():
    x = torch.tensor([[0.0], [0.0], [0.0], [3.0], [0.0]], dtype=f64, requires_grad=True)  # [T=5, C=1]
    valid = torch.tensor([False, True, False, True, False])
    pts = torch.cat((x, x), dim=1)[..., None]  # [5, 2, 1]: two identical tracks
    pts = pts * torch.tensor([1.0, 2.0], dtype=f64)[None, :, None]
    filled, _ = fill_gaps(pts, torch.stack((valid, valid), 1))
    np.testing.assert_allclose(filled[:, 0, 0].detach().numpy(), [0.0, 0.0, 1.5, 3.0, 3.0])
    filled[:, 0, 0].sum().backward()
    # filled = (x1, x1, (x1 + x3) / 2, x3, x3): each valid value gets 2.5, gaps get no gradient.
    np.testing.assert_allclose(x.grad[:, 0].numpy(), [0.0, 2.5, 0.0, 2.5, 0.0])
