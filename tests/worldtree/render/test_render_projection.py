"""The C++ projection (hand-written backward) against the PyTorch projection (autograd)."""

from __future__ import annotations

import pytest
import torch

from worldtree.render import cpu_kernel
from worldtree.render.projection import project_gaussians

pytestmark = pytest.mark.skipif(not cpu_kernel.available(), reason="C++ rasterizer did not build here")


def _cloud(dtype, n=400, seed=0):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([2.0, 1.5, 1.5], dtype=dtype)
    means[:, 2] += 2.5  # some behind the camera, many outside the frustum (Jacobian clamp), most in view
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    log_scales = torch.randn(n, 3, generator=g, dtype=dtype) * 0.7 - 2.5
    with torch.no_grad():
        means[0, 1] = float("nan")
        log_scales[1, 0] = 80.0  # covariance overflow (float32) or huge footprint (float64)
        quats[2] = 0.0
    keep = torch.ones(n, dtype=torch.bool)
    keep[3] = False
    K = torch.tensor([[70.0, 0, 39.5], [0, 72.0, 24.5], [0, 0, 1]], dtype=dtype)
    w2c = torch.eye(4, dtype=dtype)
    w2c[:3, :3] = torch.linalg.matrix_exp(
        torch.tensor([[0, -0.1, 0.2], [0.1, 0, -0.05], [-0.2, 0.05, 0]], dtype=dtype)
    )
    w2c[:3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=dtype)
    for t in (means, quats, log_scales, w2c):
        t.requires_grad_(True)
    return means, quats, log_scales, K, w2c, keep


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-9), (torch.float32, 1e-4)])
def test_projection_forward_and_backward_match_torch(dtype, tol):
    means, quats, log_scales, K, w2c, keep = _cloud(dtype)
    args = (K, w2c, 80, 50)
    ref = project_gaussians(means, quats, log_scales, *args, near=0.01, eps2d=0.3, keep=keep)
    m2d, con, z, radii = cpu_kernel.project_cpu(means, quats, log_scales, *args, 0.01, 0.3, keep)
    # Rows 0, 2, 3 are culled (NaN mean, zero quaternion, keep=False). Row 1's covariance overflows float32
    # (culled); in float64 it is a huge thin footprint, drawn at the radius cap by both.
    assert not (radii[[0, 2, 3]] > 0).any()
    if dtype == torch.float32:
        assert radii[1] == 0
    else:
        assert radii[1] == 2**24 and ref.radii[1] == 2**24
    assert (radii > 0).sum() > 100 and (radii == 0).sum() > 30  # both kinds really occur
    assert (radii - ref.radii).abs().max() <= 1 and (radii != ref.radii).float().mean() < 0.01
    same = (radii > 0) & (ref.radii > 0)
    with torch.no_grad():  # some drawn Gaussians lie outside the clamp cone of the Jacobian
        p = means @ w2c[:3, :3].T + w2c[:3, 3]
        xr = p[:, 0] / p[:, 2]
        clamped = (xr > (80 - 0.5 - 39.5) / 70 + 0.3 * 40 / 70) | (xr < -40 / 70 - 0.3 * 40 / 70)
    assert (clamped & same).sum() > 3
    assert torch.allclose(m2d[same], ref.means2d[same], rtol=tol, atol=tol)
    assert torch.allclose(
        con[same], ref.conics[same], rtol=tol, atol=tol * float(con[same].detach().abs().max())
    )
    assert torch.allclose(z, ref.depths, rtol=tol, atol=tol)

    g = torch.Generator().manual_seed(3)
    gm = torch.randn(m2d.shape, generator=g, dtype=dtype) * same[:, None]
    gc = torch.randn(con.shape, generator=g, dtype=dtype) * same[:, None] * 30.0
    gz = torch.randn(z.shape, generator=g, dtype=dtype) * same
    params = (means, quats, log_scales, w2c)
    g_ref = torch.autograd.grad(
        (ref.means2d * gm).sum() + (ref.conics * gc).sum() + (ref.depths * gz).sum(), params
    )
    g_cpp = torch.autograd.grad((m2d * gm).sum() + (con * gc).sum() + (z * gz).sum(), params)
    for name, a, b in zip(("means", "quats", "log_scales", "w2c"), g_cpp, g_ref, strict=True):
        assert torch.isfinite(a).all(), name
        rel = (a - b).norm() / b.norm()
        assert rel < tol, f"{name}: relative error {rel:.2e}"
    for a in g_cpp[:3]:
        assert (a[[0, 2, 3]] == 0).all()  # culled rows: exactly zero


def _conic_mp(mean, quat, log_scale, K, eps2d, dps=80):
    """The conic of one Gaussian (camera = world frame, mean in view) in mpmath at ``dps`` digits: a reference
    free of float rounding, from the textbook a c - b^2."""
    import mpmath as mp

    mp.mp.dps = dps
    x, y, z = (mp.mpf(float(v)) for v in mean)
    w, qx, qy, qz = (mp.mpf(float(v)) for v in quat)
    n = mp.sqrt(w * w + qx * qx + qy * qy + qz * qz)
    w, qx, qy, qz = w / n, qx / n, qy / n, qz / n
    Rq = mp.matrix([
        [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy)],
        [2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx)],
        [2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)],
    ])  # fmt: skip
    S = mp.diag([mp.exp(mp.mpf(float(v))) for v in log_scale])
    fx, fy = mp.mpf(float(K[0, 0])), mp.mpf(float(K[1, 1]))
    J = mp.matrix([[fx / z, 0, -fx * x / z**2], [0, fy / z, -fy * y / z**2]])
    A = J * Rq * S
    cov = A * A.T
    a, b, c = cov[0, 0] + eps2d, cov[0, 1], cov[1, 1] + eps2d
    det = a * c - b * b
    return [float(c / det), float(-b / det), float(a / det)]


@pytest.mark.parametrize("log_scale", [(20.0, -3.0, -3.0), (80.0, -2.0, -3.0), (12.0, -8.0, 1.0)])
def test_thin_huge_footprints_get_the_exact_conic(log_scale):
    """a c - b^2 cancels to rounding noise (of either sign, machine-dependent) for long thin Gaussians; both
    projections compute the determinant without the cancellation and match an 80-digit reference."""
    dtype = torch.float64
    means = torch.tensor([[0.3, -0.2, 3.0]], dtype=dtype)
    quats = torch.tensor([[0.9, 0.2, -0.3, 0.1]], dtype=dtype)
    log_scales = torch.tensor([log_scale], dtype=dtype)
    K = torch.tensor([[70.0, 0, 39.5], [0, 72.0, 24.5], [0, 0, 1]], dtype=dtype)
    w2c = torch.eye(4, dtype=dtype)
    want = torch.tensor(_conic_mp(means[0], quats[0], log_scales[0], K, 0.3), dtype=dtype)
    ref = project_gaussians(means, quats, log_scales, K, w2c, 80, 50, near=0.01, eps2d=0.3)
    _, con, _, radii = cpu_kernel.project_cpu(
        means, quats, log_scales, K, w2c, 80, 50, 0.01, 0.3, torch.ones(1, dtype=torch.bool)
    )
    assert ref.radii[0] > 0 and radii[0] > 0
    for got in (ref.conics[0], con[0]):
        assert torch.allclose(got, want, rtol=1e-9, atol=1e-12 * float(want.abs().max()))
