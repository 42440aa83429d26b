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


def test_object_affine_flow_recovers_a_known_affine_motion():
    import cv2

    from benchmarks.speed.motion_steps import object_affine_flow

    if not hasattr(cv2, "findTransformECCWithMask"):
        pytest.skip(f"OpenCV {cv2.__version__} has no findTransformECCWithMask (4.13+)")

    rng = np.random.default_rng(3)
    H, W = 60, 80
    tex = cv2_blur(rng.uniform(0, 255, (H, W)).astype(np.float32))
    th, sc = np.deg2rad(3.0), 1.02  # a turn and a zoom: a translation alone would be off at the corners
    A = np.array(
        [[sc * np.cos(th), -sc * np.sin(th), 3.0], [sc * np.sin(th), sc * np.cos(th), 2.0]], np.float32
    )
    g1 = cv2.warpAffine(tex, A, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    oid = np.zeros((H, W), np.int16)
    oid[15:45, 20:60] = 1
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    gt = np.stack(
        [A[0, 0] * xx + A[0, 1] * yy + A[0, 2] - xx, A[1, 0] * xx + A[1, 1] * yy + A[1, 2] - yy], -1
    )
    flow = object_affine_flow(_view(oid), tex, g1, gt)
    err = np.linalg.norm(flow - gt, axis=-1)[oid > 0]
    # Started from the median translation, up to 1.4 px off at the corners: the fit recovers the rest.
    assert np.median(err) < 0.1 and err.max() < 0.3
    assert np.abs(flow[oid == 0]).max() == 0.0  # nothing off the object
    # Scored the same way as the other columns: an object that stays visible is followed.
    moved = cv2.warpAffine(oid.astype(np.uint8), A, (W, H), flags=cv2.INTER_NEAREST).astype(np.int16)
    assert object_step_accuracy(_view(oid), _view(moved), gt, flow, 1.5) > 0.9


def cv2_blur(img: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.GaussianBlur(img, (0, 0), 2.0)
