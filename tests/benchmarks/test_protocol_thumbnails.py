"""The diagnostics image's proxy of Balloon1's test views: the layout read against the shared frames, the scores
against a numpy PSNR and a drawn balloon, bad images refused."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from benchmarks.speed.protocol_thumbnails import (
    COLUMNS,
    DEFAULT_IMAGE,
    LABEL_ROWS,
    PANEL_H,
    PANEL_W,
    TIMES,
    contact_sheet,
    main,
    match_points,
    panel_scores,
    panel_to_image,
    read_panels,
    shrink,
    triangulate_depth,
)
from worldtree.imageio import read_image, write_image
from worldtree.infra.errors import UserError

FRAMES = DEFAULT_IMAGE.parents[1] / "Balloon1" / "images"


def _numpy_psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10.0 * np.log10(255.0**2 / mse))


@pytest.mark.skipif(not DEFAULT_IMAGE.is_file(), reason="the shared diagnostics image is not in this clone")
def test_the_layout_matches_the_shared_training_frames():
    # The first panel of each row is training frame t: the 960x540 frame brought to the protocol's 480x270 as
    # the importer does (area filter), then shrunk as the script shrinks renders, which here gives the panel to
    # the last bit. A panel read one caption row off, or from the wrong row or column, scores under 25 dB; a
    # bilinear instead of the area filter about 42; the margin leaves room for another OpenCV's rounding.
    panels = read_panels(DEFAULT_IMAGE)
    for t in TIMES:
        frame = cv2.resize(read_image(FRAMES / f"{t:03d}.png")[..., :3], (480, 270), interpolation=cv2.INTER_AREA)
        err = np.abs(shrink(frame).astype(int) - panels[t]["train"].astype(int))
        assert err.max() <= 1 and err.mean() < 0.01
        # And the test view is another image: camera 0, not camera t.
        assert _numpy_psnr(panels[t]["test"], panels[t]["train"]) < 25.0


def test_panels_are_cut_where_they_were_drawn(tmp_path: Path):
    rng = np.random.default_rng(0)
    grid = np.zeros((PANEL_H * len(TIMES), PANEL_W * len(COLUMNS), 3), np.uint8)
    truth = {}
    for r, t in enumerate(TIMES):
        for c, name in enumerate(COLUMNS):
            panel = rng.integers(0, 256, (PANEL_H, PANEL_W, 3), dtype=np.uint8)
            grid[r * PANEL_H : (r + 1) * PANEL_H, c * PANEL_W : (c + 1) * PANEL_W] = panel
            truth[t, name] = panel[LABEL_ROWS:]
    path = tmp_path / "grid.png"
    write_image(path, grid)
    panels = read_panels(path)
    for (t, name), want in truth.items():
        np.testing.assert_array_equal(panels[t][name], want)


def test_a_wrong_image_is_refused_by_name(tmp_path: Path):
    with pytest.raises(UserError, match="no such file"):
        read_panels(tmp_path / "missing.png")
    path = tmp_path / "small.png"
    write_image(path, np.zeros((90, 160, 3), np.uint8))
    with pytest.raises(UserError, match="small.png: 160x90"):
        read_panels(path)


def test_shrink_keeps_a_flat_image_and_the_uncovered_rows():
    img = np.full((270, 480, 3), 77, np.uint8)
    img[:30] = 200  # the top 30 of 270 rows are the top 20 of 180: all but one under the caption
    out = shrink(img)
    assert out.shape == (PANEL_H - LABEL_ROWS, PANEL_W, 3)
    assert (out[2:] == 77).all()


def test_scores_follow_a_numpy_psnr_and_put_a_moved_balloon_in_its_region():
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[: PANEL_H - LABEL_ROWS, :PANEL_W]
    ref = np.clip(120 + rng.normal(0, 20, (PANEL_H - LABEL_ROWS, PANEL_W, 3)), 0, 255).astype(np.uint8)
    ref[..., :] = ref.mean(axis=2, keepdims=True).astype(np.uint8)  # grey: no green outside the balloon
    pred = np.clip(ref.astype(int) + rng.integers(-3, 4, ref.shape), 0, 255).astype(np.uint8)
    green = np.array([40, 200, 60], np.uint8)
    ref[(xx - 100) ** 2 + (yy - 80) ** 2 <= 30**2] = green
    pred[(xx - 160) ** 2 + (yy - 80) ** 2 <= 30**2] = green  # drawn 60 px to the right
    s = panel_scores(pred, ref)
    assert s["psnr"] == pytest.approx(_numpy_psnr(pred, ref), abs=1e-3)
    # Outside both disks only the +-3 noise differs (about 38.6 dB); inside, a whole disk is wrong twice.
    assert s["background"] > 35.0 > 15.0 > s["balloon"]


def _cameras(baseline: float):
    """Two 480x270 cameras of focal 460 px, the second ``baseline`` units to the right of the first."""
    K = np.array([[460.0, 0, 239.5], [0, 460.0, 134.5], [0, 0, 1]])
    w2c_a = np.eye(4)
    w2c_b = np.eye(4)
    w2c_b[0, 3] = -baseline  # centre at +baseline on x
    return K, w2c_a, w2c_b


def test_triangulation_recovers_a_plane_and_drops_what_no_point_explains():
    K, wa, wb = _cameras(0.1)
    rng = np.random.default_rng(0)
    pa = rng.uniform([20, 20], [460, 250], (50, 2))
    z = 2.0
    pb = pa - np.array([460.0 * 0.1 / z, 0.0])  # a point at depth z moves f B / z to the left in b
    depth, keep = triangulate_depth(K, wa, K, wb, pa, pb)
    assert keep.all()
    np.testing.assert_allclose(depth, z, rtol=1e-6)
    # A match off the epipolar line by 10 px reprojects 5 px off in each view: dropped at 3 px.
    bad = pb.copy()
    bad[0, 1] += 10.0
    # A match that moved the wrong way is a point behind the cameras: dropped.
    bad[1, 0] = pa[1, 0] + 23.0
    _, keep = triangulate_depth(K, wa, K, wb, pa, bad)
    assert not keep[0] and not keep[1] and keep[2:].all()
    d0, k0 = triangulate_depth(K, wa, K, wb, np.zeros((0, 2)), np.zeros((0, 2)))
    assert d0.size == 0 and k0.size == 0


def test_a_textured_plane_matched_into_a_shrunk_panel_gives_its_depth():
    # The whole path of --depth on a closed-form pair: a textured plane at depth 2 seen by two cameras 0.1
    # apart (the second image is the first shifted by f B / z = 23 px), the second shrunk into a panel as the
    # diagnostics image's were, matched back at the first image's scale and triangulated.
    K, wa, wb = _cameras(0.1)
    rng = np.random.default_rng(2)
    tex = cv2.resize(rng.integers(0, 256, (68, 120, 3)).astype(np.uint8), (480, 270), interpolation=cv2.INTER_CUBIC)
    shifted = cv2.warpAffine(tex, np.float32([[1, 0, -23.0], [0, 1, 0]]), (480, 270), borderMode=cv2.BORDER_REFLECT)
    panel = shrink(shifted)
    up = cv2.resize(panel, (480, round(panel.shape[0] * 1.5)), interpolation=cv2.INTER_CUBIC)
    region_a = np.zeros((270, 480), bool)
    region_a[40:230, 60:420] = True
    region_b = np.zeros(up.shape[:2], bool)
    region_b[20:200, 40:400] = True
    pa, pb_up = match_points(tex, up, region_a, region_b)
    pb = panel_to_image(pb_up / 1.5, 480, 270)
    depth, keep = triangulate_depth(K, wa, K, wb, pa, pb)
    assert keep.sum() >= 20
    assert abs(np.median(depth[keep]) / 2.0 - 1.0) < 0.02  # the panel's third of the pixels: about 0.2 px


def test_the_sheet_puts_the_test_view_first_and_each_run_after_it():
    rng = np.random.default_rng(4)
    shape = (PANEL_H - LABEL_ROWS, PANEL_W, 3)
    panels = {t: {"test": rng.integers(0, 256, shape, dtype=np.uint8)} for t in TIMES}
    runs = [{t: rng.integers(0, 256, shape, dtype=np.uint8) for t in TIMES} for _ in range(2)]
    sheet = contact_sheet(panels, runs)
    assert sheet.shape == (shape[0] * len(TIMES), PANEL_W * 3, 3)
    for i, t in enumerate(TIMES):
        rows = slice(i * shape[0], (i + 1) * shape[0])
        np.testing.assert_array_equal(sheet[rows, :PANEL_W], panels[t]["test"])
        np.testing.assert_array_equal(sheet[rows, 2 * PANEL_W :], runs[1][t])


def test_save_wants_an_image_file(tmp_path: Path):
    with pytest.raises(UserError, match="--save .*sheet.txt"):
        main([str(tmp_path / "run"), "--save", str(tmp_path / "sheet.txt")])
    assert not (tmp_path / "sheet.txt").exists()
