"""Edge cases: culling, degenerate inputs, odd image sizes. Output and gradients must stay finite."""

from __future__ import annotations

import math

import pytest
import torch

from worldtree.infra.errors import UserError
from worldtree.render import cpu_kernel, rasterize

BACKENDS = [
    "reference",
    pytest.param("cpu", marks=pytest.mark.skipif(not cpu_kernel.available(), reason="no build")),
]
KEYS = ("means", "quats", "log_scales", "opacities", "colors", "w2c", "background")


def _run(p, w, h, backend):
    for k in KEYS:
        if p[k].grad is not None:
            p[k].grad = None
    out = rasterize(width=w, height=h, backend=backend, **p)
    (out.rgb.sum() + out.alpha.sum() + out.depth.sum()).backward()
    for name, t in (("rgb", out.rgb), ("alpha", out.alpha), ("depth", out.depth)):
        assert torch.isfinite(t).all(), name
    for k in KEYS:
        assert p[k].grad is not None and torch.isfinite(p[k].grad).all(), k
    return out


def _single(mean, log_scale=-2.0, opacity=0.8, dtype=torch.float32, width=32, height=32, f=30.0):
    """One isotropic Gaussian; camera at the origin looking down +z, principal point (cx, cy) at (15.5, 15.5)."""
    p = dict(
        means=torch.tensor([mean], dtype=dtype),
        quats=torch.tensor([[1.0, 0, 0, 0]], dtype=dtype),
        log_scales=torch.full((1, 3), float(log_scale), dtype=dtype),
        opacities=torch.tensor([opacity], dtype=dtype),
        colors=torch.tensor([[0.9, 0.4, 0.1]], dtype=dtype),
        K=torch.tensor([[f, 0, 15.5], [0, f, 15.5], [0, 0, 1]], dtype=dtype),
        w2c=torch.eye(4, dtype=dtype),
        background=torch.tensor([0.1, 0.2, 0.3], dtype=dtype),
    )
    for k in KEYS:
        p[k].requires_grad_(True)
    return p, width, height


@pytest.mark.parametrize("backend", BACKENDS)
def test_gaussian_on_tile_corner_is_symmetric(backend):
    """Centred exactly where four tiles meet: the image must be point-symmetric across the tile borders."""
    p, w, h = _single([0.0, 0.0, 3.0], log_scale=-1.5, dtype=torch.float64)
    out = _run(p, w, h, backend)
    assert int(out.radii[0]) > 4  # really spans the four tiles around (15.5, 15.5)
    a = out.alpha
    assert a[15, 15] > 0.5
    assert torch.allclose(a, a.flip(0).flip(1), atol=1e-12)
    assert torch.allclose(a, a.T, atol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_behind_camera_and_near_plane_are_culled(make_scene, backend):
    p, w, h = make_scene(n=20, dtype=torch.float32, seed=3)
    with torch.no_grad():
        p["means"][0] = torch.tensor([0.0, 0.0, -2.0])  # behind (world and camera frames nearly agree)
        p["means"][1] = torch.tensor([0.0, 0.0, -0.1])  # also behind, after the small w2c translation
    out = _run(p, w, h, backend)
    assert not out.visible[:2].any() and (out.radii[:2] == 0).all()
    for k in ("means", "quats", "log_scales", "opacities", "colors"):
        assert (p[k].grad[:2] == 0).all(), k
    assert out.visible[2:].sum() > 10


@pytest.mark.parametrize("backend", BACKENDS)
def test_non_finite_parameters_are_culled(make_scene, backend):
    p, w, h = make_scene(n=20, dtype=torch.float32, seed=4)
    ref = rasterize(
        width=w,
        height=h,
        backend=backend,
        **{k: v.detach()[3:] if v.dim() and v.shape[0] == 20 else v.detach() for k, v in p.items()},
    )
    with torch.no_grad():
        p["means"][0, 0] = float("nan")
        p["log_scales"][1, 2] = float("inf")
        p["quats"][2] = 0.0  # zero-norm quaternion: no rotation defined
    out = _run(p, w, h, backend)
    assert not out.visible[:3].any()
    for k in ("means", "quats", "log_scales", "opacities", "colors"):
        assert (p[k].grad[:3] == 0).all(), k
    assert torch.allclose(out.rgb, ref.rgb, atol=1e-6)  # the culled three changed nothing


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("log_scale", [12.0, 60.0, -30.0])
def test_huge_and_tiny_scales(backend, log_scale):
    p, w, h = _single([0.1, -0.05, 2.0], log_scale=log_scale)
    out = _run(p, w, h, backend)
    if log_scale == -30.0:
        # Smaller than a pixel: the 0.3 px^2 dilation alone sets its footprint; 3DGS's eigenvalue floor adds
        # sqrt(0.1): radius = ceil(3 sqrt(0.3 + sqrt(0.1))) = 3.
        assert int(out.radii[0]) == 3 and out.alpha.max() > 0.5
    elif log_scale == 60.0:
        assert not out.visible[0]  # covariance overflows float32: dropped, not NaN
    else:
        assert out.visible[0]


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_opacity_changes_nothing(make_scene, backend):
    p, w, h = make_scene(n=15, dtype=torch.float32, seed=6)
    base = rasterize(width=w, height=h, backend=backend, **{k: v.detach() for k, v in p.items()})
    with torch.no_grad():
        p["means"][0] = torch.tensor([0.0, 0.0, 2.5])
        p["opacities"][0] = 0.0
    out = _run(p, w, h, backend)
    p2 = {k: (v.detach()[1:] if v.dim() and v.shape[0] == 15 else v.detach()) for k, v in p.items()}
    without = rasterize(width=w, height=h, backend=backend, **p2)
    assert torch.allclose(out.rgb, without.rgb, atol=1e-7)
    assert not torch.allclose(base.rgb, out.rgb)  # moving Gaussian 0 did matter while it was opaque


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("size", [(1, 1), (37, 23), (16, 1), (1, 40)])
def test_odd_image_sizes(make_scene, backend, size):
    w, h = size
    p, _, _ = make_scene(n=40, width=40, height=35, dtype=torch.float32, seed=8, log_scale=-1.5)
    with torch.no_grad():
        p["K"][0, 2] = (w - 1) / 2
        p["K"][1, 2] = (h - 1) / 2
    out = _run(p, w, h, backend)
    assert out.rgb.shape == (h, w, 3) and out.alpha.shape == (h, w) and out.depth.shape == (h, w)
    assert out.alpha.max() > 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_no_gaussians(backend):
    dt = torch.float32
    p = dict(
        means=torch.zeros(0, 3, dtype=dt, requires_grad=True),
        quats=torch.zeros(0, 4, dtype=dt, requires_grad=True),
        log_scales=torch.zeros(0, 3, dtype=dt, requires_grad=True),
        opacities=torch.zeros(0, dtype=dt, requires_grad=True),
        colors=torch.zeros(0, 3, dtype=dt, requires_grad=True),
        K=torch.tensor([[10.0, 0, 5], [0, 10, 4], [0, 0, 1]]),
        w2c=torch.eye(4, requires_grad=True),
        background=torch.tensor([0.3, 0.6, 0.9], requires_grad=True),
    )
    out = _run(p, 11, 9, backend)
    assert torch.allclose(out.rgb, torch.tensor([0.3, 0.6, 0.9]).expand(9, 11, 3))
    assert (out.alpha == 0).all() and (out.depth == 0).all()
    assert out.means2d.shape == (0, 2) and out.radii.shape == (0,)
    assert torch.allclose(p["background"].grad, torch.full((3,), 99.0))  # d sum(rgb) / d bg = H W


def test_bad_arguments_raise():
    p, w, h = _single([0.0, 0.0, 2.0])
    with pytest.raises(UserError, match="unknown"):
        rasterize(width=w, height=h, backend="vulkan", **p)
    with pytest.raises(ValueError, match="quats"):
        rasterize(width=w, height=h, **{**p, "quats": p["quats"][:, :3]})
    with pytest.raises(ValueError, match="one dtype"):
        rasterize(width=w, height=h, **{**p, "colors": p["colors"].double()})
    with pytest.raises(ValueError, match="width"):
        rasterize(width=0, height=h, **p)
    if not torch.cuda.is_available():
        with pytest.raises(UserError, match="gsplat"):
            rasterize(width=w, height=h, backend="gsplat", **p)


def test_auto_falls_back_to_reference_when_the_build_fails(monkeypatch, caplog, tmp_path):
    """A real failed build (a source that does not compile): one warning, then the reference, logged once."""
    from worldtree.render import backends, kernel_build

    broken = tmp_path / "broken.cpp"
    broken.write_text("#error simulated build failure\n")
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    monkeypatch.setattr(kernel_build, "SOURCE", broken)
    monkeypatch.setattr(kernel_build, "EXTRA_SOURCES", ())
    monkeypatch.setattr(kernel_build, "INCLUDED_SOURCES", ())
    monkeypatch.delenv(kernel_build.ENV_TARGET, raising=False)
    monkeypatch.setattr(cpu_kernel, "_module", None)
    monkeypatch.setattr(cpu_kernel, "_target", None)
    monkeypatch.setattr(cpu_kernel, "_error", None)
    monkeypatch.setattr(backends, "_logged", set())
    p, w, h = _single([0.0, 0.0, 2.0])
    with caplog.at_level("INFO", logger="worldtree.render"):
        out = rasterize(width=w, height=h, **p)
        rasterize(width=w, height=h, **p)
    assert out.backend == "reference"
    warnings = [r for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "C++ rasterizer unavailable" in warnings[0].getMessage()
    assert "native:" in warnings[0].getMessage() and "portable:" in warnings[0].getMessage()  # both tried
    assert sum("backend on cpu: reference" in r.getMessage() for r in caplog.records) == 1  # logged once
    with pytest.raises(UserError, match="did not build"):
        rasterize(width=w, height=h, backend="cpu", **p)


def test_radius_formula_independent():
    """radius = ceil(3 sqrt(lambda)), lambda = mid + sqrt(max(0.1, mid^2 - det)) (the 3DGS eigenvalue bound)."""
    p, w, h = _single([0.0, 0.0, 2.0], log_scale=math.log(0.1))
    out = rasterize(width=w, height=h, backend="reference", **p)
    sigma_px = 30.0 * 0.1 / 2.0  # f s / z
    lam = sigma_px**2 + 0.3 + math.sqrt(0.1)  # isotropic: mid^2 - det = 0, floored at 0.1
    assert int(out.radii[0]) == math.ceil(3 * math.sqrt(lam))
