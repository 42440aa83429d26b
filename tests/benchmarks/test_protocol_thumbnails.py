"""The diagnostics image's proxy of Balloon1's test views: the layout read against the shared frames, the scores
against a numpy PSNR and a drawn balloon, bad images refused."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from benchmarks.speed.protocol_thumbnails import (
    COLUMNS,
    DEFAULT_IMAGE,
    EDGE_COLS,
    LABEL_ROWS,
    PANEL_H,
    PANEL_W,
    PROTOCOL_W,
    TIMES,
    _factors,
    balloon_gaussians,
    balloon_placement,
    contact_sheet,
    main,
    match_points,
    panel_scores,
    panel_to_image,
    read_panels,
    scale_about,
    shrink,
    triangulate_depth,
)
from worldtree.imageio import read_image, write_image
from worldtree.infra.errors import UserError
from worldtree.motion.lift import project_points

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


def test_edge_score_is_the_left_tenth_alone():
    rng = np.random.default_rng(2)
    ref = rng.integers(20, 200, (PANEL_H - LABEL_ROWS, PANEL_W, 3)).astype(np.uint8)
    pred = ref.copy()
    pred[:, :EDGE_COLS] += 10  # the left tenth off by 10 grey levels everywhere: 20 log10(255 / 10) dB
    pred[:, EDGE_COLS:] = 255 - pred[:, EDGE_COLS:]  # the rest far off, which the edge must not see
    assert EDGE_COLS == 32
    assert panel_scores(pred, ref)["edge"] == pytest.approx(20 * np.log10(255 / 10), abs=1e-6)


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


def _disc(mask_shape, cx: float, cy: float, r: float) -> np.ndarray:
    yy, xx = np.mgrid[: mask_shape[0], : mask_shape[1]]
    return (xx - cx) ** 2 + (yy - cy) ** 2 <= r**2


def test_placement_gives_a_moved_balloons_offset_in_protocol_pixels_and_the_lens_iou():
    h, w = PANEL_H - LABEL_ROWS, PANEL_W
    grey = np.full((h, w, 3), 128, np.uint8)
    green = np.array([40, 200, 60], np.uint8)
    ref, pred = grey.copy(), grey.copy()
    r, dx, dy = 30.0, 12.0, -5.0
    ref[_disc((h, w), 120, 80, r)] = green
    pred[_disc((h, w), 120 + dx, 80 + dy, r)] = green
    p = balloon_placement(pred, ref)
    up = PROTOCOL_W / PANEL_W  # a panel pixel is 1.5 protocol pixels
    assert p["dx"] == pytest.approx(dx * up, abs=0.2) and p["dy"] == pytest.approx(dy * up, abs=0.2)
    assert p["offset_px"] == pytest.approx(np.hypot(dx, dy) * up, abs=0.3)
    # Two discs of radius r whose centres are d apart overlap in a lens of area 2 r^2 acos(d / 2r) - d/2 sqrt(4r^2 - d^2).
    d = np.hypot(dx, dy)
    lens = 2 * r**2 * np.arccos(d / (2 * r)) - d / 2 * np.sqrt(4 * r**2 - d**2)
    assert p["iou"] == pytest.approx(lens / (2 * np.pi * r**2 - lens), abs=0.02)
    same = balloon_placement(ref, ref)
    assert same["offset_px"] == 0.0 and same["iou"] == 1.0
    none = balloon_placement(grey, ref)
    assert np.isnan(none["offset_px"]) and none["iou"] == 0.0


def _frame(means: torch.Tensor, dynamic: torch.Tensor):
    from worldtree.gaussian_frame import GaussianFrame
    from worldtree.stages.cameras import Sim3

    n = means.shape[0]
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=torch.Generator().manual_seed(3)), dim=1)
    return GaussianFrame(
        0, means, quats, torch.full((n, 3), -3.0), torch.full((n,), 0.5), torch.zeros(n, 3), dynamic,
        Sim3.identity(),
    )  # fmt: skip


def _look(centre: np.ndarray, yaw: float) -> torch.Tensor:
    """OpenCV world-to-camera pose of a camera at ``centre`` turned by ``yaw`` about the y axis."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ centre
    return torch.tensor(w2c, dtype=torch.float32)


def test_scaling_about_a_camera_keeps_its_image_and_scales_depth_and_size():
    K = torch.tensor([[300.0, 0, 160], [0, 300.0, 90], [0, 0, 1]])
    centre = np.array([0.3, -0.1, -2.0])
    w2c = _look(centre, 0.2)
    g = torch.Generator().manual_seed(0)
    means = torch.randn(50, 3, generator=g) * 0.3
    select = torch.rand(50, generator=g) < 0.5
    frame = _frame(means, torch.ones(50, dtype=torch.bool))
    moved = scale_about(frame, torch.tensor(centre, dtype=torch.float32), select, 0.8)
    uv0, z0 = project_points(frame.means, K, w2c)
    uv1, z1 = project_points(moved.means, K, w2c)
    torch.testing.assert_close(uv1, uv0, atol=1e-3, rtol=0)
    torch.testing.assert_close(z1[select], 0.8 * z0[select], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(moved.means[~select], frame.means[~select])
    torch.testing.assert_close(moved.log_scales[select], frame.log_scales[select] + np.log(0.8))
    torch.testing.assert_close(moved.log_scales[~select], frame.log_scales[~select])
    # Another camera sees the selected points where points at 0.8 of their depth along the same rays would be.
    other = _look(centre + np.array([0.5, 0.0, 0.0]), 0.2)
    uv_other, _ = project_points(moved.means, K, other)
    pts = frame.means[select]
    c = torch.tensor(centre, dtype=torch.float32)
    torch.testing.assert_close(uv_other[select], project_points(c + 0.8 * (pts - c), K, other)[0])
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(UserError, match="--dynamic-scale"):
            scale_about(frame, c, select, bad)


def test_factors_are_read_or_refused_by_option_name():
    assert _factors("0.85, 1.0") == [0.85, 1.0]
    for bad in ("", "a,1", "0", "-0.5", "inf"):
        with pytest.raises(UserError, match="--dynamic-scale"):
            _factors(bad)


class _FakeRun:
    """What :func:`balloon_gaussians` reads of a loaded run: a frame, the training camera and its model pose."""

    def __init__(self, frame, K, w2c, width, height):
        from benchmarks.api import Camera

        self._frame = frame
        self._w2c = w2c
        self.cameras = {"train_005": Camera("train_005", "train", K, w2c, width, height, 5, 5)}

    def gaussians_at(self, t):
        return self._frame

    def model_w2c(self, camera, t):
        return self._w2c


def test_the_balloons_gaussians_are_the_dynamic_ones_in_front_of_the_camera_on_its_key():
    K = torch.tensor([[100.0, 0, 49.5], [0, 100.0, 29.5], [0, 0, 1]])
    w2c = torch.eye(4)
    key = np.zeros((60, 100), bool)
    key[10:30, 20:60] = True  # the balloon: x 20..59, y 10..29
    pix = [(40, 20), (40, 20), (40, 20), (80, 50), (59, 29), (60, 29)]
    depth = [1.0, 1.0, -1.0, 1.0, 2.0, 2.0]  # the third behind the camera
    rows = [[(u - 49.5) / 100 * z, (v - 29.5) / 100 * z, z] for (u, v), z in zip(pix, depth, strict=True)]
    means = torch.tensor(rows)
    dynamic = torch.tensor([True, False, True, True, True, True])
    _, sel = balloon_gaussians(_FakeRun(_frame(means, dynamic), K, w2c, 100, 60), 5, key)
    # On the key and dynamic; the static one, the one behind, the one off the key and the one a pixel past it: not.
    assert sel.tolist() == [True, False, False, False, True, False]
