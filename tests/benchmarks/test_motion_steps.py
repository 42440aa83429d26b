"""benchmarks.speed.motion_steps: per-step accuracy of flow and SIFT on the moving objects, on known answers."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.speed.motion_steps import StepFigures, object_step_accuracy, sift_step, summary
from nvidia_ls.synth import SynthConfig, SynthView, make_scene, render_view


def _view(object_id: np.ndarray) -> SynthView:
    H, W = object_id.shape
    return SynthView(np.zeros((H, W, 3), np.uint8), np.ones((H, W), np.float32), object_id.astype(np.int16))


def test_accuracy_counts_only_pixels_seen_again():
    oid = np.zeros((10, 20), np.int16)
    oid[2:6, 2:6] = 1  # 16 object pixels
    gt = np.zeros((10, 20, 2), np.float32)
    gt[..., 0] = 3.0
    flow = gt.copy()
    flow[2:4, 2:6, 0] += 5.0  # the top 8 pixels 5 px off
    seen = np.zeros_like(oid)
    seen[2:6, 5:9] = 1  # the object moved 3 px right
    assert object_step_accuracy(_view(oid), _view(seen), gt, flow, 1.5) == pytest.approx(0.5)
    # The bottom rows hidden at t+1 (another object in front): only the wrong top half is left.
    hidden = seen.copy()
    hidden[4:6] = 2
    assert object_step_accuracy(_view(oid), _view(hidden), gt, flow, 1.5) == pytest.approx(0.0)
    # Undefined exact motion (NaN) is not scored; too few pixels give NaN.
    gt_nan = gt.copy()
    gt_nan[2:5] = np.nan
    assert np.isnan(object_step_accuracy(_view(oid), _view(seen), gt_nan, flow, 1.5))


@pytest.fixture(scope="module")
def rendered() -> SynthView:
    sc = make_scene(SynthConfig(steps=8, width=160, height=90, motion="constant", seed=0))
    return render_view(sc, sc.Ks[1], sc.w2cs[1], 160, 90, 2.0, supersample=2)


def test_dis_without_motion_is_right(rendered):
    from worldtree.priors.flow import dis_flow, to_gray_u8

    g = to_gray_u8(rendered.rgb)
    zero = np.zeros(rendered.rgb.shape[:2] + (2,), np.float32)
    assert object_step_accuracy(rendered, rendered, zero, dis_flow(g, g), 1.5) > 0.95


def test_sift_follows_a_known_shift(rendered):
    dx, dy = 6, 2
    shifted = SynthView(
        np.roll(rendered.rgb, (dy, dx), axis=(0, 1)),
        np.roll(rendered.depth, (dy, dx), axis=(0, 1)),
        np.roll(rendered.object_id, (dy, dx), axis=(0, 1)),
    )
    gt = np.zeros(rendered.rgb.shape[:2] + (2,), np.float32)
    gt[...] = (dx, dy)
    matches, right = sift_step(rendered, shifted, gt)
    assert matches >= 3
    assert right >= 0.8 * matches  # a pure translation: nearly every ratio-test match is right
    wrong = gt + 10.0  # the same matches scored against a wrong motion are all wrong
    assert sift_step(rendered, shifted, wrong)[1] == 0


def test_summary_halves():
    rows = [
        StepFigures(1.0, 0.5, 1.0, 2, 1),
        StepFigures(3.0, np.nan, 0.0, 0, 0),
        StepFigures(9.0, 0.1, 0.2, 4, 1),
    ]
    s = summary(rows)
    assert s["first half"]["speed_px"] == pytest.approx(2.0)
    assert s["first half"]["dis_change"] == pytest.approx(0.5)  # NaN steps skipped
    assert s["first half"]["sift_right_frac"] == pytest.approx(0.5)
    assert s["second half"]["dis_same_camera"] == pytest.approx(0.2)
