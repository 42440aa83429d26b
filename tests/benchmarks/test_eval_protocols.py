"""Both protocols through `evaluate_arrays`: per-frame values against scikit-image and hand computations,
and every edge case of docs/evaluation.md (identical images, empty / tiny / all-ones masks, no LPIPS)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio as sk_psnr
from skimage.metrics import structural_similarity as sk_ssim

from benchmarks.evaluation.evaluate import COLUMNS, EvalWarning, evaluate_arrays
from benchmarks.evaluation.lpips import LPIPS, random_state_dicts
from benchmarks.evaluation.metrics import avge
from benchmarks.evaluation.metrics.protocol_dycheck import masked_map_mean
from worldtree.infra.errors import UserError


@pytest.fixture(scope="module")
def lp():
    return LPIPS.from_state_dicts(*random_state_dicts(seed=5))


def frames(n=3, h=36, w=44, seed=0):
    rng = np.random.default_rng(seed)
    gts = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(n)]
    preds = [np.clip(g.astype(int) + rng.integers(-30, 31, g.shape), 0, 255).astype(np.uint8) for g in gts]
    masks = [rng.random((h, w)) > 0.6 for _ in range(n)]
    return preds, gts, masks


def run(*args, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = evaluate_arrays(*args, **kw)
    return res, [str(w.message) for w in caught if issubclass(w.category, EvalWarning)]


def lpips_u8(model, a, b, bgr=False):
    def t(x):
        x = x[..., ::-1] if bgr else x
        return torch.from_numpy(np.ascontiguousarray(x)).permute(2, 0, 1)[None].float() / 127.5 - 1

    return model.distance(t(a), t(b)).item()


def test_worldtree_frames_equal_skimage_and_authors_recipe(lp):
    preds, gts, masks = frames()
    res, _ = run(preds, gts, masks, protocol="worldtree", lpips_weights=lp)
    t = res.table
    assert list(t.columns) == list(COLUMNS)
    assert list(t["frame"]) == ["0000", "0001", "0002", "mean"]
    for i, (p, g, m) in enumerate(zip(preds, gts, masks, strict=True)):
        row = t.iloc[i]
        assert row["psnr"] == pytest.approx(sk_psnr(g, p), abs=1e-9)
        assert row["ssim"] == pytest.approx(sk_ssim(g, p, channel_axis=-1), abs=1e-6)
        # Authors: images read as BGR, mask replicated to 3 channels, img[mask] is the flattened vector.
        gb, pb, m3 = g[..., ::-1], p[..., ::-1], np.repeat(m[..., None], 3, axis=2)
        assert row["mpsnr"] == pytest.approx(sk_psnr(gb[m3], pb[m3]), abs=1e-9)
        assert row["mssim"] == pytest.approx(sk_ssim(gb[m3], pb[m3]), abs=1e-6)
        assert row["lpips"] == pytest.approx(lpips_u8(lp, g, p, bgr=True), rel=1e-5)
        gw, pw = np.where(m3, g, 255), np.where(m3, p, 255)
        assert row["mlpips"] == pytest.approx(lpips_u8(lp, gw, pw, bgr=True), rel=1e-5)
        assert row["avge"] == pytest.approx(float(avge(row["psnr"], row["ssim"], row["lpips"])), rel=1e-12)
        assert row["mavge"] == pytest.approx(float(avge(row["mpsnr"], row["mssim"], row["lpips"])), rel=1e-12)
    mean = t.iloc[-1]
    for k in ("psnr", "ssim", "lpips", "mpsnr", "mssim", "mlpips"):
        assert mean[k] == pytest.approx(t[k].iloc[:-1].mean(), rel=1e-12)
    # The mean row's AVGE is computed from the mean PSNR, SSIM and LPIPS (as in the paper's tables).
    assert mean["avge"] == pytest.approx(float(avge(mean["psnr"], mean["ssim"], mean["lpips"])), rel=1e-12)
    assert mean["mavge"] == pytest.approx(float(avge(mean["mpsnr"], mean["mssim"], mean["lpips"])), rel=1e-12)
    assert res.record["protocol"]["name"] == "worldtree" and res.record["frame_count"] == 3


def test_dycheck_frames_equal_hand_computation(lp):
    preds, gts, masks = frames(n=2, seed=1)
    res, _ = run(preds, gts, masks, protocol="dycheck", lpips_weights=lp)
    for i, (p, g, m) in enumerate(zip(preds, gts, masks, strict=True)):
        row = res.table.iloc[i]
        a, b = p / 255.0, g / 255.0
        assert row["psnr"] == pytest.approx(-10 * math.log10(((a - b) ** 2).mean()), abs=1e-9)
        assert row["mpsnr"] == pytest.approx(
            -10 * math.log10(((a - b) ** 2 * m[..., None]).sum() / (3 * m.sum())), abs=1e-9
        )
        ref_ssim = sk_ssim(
            a,
            b,
            channel_axis=-1,
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
            data_range=1.0,
        )
        assert row["ssim"] == pytest.approx(ref_ssim, abs=1e-9)
        # mLPIPS: map of the black-masked images (RGB, 2x - 1), averaged over the mask by hand.
        ta = torch.from_numpy(a * m[..., None]).permute(2, 0, 1)[None].float() * 2 - 1
        tb = torch.from_numpy(b * m[..., None]).permute(2, 0, 1)[None].float() * 2 - 1
        lmap = lp.distance_map(ta, tb)[0].double().numpy()
        assert row["mlpips"] == pytest.approx(lmap[m].sum() / m.sum(), rel=1e-5)
        full = lp.distance_map(
            torch.from_numpy(a).permute(2, 0, 1)[None].float() * 2 - 1,
            torch.from_numpy(b).permute(2, 0, 1)[None].float() * 2 - 1,
        )
        assert row["lpips"] == pytest.approx(full.mean().item(), rel=1e-5)


def test_masked_map_mean_by_hand():
    v = torch.tensor([[[1.0, 2.0], [3.0, 4.0]], [[5.0, 6.0], [7.0, 8.0]]])
    m = torch.tensor([[[True, False], [False, True]], [[False, False], [False, False]]])
    got = masked_map_mean(v, m)
    assert got[0].item() == 2.5
    assert math.isnan(got[1].item())


@pytest.mark.parametrize("protocol", ["worldtree", "dycheck"])
def test_all_ones_mask(lp, protocol):
    preds, gts, _ = frames(n=2, seed=2)
    ones = [np.ones(g.shape[:2], dtype=bool) for g in gts]
    t = run(preds, gts, ones, protocol=protocol, lpips_weights=lp)[0].table.iloc[:-1]
    np.testing.assert_allclose(t["mpsnr"], t["psnr"], rtol=1e-12)  # both protocols: same pixels, same MSE
    np.testing.assert_allclose(t["mlpips"], t["lpips"], rtol=1e-6)  # nothing filled / nothing blacked out
    if protocol == "dycheck":
        np.testing.assert_allclose(t["mssim"], t["ssim"], rtol=1e-12)  # partial conv with a full mask
    else:
        # worldtree keeps the authors' 1-D SSIM of the flattened image, which is NOT the 2-D SSIM.
        for i, (p, g) in enumerate(zip(preds, gts, strict=True)):
            assert t["mssim"].iloc[i] == pytest.approx(
                sk_ssim(g[..., ::-1].ravel(), p[..., ::-1].ravel()), abs=1e-6
            )
        assert not np.allclose(t["mssim"], t["ssim"], atol=1e-3)


@pytest.mark.parametrize("protocol", ["worldtree", "dycheck"])
def test_empty_mask_leaves_masked_cells_empty_with_warning(lp, protocol):
    preds, gts, masks = frames(n=3, seed=3)
    masks[1][:] = False
    res, warns = run(preds, gts, masks, protocol=protocol, lpips_weights=lp)
    t = res.table
    assert t.loc[1, ["mpsnr", "mssim", "mlpips", "mavge"]].isna().all()
    assert not t.loc[1, ["psnr", "ssim", "lpips", "avge"]].isna().any()
    assert t.iloc[-1]["mpsnr"] == pytest.approx(t["mpsnr"].iloc[[0, 2]].mean(), rel=1e-12)
    assert any("empty mask" in w and "0001" in w for w in warns)


def test_tiny_mask_worldtree_mssim_empty(lp):
    preds, gts, masks = frames(n=1, seed=4)
    masks[0][:] = False
    masks[0][5, 5:7] = True  # 2 pixels = 6 values < scikit-image's 7-sample window
    res, warns = run(preds, gts, masks, protocol="worldtree", lpips_weights=lp)
    row = res.table.iloc[0]
    assert math.isnan(row["mssim"]) and not math.isnan(row["mpsnr"])
    assert any("fewer than 3 mask pixels" in w for w in warns)


def test_identical_frames_inf_psnr_mean_over_finite():
    preds, gts, masks = frames(n=3, seed=5)
    preds[0] = gts[0].copy()
    res, warns = run(preds, gts, masks, lpips_weights=False)
    t = res.table
    assert t.loc[0, "psnr"] == math.inf and t.loc[0, "mpsnr"] == math.inf
    assert t.loc[0, "ssim"] == pytest.approx(1.0)
    assert t.iloc[-1]["psnr"] == pytest.approx(t["psnr"].iloc[1:3].mean(), rel=1e-12)
    assert any("identical" in w and "0000" in w for w in warns)
    # Every frame identical: the mean is inf too.
    res2, _ = run(gts, [g.copy() for g in gts], lpips_weights=False)
    assert res2.table.iloc[-1]["psnr"] == math.inf
    assert res2.record["mean"]["psnr"] == "inf"


def test_no_lpips_weights_warns_once_and_keeps_other_columns(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.delenv("WTBENCH_LPIPS_WEIGHTS", raising=False)
    preds, gts, masks = frames(n=2, seed=6)
    res, warns = run(preds, gts, masks)
    t = res.table
    assert t[["lpips", "mlpips", "avge", "mavge"]].isna().all().all()
    assert t[["psnr", "ssim", "mpsnr", "mssim"]].notna().all().all()
    lp_warns = [w for w in warns if "LPIPS" in w]
    assert len(lp_warns) == 1 and "wtbench weights install --from DIR" in lp_warns[0]
    assert res.record["lpips"]["available"] is False


def test_float_inputs_are_quantised_first():
    preds, gts, _ = frames(n=1, seed=7)
    as_float = [p / 255.0 + 0.4 / 255.0 for p in preds]  # rounds back to the same uint8 levels
    a = run(preds, gts, lpips_weights=False)[0].table
    b = run(as_float, gts, lpips_weights=False)[0].table
    assert a["psnr"].iloc[0] == b["psnr"].iloc[0] and a["ssim"].iloc[0] == b["ssim"].iloc[0]


def test_mixed_sizes_are_scored_separately():
    p1, g1, _ = frames(n=1, h=20, w=30, seed=8)
    p2, g2, _ = frames(n=1, h=33, w=17, seed=9)
    t = run(p1 + p2, g1 + g2, lpips_weights=False)[0].table
    assert t.loc[1, "ssim"] == pytest.approx(sk_ssim(g2[0], p2[0], channel_axis=-1), abs=1e-6)


def test_array_errors():
    preds, gts, masks = frames(n=2, seed=10)
    with pytest.raises(UserError, match="differ in size"):
        evaluate_arrays([preds[0][:-1]], [gts[0]], lpips_weights=False)
    with pytest.raises(UserError, match="mask"):
        evaluate_arrays(preds, gts, [m[:-1] for m in masks], lpips_weights=False)
    with pytest.raises(UserError, match="one of each"):
        evaluate_arrays(preds, gts[:1], lpips_weights=False)
    with pytest.raises(UserError, match="--protocol"):
        evaluate_arrays(preds, gts, protocol="nope", lpips_weights=False)
    bad = preds[0].astype(np.float32) / 255
    bad[3, 4, 1] = np.nan  # a diverged render: refused, not scored as a black pixel
    with pytest.raises(UserError, match="prediction 0000: the image holds NaN"):
        evaluate_arrays([bad], [gts[0]], lpips_weights=False)
    small = [np.zeros((10, 12, 3), np.uint8)]
    with pytest.raises(UserError, match="at least 11 pixels"):
        evaluate_arrays(small, small, protocol="dycheck", lpips_weights=False)


def test_lpips_needs_31_pixels(lp):
    small = [np.zeros((30, 40, 3), np.uint8)]
    with pytest.raises(UserError, match="31 for LPIPS"):
        evaluate_arrays(small, small, lpips_weights=lp)
    with pytest.warns(EvalWarning, match="identical"):
        assert evaluate_arrays(small, small, lpips_weights=False).table.loc[0, "ssim"] == 1.0


def test_every_registered_protocol_loads_under_its_own_name(monkeypatch):
    from benchmarks.evaluation.metrics import protocols

    assert protocols.PROTOCOL_NAMES == ("worldtree", "dycheck")  # the default first
    for name in protocols.PROTOCOL_NAMES:
        proto = protocols.get_protocol(name)
        assert proto.name == name and proto.record()["name"] == name
    with pytest.raises(UserError, match="--protocol 'nope' is unknown; use one of: worldtree, dycheck"):
        protocols.get_protocol("nope")
    # A registry line naming the wrong class is caught, not silently scored under the wrong name.
    monkeypatch.setitem(protocols.PROTOCOLS, "dycheck", protocols.PROTOCOLS["worldtree"])
    with pytest.raises(TypeError, match="PROTOCOLS\\['dycheck'\\] is WorldTreeProtocol"):
        protocols.get_protocol("dycheck")
