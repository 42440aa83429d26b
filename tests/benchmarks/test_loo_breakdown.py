"""The leave-one-out breakdown's oracles against closed-form cases: a known colour map is undone, a known shift is
measured and undone, a colour key finds a drawn disk; the CLI reads a leave-one-out folder."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from benchmarks.evaluation.leave_one_out import score
from benchmarks.speed.loo_breakdown import align_background, breakdown, colour_key, colour_oracle, main
from worldtree.infra.errors import UserError


def _texture(h=90, w=120, seed=0):
    rng = np.random.default_rng(seed)
    small = rng.integers(40, 216, (h // 6, w // 6, 3)).astype(np.float32)
    return np.clip(cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC), 0, 255).astype(np.uint8)


def test_colour_oracle_recovers_a_per_channel_gain_and_bias():
    pred = _texture()
    gain, bias = np.array([0.9, 1.05, 0.8]), np.array([0.03, -0.02, 0.1])
    gt = np.clip(np.rint((pred / 255.0 * gain + bias) * 255.0), 0, 255).astype(np.uint8)
    fixed, coef = colour_oracle(pred, gt)
    # Rounding to 8 bits on both sides is the only error left: half a level, about 1/500 in gain.
    np.testing.assert_allclose(coef[:, 0], gain, atol=5e-3)
    np.testing.assert_allclose(coef[:, 1], bias, atol=3e-3)
    assert score(fixed, gt) > 50.0 > score(pred, gt)


def test_colour_oracle_on_a_constant_channel_is_finite():
    pred = _texture()
    pred[..., 1] = 128
    gt = _texture(seed=1)
    fixed, coef = colour_oracle(pred, gt)
    assert np.isfinite(coef).all()
    # The best a constant can do is the frame's mean in that channel.
    assert abs(float(fixed[..., 1].mean()) - float(gt[..., 1].mean())) < 1.0


def test_colour_key_keeps_the_largest_region_of_the_hue():
    img = np.full((90, 120, 3), 128, np.uint8)
    cv2.circle(img, (60, 45), 20, (40, 200, 60), -1)  # a green disk (RGB)
    cv2.circle(img, (10, 10), 3, (40, 200, 60), -1)  # a small green speck, not the object
    m = colour_key(img, (70.0, 170.0), 0.25, dilate=2)
    yy, xx = np.mgrid[:90, :120]
    disk = (xx - 60) ** 2 + (yy - 45) ** 2 <= 22**2  # radius 20, dilated 2 px
    iou = (m & disk).sum() / (m | disk).sum()
    assert iou > 0.9 and not m[:15, :15].any()
    assert not colour_key(np.full((20, 20, 3), 128, np.uint8), (70.0, 170.0), 0.25, 2).any()


def test_alignment_measures_and_undoes_a_known_shift():
    gt = _texture(180, 240, seed=3)  # large enough that the homography has no room to bend
    shift = np.float32([[1, 0, 1.5], [0, 1, -0.5]])
    pred = cv2.warpAffine(gt, shift, (gt.shape[1], gt.shape[0]), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REFLECT)  # fmt: skip
    region = np.zeros(gt.shape[:2], bool)
    region[10:-10, 10:-10] = True
    aligned, moved = align_background(pred, gt, region)
    assert moved == pytest.approx(1.5, abs=0.2)
    assert score(aligned, gt, region) > score(pred, gt, region) + 5.0


def test_breakdown_splits_object_and_background():
    gt = _texture(seed=4)
    pred = gt.copy()
    region = np.zeros(gt.shape[:2], bool)
    region[30:60, 40:80] = True
    pred[region] = 255 - pred[region]  # wrong inside the region only
    row = breakdown(pred, gt, region)
    assert row["background"] == float("inf") and row["object"] < 15.0
    assert row["object"] == pytest.approx(score(pred, gt, region))
    assert row["region_share"] == pytest.approx(region.mean())


def test_cli_reads_a_leave_one_out_folder(tmp_path, capsys):
    from benchmarks.fixtures.planar_scene import PlanarScene, PlanarSceneConfig, write_scene_folder
    from worldtree.imageio import write_image
    from worldtree.pixels import as_uint8

    ps = PlanarScene(PlanarSceneConfig(width=48, height=32, num_frames=4, supersample=1))
    scene_dir = write_scene_folder(ps, tmp_path / "scene")
    sc = ps.to_scene()
    loo = tmp_path / "loo"
    loo.mkdir()
    frames = [as_uint8(sc.images[t]).numpy() for t in range(4)]
    write_image(loo / "k01_base.png", frames[1])  # a perfect held-out render
    write_image(loo / "k01_base_prev.png", 255 - frames[0])
    (loo / "loo.json").write_text(json.dumps({"runs": [{"k": 1, "method": "base", "scored_size": [48, 32]}]}))
    out = tmp_path / "bd.json"
    main([str(loo), str(scene_dir), "--json", str(out)])
    rows = json.loads(out.read_text())["rows"]
    assert [(r["side"], r["psnr"]) for r in rows][0] == ("held", float("inf"))
    assert rows[1]["side"] == "prev" and rows[1]["psnr"] == pytest.approx(score(255 - frames[0], frames[0]))
    assert "held" in capsys.readouterr().out
    with pytest.raises(UserError, match="--key-hue"):
        main([str(loo), str(scene_dir), "--key-hue", "170,70"])
    with pytest.raises(UserError, match="loo.json: no such file"):
        main([str(tmp_path), str(scene_dir)])
