"""GaussianSet: activations, initialisation, persistence, PLY export."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from worldtree.gaussians import SH_C0, GaussianSet, knn_rms_distance, quat_to_rotmat, read_ply_vertices
from worldtree.infra.errors import UserError


def _random_set(n: int = 50, seed: int = 0) -> GaussianSet:
    g = torch.Generator().manual_seed(seed)
    return GaussianSet(
        {
            "means": torch.randn(n, 3, generator=g),
            "quats": torch.randn(n, 4, generator=g),
            "log_scales": torch.randn(n, 3, generator=g) - 2,
            "opacity_logits": torch.randn(n, generator=g) * 3,
            "sh0": torch.randn(n, 3, generator=g),
        }
    )


def test_activations_match_closed_forms():
    gs = _random_set()
    p = {k: v.detach() for k, v in gs.params.items()}
    q = p["quats"].numpy()
    np.testing.assert_allclose(
        gs.quats.detach().numpy(), q / np.linalg.norm(q, axis=1, keepdims=True), rtol=1e-6
    )
    np.testing.assert_allclose(gs.scales.detach().numpy(), np.exp(p["log_scales"].numpy()), rtol=1e-6)
    np.testing.assert_allclose(
        gs.opacities.detach().numpy(), 1 / (1 + np.exp(-p["opacity_logits"].numpy())), rtol=1e-6
    )
    expect = np.maximum(0.28209479177387814 * p["sh0"].numpy() + 0.5, 0.0)
    np.testing.assert_allclose(gs.colors.detach().numpy(), expect, rtol=1e-6, atol=1e-7)
    assert math.isclose(SH_C0, 1 / (2 * math.sqrt(math.pi)), rel_tol=1e-12)
    assert len(gs) == 50


def test_from_tensors_inverts_the_activations():
    n = 20
    means = torch.rand(n, 3)
    scales = torch.rand(n, 3) * 0.1 + 1e-3
    opac = torch.rand(n) * 0.98 + 0.01
    cols = torch.rand(n, 3)
    gs = GaussianSet.from_tensors(means, scales, opac, cols)
    torch.testing.assert_close(gs.scales.detach(), scales, rtol=1e-5, atol=0)
    torch.testing.assert_close(gs.opacities.detach(), opac, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(gs.colors.detach(), cols, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(gs.quats.detach(), torch.tensor([1.0, 0, 0, 0]).expand(n, 4))


def test_zero_quaternion_and_extreme_logits_stay_finite():
    gs = _random_set(4)
    with torch.no_grad():
        gs.params["quats"][0] = 0
    assert torch.isfinite(gs.quats).all()
    gs2 = GaussianSet.from_tensors(
        torch.zeros(2, 3), torch.ones(2, 3), torch.tensor([0.0, 1.0]), torch.zeros(2, 3)
    )
    assert torch.isfinite(gs2.params["opacity_logits"]).all()


def test_knn_scale_matches_brute_force():
    rng = np.random.default_rng(1)
    pts = rng.random((60, 3))
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    expect = np.sqrt((np.sort(d, axis=1)[:, :3] ** 2).mean(axis=1))
    np.testing.assert_allclose(knn_rms_distance(pts, 3), expect, rtol=1e-10)
    gs = GaussianSet.from_points(torch.from_numpy(pts).float())
    np.testing.assert_allclose(gs.scales.detach().numpy(), np.repeat(expect[:, None], 3, 1), rtol=1e-5)
    # Duplicates and single points still give finite, positive sizes.
    assert np.all(knn_rms_distance(np.zeros((3, 3))) > 0)
    assert knn_rms_distance(np.zeros((1, 3)))[0] > 0


def test_from_points_rejects_bad_input():
    with pytest.raises(UserError):
        GaussianSet.from_points(torch.zeros(0, 3))
    with pytest.raises(UserError):
        GaussianSet.from_points(torch.tensor([[0.0, float("nan"), 1.0]]))


def test_random_points_lie_in_a_training_frustum():
    W, H, near, far = 40, 30, 0.5, 4.0
    K = torch.tensor([[30.0, 0, 19.5], [0, 30.0, 14.5], [0, 0, 1]])
    rot = Rotation.from_euler("y", [[0.0], [20.0]], degrees=True).as_matrix()
    w2cs = torch.eye(4).repeat(2, 1, 1)
    w2cs[:, :3, :3] = torch.from_numpy(rot).float()
    w2cs[:, :3, 3] = torch.tensor([[0.0, 0, 0], [0.3, 0.1, 0]])
    Ks = K.expand(2, 3, 3)
    imgs = torch.rand(2, H, W, 3)
    gs = GaussianSet.random_in_frustums(
        500, Ks, w2cs, W, H, near, far, images=imgs, generator=torch.Generator().manual_seed(0)
    )
    x = gs.means.detach().double()
    inside_any = torch.zeros(500, dtype=torch.bool)
    for i in range(2):
        cam = x @ w2cs[i, :3, :3].double().T + w2cs[i, :3, 3].double()
        z = cam[:, 2]
        u = K[0, 0] * cam[:, 0] / z + K[0, 2] + 0.5
        v = K[1, 1] * cam[:, 1] / z + K[1, 2] + 0.5
        ok = (
            (z > near - 1e-4) & (z < far + 1e-4) & (u > -1e-3) & (u < W + 1e-3) & (v > -1e-3) & (v < H + 1e-3)
        )
        inside_any |= ok
    assert inside_any.all()
    # Colours come from the images, so they are within the images' range and not the grey default.
    assert (gs.colors.detach() - 0.5).abs().max() > 0.3


def test_save_load_and_ply_roundtrip(tmp_path):
    gs = _random_set(30)
    gs.save(tmp_path / "g.pt")
    back = GaussianSet.load(tmp_path / "g.pt")
    for k in gs.params:
        assert torch.equal(back.params[k], gs.params[k].detach())
    gs.write_ply(tmp_path / "g.ply")
    v = read_ply_vertices(tmp_path / "g.ply")
    np.testing.assert_array_equal(v["x"], gs.params["means"][:, 0].detach().numpy())
    np.testing.assert_array_equal(v["opacity"], gs.params["opacity_logits"].detach().numpy())
    np.testing.assert_array_equal(v["rot_0"], gs.params["quats"][:, 0].detach().numpy())
    np.testing.assert_array_equal(v["f_dc_2"], gs.params["sh0"][:, 2].detach().numpy())
    with pytest.raises(UserError):
        GaussianSet.load(tmp_path / "missing.pt")
    (tmp_path / "bad.pt").write_bytes(b"garbage")
    with pytest.raises(UserError):
        GaussianSet.load(tmp_path / "bad.pt")


def test_quat_to_rotmat_matches_scipy():
    q = torch.randn(20, 4, dtype=torch.float64)
    R = quat_to_rotmat(q).numpy()
    qn = q.numpy()
    expect = Rotation.from_quat(qn[:, [1, 2, 3, 0]]).as_matrix()  # scipy is (x, y, z, w)
    np.testing.assert_allclose(R, expect, atol=1e-12)


def test_sh_basis_is_orthonormal_on_the_sphere():
    from worldtree.gaussians import sh_basis

    # Gauss-Legendre in cos(theta) x uniform phi integrates these degree <= 6 products exactly.
    mu, w_mu = np.polynomial.legendre.leggauss(12)
    phi = np.arange(24) * 2 * np.pi / 24
    m, p = np.meshgrid(mu, phi, indexing="ij")
    s = np.sqrt(1 - m**2)
    dirs = torch.from_numpy(np.stack([s * np.cos(p), s * np.sin(p), m], -1).reshape(-1, 3))
    weights = torch.from_numpy((w_mu[:, None] * np.full(24, 2 * np.pi / 24)[None]).reshape(-1))
    Y = sh_basis(dirs, 3)  # [M, 16]
    gram = (Y * weights[:, None]).T @ Y
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=1e-12, rtol=0)
    # Degree 1 is the 3DGS convention: (-C1 y, C1 z, -C1 x).
    d = torch.tensor([[0.6, 0.0, 0.8]], dtype=torch.float64)
    torch.testing.assert_close(
        sh_basis(d, 1)[0, 1:], torch.tensor([0.0, 0.8, -0.6], dtype=torch.float64) * 0.4886025119029199
    )


def test_view_colors_and_ply_with_sh(tmp_path):
    gs = _random_set(10)
    assert gs.sh_degree == 0
    torch.testing.assert_close(gs.view_colors(torch.zeros(3)), gs.colors)
    gs.add_sh(2)
    assert gs.sh_degree == 2 and gs.params["shN"].shape == (10, 8, 3)
    torch.testing.assert_close(gs.view_colors(torch.zeros(3)), gs.colors)  # zero coefficients
    with torch.no_grad():
        gs.params["shN"][:, 2, 0] = 1.0  # the (-C1 x) basis function, red channel
    cam = torch.tensor([5.0, 0.0, 0.0])
    d = gs.means.detach() - cam
    d = d / d.norm(dim=-1, keepdim=True)
    expect = (
        0.28209479177387814 * gs.params["sh0"].detach()[:, 0] + 0.5 - 0.4886025119029199 * d[:, 0]
    ).clamp_min(0)
    torch.testing.assert_close(gs.view_colors(cam)[:, 0].detach(), expect)
    torch.testing.assert_close(gs.view_colors(cam, degree=0), gs.colors)
    gs.view_colors(cam).sum().backward()
    assert gs.params["shN"].grad is not None and gs.params["shN"].grad.abs().sum() > 0
    gs.write_ply(tmp_path / "sh.ply")
    v = read_ply_vertices(tmp_path / "sh.ply")
    # Channel-major f_rest: 8 red coefficients, then 8 green, then 8 blue.
    np.testing.assert_array_equal(v["f_rest_2"], np.ones(10, np.float32))
    assert "f_rest_23" in v and "f_rest_24" not in v
    np.testing.assert_array_equal(v["f_rest_10"], gs.params["shN"][:, 2, 1].detach().numpy())
