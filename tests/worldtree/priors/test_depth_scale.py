"""Imported depth in other units is put in the cameras' units (two-view triangulation of the flow)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from worldtree.priors import DepthConfig, PriorsConfig, compute_priors
from worldtree.priors.depth_scale import fit_depth_scale, triangulate_along_ray
from worldtree.priors.flow import FlowPair

FAST = PriorsConfig(depth=DepthConfig(num_planes=32))


def _camera(centre, yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ np.asarray(centre, float)
    return w2c


def _project(K, w2c, X):
    cam = X @ w2c[:3, :3].T + w2c[:3, 3]
    return cam[:, :2] / cam[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2], cam[:, 2]


def test_triangulation_is_exact_and_its_parallax_matches_finite_differences():
    rng = np.random.default_rng(0)
    K = np.array([[120.0, 0, 80], [0, 130.0, 45], [0, 0, 1]])
    wi, wj = _camera([0, 0, 0], 0.05), _camera([0.3, 0.05, 0.1], -0.1)
    X = np.stack([rng.uniform(-1, 1, 200), rng.uniform(-0.5, 0.5, 200), rng.uniform(2, 6, 200)], -1)
    pi, zi = _project(K, wi, X)
    pj, _ = _project(K, wj, X)
    z, res, par = triangulate_along_ray(pi, pj, K, wi, K, wj)
    np.testing.assert_allclose(z, zi, rtol=1e-9)
    assert res.max() < 1e-6
    # Parallax: pixels moved in frame j per unit of log depth, against a central difference.
    ray = np.linalg.solve(K, np.concatenate([pi, np.ones((200, 1))], 1).T).T  # camera-i rays, z = 1
    h = 1e-5

    def at(scale):
        cam_i = ray * (zi * scale)[:, None]
        Xw = (cam_i - wi[:3, 3]) @ wi[:3, :3]
        return _project(K, wj, Xw)[0]

    fd = np.linalg.norm(at(np.exp(h)) - at(np.exp(-h)), axis=1) / (2 * h)
    np.testing.assert_allclose(par, fd, rtol=1e-5)
    # No baseline: nothing to triangulate, zero parallax.
    _, _, par0 = triangulate_along_ray(pi, pi, K, wi, K, wi)
    assert np.all(par0 == 0)


def test_scale_of_exact_matches_is_recovered_and_moving_points_are_outvoted():
    rng = np.random.default_rng(1)
    H, W = 40, 60
    K = np.array([[70.0, 0, 29.5], [0, 70.0, 19.5], [0, 0, 1]])
    w2cs = np.stack([_camera([0.0, 0, 0], 0.0), _camera([0.25, 0.02, 0], -0.04)])
    Ks = np.stack([K, K])
    depth0 = rng.uniform(2.0, 5.0, (H, W))
    ys, xs = np.mgrid[0:H, 0:W]
    pts = np.stack([xs.ravel(), ys.ravel()], -1).astype(np.float64)
    ray = np.linalg.solve(K, np.concatenate([pts, np.ones((H * W, 1))], 1).T).T
    Xw = (ray * depth0.reshape(-1, 1) - w2cs[0][:3, 3]) @ w2cs[0][:3, :3]
    pj, _ = _project(K, w2cs[1], Xw)
    flow = (pj - pts).reshape(H, W, 2)
    flow[:10, :15] += [4.0, -3.0]  # a moving patch: its matches leave the epipolar lines
    flows = {(0, 1): FlowPair(flow.astype(np.float32), np.ones((H, W), bool))}
    depth = np.stack([depth0, depth0]) * 3.7  # the same depth in other units
    fit = fit_depth_scale(depth, flows, Ks, w2cs, stride=1)
    assert fit.observable and fit.matches > 0.8 * H * W
    assert fit.scale == pytest.approx(1 / 3.7, rel=1e-3)
    # A camera that only rotates measures no depth: the scale stays 1 and says so.
    rot = np.stack([w2cs[0], _camera([0.0, 0, 0], 0.05)])
    none = fit_depth_scale(depth, flows, Ks, rot, stride=1)
    assert not none.observable and none.scale == 1.0


def test_imported_exact_depth_in_other_units_beats_classical_depth(planar, tmp_path):
    """The generated scene's exact depth, written in other units (x2.5), is brought back to the cameras'
    scale: its error is then below the classical (plane-sweep) depth's; taken as it is, it is 150 % off."""
    sc, fr = planar
    scene = sc.to_scene(fr)
    exact = fr["depth"]
    ddir = tmp_path / "depth"
    ddir.mkdir()
    for t in range(len(exact)):
        np.save(ddir / f"{t:05d}.npy", (exact[t] * 2.5).astype(np.float32))
    static = ~fr["mask"]

    def rel_err(d):
        return float(np.mean(np.abs(d - exact)[static] / exact[static]))

    classical = compute_priors(scene, FAST, None)
    cfg = dataclasses.replace(FAST, depth_source=str(ddir))
    got = compute_priors(scene, cfg, None)
    assert "to the cameras" in got.sources["depth"]
    assert rel_err(got.depth) < 0.02
    assert rel_err(got.depth) < rel_err(classical.depth)
    # Scaled, the import counts as metric depth: the depth-consistency cue joins the motion cues.
    assert "rigid" in got.sources["masks"]
    off = compute_priors(
        scene,
        dataclasses.replace(cfg, depth_import=dataclasses.replace(cfg.depth_import, fit_global_scale=False)),
        None,
    )
    assert rel_err(off.depth) == pytest.approx(1.5, rel=1e-3)
