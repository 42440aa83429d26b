"""`wtbench video`: side-by-side mp4 of a run's renders and the ground truth."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from benchmarks.cli import app
from benchmarks.reporting.video import compose_frames
from worldtree.imageio import read_image
from worldtree.infra.errors import UserError


@pytest.fixture
def run_dir(tmp_path, write_tiny_scene):
    scene = write_tiny_scene(tmp_path / "scene", frames=4)
    run = tmp_path / "run"
    (run / "renders").mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"scene": str(scene)}))
    # "Renders" are the ground truth shifted in colour, so the left panel differs from the middle one.
    for f in sorted((scene / "gt_images").iterdir()):
        img = read_image(f)
        cv2.imwrite(str(run / "renders" / f.name), cv2.cvtColor(255 - img, cv2.COLOR_RGB2BGR))
    return run


def test_mp4_has_every_frame_side_by_side(run_dir):
    res = CliRunner().invoke(app, ["video", str(run_dir)])
    assert res.exit_code == 0, res.output
    cap = cv2.VideoCapture(str(run_dir / "test_view.mp4"))
    n = 0
    frames, _ = compose_frames(run_dir)
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        h, w = frame.shape[:2]
        ref = frames[n][:h, :w]
        # Lossy codec: compare coarse content (mean absolute error on a 0..255 scale).
        assert np.abs(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB).astype(float) - ref).mean() < 12
        n += 1
    assert n == len(frames) == 4
    gt_w = frames[0].shape[1] // 3
    assert frames[0].shape[1] == 3 * gt_w  # render | ground truth | mask overlay


def test_missing_render_is_user_error(run_dir):
    first = sorted((run_dir / "renders").iterdir())[0]
    first.unlink()
    with pytest.raises(UserError, match="missing render"):
        compose_frames(run_dir)
    shutil.rmtree(run_dir / "renders")
    with pytest.raises(UserError, match=r"config.json|missing render"):
        compose_frames(run_dir.parent / "nowhere")
