"""`wtbench view`'s request logic without a browser: viser's camera <-> OpenCV w2c, intrinsics and resolution,
letterboxing, time slider -> time index, render modes -> displayed image, encoding."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from benchmarks.viewer import camera as cam
from benchmarks.viewer import frames


def _rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _pose(rng) -> np.ndarray:
    w2c = np.eye(4)
    w2c[:3, :3] = _rotation(rng)
    w2c[:3, 3] = rng.normal(size=3)
    return w2c


def test_quaternion_round_trip_including_half_turns():
    rng = np.random.default_rng(0)
    rotations = [_rotation(rng) for _ in range(50)]
    rotations += [
        np.diag([1.0, -1.0, -1.0]),
        np.diag([-1.0, 1.0, -1.0]),
        np.diag([-1.0, -1.0, 1.0]),
        np.eye(3),
    ]
    for R in rotations:
        q = cam.matrix_to_quat(R)
        assert q[0] >= 0 and math.isclose(np.linalg.norm(q), 1.0, rel_tol=1e-12)
        np.testing.assert_allclose(cam.quat_to_matrix(q), R, atol=1e-12)


def test_quaternion_is_scalar_first_and_rotates_like_the_matrix():
    # 90 degrees about +z: (cos 45, 0, 0, sin 45) maps x to y.
    q = np.array([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])
    np.testing.assert_allclose(cam.quat_to_matrix(q) @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)


def test_viser_camera_at_a_training_camera_gives_its_w2c():
    rng = np.random.default_rng(1)
    for _ in range(20):
        w2c = _pose(rng)
        wxyz, position = cam.viser_from_w2c(w2c)
        np.testing.assert_allclose(cam.w2c_from_viser(wxyz, position), w2c, atol=1e-12)


def test_viser_pose_meaning_position_is_the_centre_and_z_looks_forward():
    # A camera at (1, 2, 3) looking along world +x, with world -z up on screen (OpenCV: camera y is down).
    R_wc = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # columns: camera x, y, z in world
    assert np.linalg.det(R_wc) == pytest.approx(1.0)
    centre = np.array([1.0, 2.0, 3.0])
    w2c = np.eye(4)
    w2c[:3, :3] = R_wc.T
    w2c[:3, 3] = -R_wc.T @ centre
    wxyz, position = cam.viser_from_w2c(w2c)
    np.testing.assert_allclose(position, centre, atol=1e-12)
    # viser: P_world = R(wxyz) p_camera + position; the point 1 unit ahead of the camera lies at centre + x.
    np.testing.assert_allclose(
        cam.quat_to_matrix(wxyz) @ [0, 0, 1.0] + position, centre + [1.0, 0, 0], atol=1e-12
    )
    ahead = w2c @ np.array([2.0, 2.0, 3.0, 1.0])
    np.testing.assert_allclose(ahead[:3], [0.0, 0.0, 1.0], atol=1e-12)  # in front: +z in the camera
    assert cam.camera_centres(w2c[None]) == pytest.approx(centre[None])


def test_pose_read_with_rounding_is_reorthonormalised():
    rng = np.random.default_rng(2)
    w2c = _pose(rng)
    noisy = w2c.copy()
    noisy[:3, :3] += 1e-7 * rng.normal(size=(3, 3))
    wxyz, position = cam.viser_from_w2c(noisy)
    np.testing.assert_allclose(cam.w2c_from_viser(wxyz, position), w2c, atol=1e-6)


def test_free_camera_intrinsics_match_the_vertical_field_of_view():
    K = cam.free_intrinsics(math.radians(60), 320, 180)
    assert K[0, 0] == K[1, 1] == pytest.approx(90 / math.tan(math.radians(30)))
    assert (K[0, 2], K[1, 2]) == (159.5, 89.5)
    assert cam.vertical_fov(K, 180) == pytest.approx(math.radians(60))
    # The top edge of the image (v = -0.5) is fov/2 above the axis.
    assert math.atan((K[1, 2] + 0.5) / K[1, 1]) == pytest.approx(math.radians(30))


@pytest.mark.parametrize(
    ("canvas", "max_size", "moving", "expected"),
    [
        ((1280, 720), 480, False, (480, 270)),  # capped at --max-size
        ((1280, 720), 480, True, (120, 68)),  # preview: 4 times smaller per side
        ((400, 300), 960, False, (400, 300)),  # never larger than the canvas
        ((400, 300), 960, True, (100, 75)),
        ((1280, 720), 64, True, (28, 16)),  # the shorter side stays at least MIN_SIDE
        ((0, 0), 320, False, (320, 240)),  # not measured yet: 640 x 480
        ((720, 1280), 480, False, (270, 480)),  # portrait
    ],
)
def test_render_size(canvas, max_size, moving, expected):
    assert cam.render_size(*canvas, max_size, moving) == expected


def test_letterbox_pads_to_the_canvas_aspect_and_keeps_the_image_whole():
    wide = cam.letterbox(64, 36, 2.0)
    assert (wide.width, wide.height, wide.x0, wide.y0) == (72, 36, 4, 0)
    tall = cam.letterbox(64, 36, 1.0)
    assert (tall.width, tall.height, tall.x0, tall.y0) == (64, 64, 0, 14)
    same = cam.letterbox(64, 36, 64 / 36)
    assert (same.width, same.height, same.x0, same.y0) == (64, 36, 0, 0)
    img = np.arange(36 * 64 * 3, dtype=np.uint8).reshape(36, 64, 3)
    padded = np.zeros((tall.height, tall.width, 3), np.uint8)
    padded[tall.y0 : tall.y0 + 36, tall.x0 : tall.x0 + 64] = img
    np.testing.assert_array_equal(tall.crop(padded, 64, 36), img)


def test_letterbox_fov_lines_the_browser_camera_up_with_the_padded_image():
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 17.5], [0, 0, 1]])
    # Canvas wider than the camera: the image's own height spans the canvas height.
    assert cam.letterbox_fov(K, 64, 36, 2.0) == pytest.approx(2 * math.atan(18 / 50))
    # Canvas taller: the padded height (64 px) does.
    assert cam.letterbox_fov(K, 64, 36, 1.0) == pytest.approx(2 * math.atan(32 / 50))


def test_same_pose_tells_an_echo_from_a_move():
    rng = np.random.default_rng(3)
    w2c = _pose(rng)
    wxyz, position = cam.viser_from_w2c(w2c)
    echo = cam.w2c_from_viser(np.float32(wxyz).astype(np.float64), np.float32(position).astype(np.float64))
    assert cam.same_pose(echo, w2c, scale=1.0, tol=1e-3)
    moved = w2c.copy()
    moved[:3, 3] += [0.01, 0, 0]
    assert not cam.same_pose(moved, w2c, scale=1.0, tol=1e-3)
    turned = w2c.copy()
    turned[:3, :3] = cam.quat_to_matrix([math.cos(0.005), math.sin(0.005), 0, 0]) @ w2c[:3, :3]
    assert not cam.same_pose(turned, w2c, scale=1.0, tol=1e-3)


def test_a_late_echo_of_a_placement_keeps_the_camera_looked_through():
    """The browser reports a placed pose in pieces; on a busy machine a piece arrives after LOCK_GRACE_S. A
    report that takes the rotation and the position each from before or after the placement is such an echo;
    any other pose is the user moving away."""
    import contextlib
    import time
    from types import SimpleNamespace

    from benchmarks.viewer.server import LOCK_GRACE_S, ClientView, _ClientState
    from benchmarks.viewer.source import ViewCamera

    rng = np.random.default_rng(5)
    w2c_a, w2c_b, w2c_c = _pose(rng), _pose(rng), _pose(rng)
    q_a, p_a = cam.viser_from_w2c(w2c_a)
    q_b, p_b = cam.viser_from_w2c(w2c_b)
    browser = SimpleNamespace(wxyz=q_a, position=p_a, fov=1.0, aspect=16 / 9, image_width=160, image_height=90)
    view = object.__new__(ClientView)  # no server, no render thread: the camera bookkeeping alone
    view.viewer = SimpleNamespace(scale=1.0, refresh_frusta=lambda: None, initial_camera=None)
    view.client = SimpleNamespace(camera=browser, atomic=contextlib.nullcontext)
    view.state = _ClientState(ready=True, canvas=(160, 90))
    target = ViewCamera("train_002", np.diag([100.0, 100.0, 1.0]), w2c_b, 160, 90, 2, is_test=False)
    view.look_through(target)
    assert view.state.locked is target and cam.same_pose(cam.w2c_from_viser(browser.wxyz, browser.position), w2c_b, 1.0)

    def report(q, p):
        view._on_camera(SimpleNamespace(wxyz=q, position=p, image_width=160, image_height=90))

    view.state.locked_at = time.monotonic() - 10 * LOCK_GRACE_S  # the echoes come late
    for q, p in ((q_b, p_a), (q_a, p_b), (q_a, p_a), (q_b, p_b)):
        report(np.float32(q).astype(np.float64), np.float32(p).astype(np.float64))  # as the browser rounds
        assert view.state.locked is target
    q_c, p_c = cam.viser_from_w2c(w2c_c)
    report(q_b, p_c)  # the user pans away from the placed camera
    assert view.state.locked is None


def test_scene_up_and_scale():
    # Cameras looking along +z with y down: up is -y; centres spread 2 units from their mean.
    w2cs = np.stack([np.eye(4)] * 3)
    w2cs[0, :3, 3] = [-2.0, 0, 0]
    w2cs[2, :3, 3] = [2.0, 0, 0]
    np.testing.assert_allclose(cam.scene_up(w2cs), [0, -1.0, 0])
    assert cam.scene_scale(w2cs) == pytest.approx(2.0)
    assert cam.scene_scale(np.eye(4)[None]) == 1.0


def test_time_slider_value_to_time_index():
    assert frames.time_index(0, 6) == 0
    assert frames.time_index(3.4, 6) == 3
    assert frames.time_index(3.6, 6) == 4
    assert frames.time_index(-2, 6) == 0
    assert frames.time_index(99, 6) == 5
    assert [frames.next_time_index(i, 3) for i in range(3)] == [1, 2, 0]
    with pytest.raises(ValueError):
        frames.time_index(0, 0)


def test_modes_dispatch_to_the_source_and_tree_mode_only_for_trees():
    assert frames.modes_for(False) == ["colour", "depth", "dynamic part"]
    assert frames.modes_for(True) == ["colour", "depth", "dynamic part", "tree node"]
    assert [frames.MODES[m] for m in frames.modes_for(True)] == ["rgb", "depth", "dynamic", "rgb"]


def test_colour_image_is_quantised_like_the_runs_test_renders():
    rgb = torch.rand(5, 7, 3) * 1.2 - 0.1  # out of range on both sides
    expected = (rgb.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)  # benchmarks.runner.runs._render_test
    np.testing.assert_array_equal(frames.to_display(rgb, "colour"), expected)
    np.testing.assert_array_equal(frames.to_display(rgb.numpy(), "dynamic part"), expected)


def test_depth_is_coloured_near_red_far_blue_and_empty_black():
    depth = np.full((4, 10), np.nan)
    depth[:, :5] = np.linspace(1.0, 2.0, 5)[None]
    depth[0, 9] = 0.0
    out = frames.to_display(torch.tensor(depth)[..., None], "depth")
    assert out.shape == (4, 10, 3) and out.dtype == np.uint8
    assert (out[:, 5:] == 0).all()  # NaN and 0: nothing drawn
    near, far = out[0, 0].astype(int), out[0, 4].astype(int)
    assert near[0] > near[2] and far[2] > far[0]


def test_tree_node_mode_tints_by_a_stable_node_colour():
    rgb = np.full((2, 2, 3), 0.5, np.float32)
    a1 = frames.to_display(rgb, "tree node", "3")
    a2 = frames.to_display(rgb, "tree node", "3")
    np.testing.assert_array_equal(a1, a2)
    plain = frames.to_display(rgb, "colour")
    assert not np.array_equal(a1, plain)
    np.testing.assert_array_equal(frames.to_display(rgb, "tree node", None), plain)
    colours = {tuple(frames.node_colour(str(n))) for n in range(1, 8)}
    assert len(colours) >= 5  # the 7 nodes of a depth-2 tree mostly get distinct colours


def test_unknown_mode_and_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="unknown render mode"):
        frames.to_display(np.zeros((2, 2, 3)), "normals")
    with pytest.raises(ValueError, match="RGB image"):
        frames.to_display(np.zeros((2, 2)), "colour")


def test_previews_are_jpeg_and_still_images_png():
    assert frames.encoding_for(True).format == "jpeg"
    assert frames.encoding_for(False) == frames.Encoding("png", None)
