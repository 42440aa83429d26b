"""The diagnostics image's proxy of Balloon1's test views: the layout read against the shared frames, the scores
against a numpy PSNR and a drawn balloon, bad images refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from benchmarks.speed.protocol_thumbnails import (
    COLUMNS,
    DEFAULT_IMAGE,
    LABEL_ROWS,
    PANEL_H,
    PANEL_W,
    TIMES,
    panel_scores,
    read_panels,
    shrink,
)
from worldtree.infra.errors import UserError

FRAMES = DEFAULT_IMAGE.parents[1] / "Balloon1" / "images"


def _numpy_psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10.0 * np.log10(255.0**2 / mse))


@pytest.mark.skipif(not DEFAULT_IMAGE.is_file(), reason="the shared diagnostics image is not in this clone")
def test_the_layout_matches_the_shared_training_frames():
    # The first panel of each row is training frame t: the 960x540 frame brought to the protocol's 480x270 as
    # the importer does (area filter), then shrunk as the script shrinks renders. A panel read one caption row
    # off, or from the wrong row or column, scores under 25 dB; the filters' differences leave about 39.
    panels = read_panels(DEFAULT_IMAGE)
    for t in TIMES:
        frame = Image.open(FRAMES / f"{t:03d}.png").convert("RGB").resize((480, 270), Image.BOX)
        assert _numpy_psnr(shrink(np.asarray(frame)), panels[t]["train"]) > 33.0
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
    Image.fromarray(grid).save(path)
    panels = read_panels(path)
    for (t, name), want in truth.items():
        np.testing.assert_array_equal(panels[t][name], want)


def test_a_wrong_image_is_refused_by_name(tmp_path: Path):
    with pytest.raises(UserError, match="no such file"):
        read_panels(tmp_path / "missing.png")
    path = tmp_path / "small.png"
    Image.fromarray(np.zeros((90, 160, 3), np.uint8)).save(path)
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
