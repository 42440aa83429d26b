"""`nvls synth --kind twin` (issue #28): a generated twin of a real capture, its rig read from poses_bounds.npy,
checked against closed forms: the rig equals the file's, the wall, person and ball sit at their depths, the ball
moves a quarter image width per step, and the ground truth (gt-priors included) stays exact."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from nvidia_ls import llff
from nvidia_ls.build import BuildConfig, build_scene
from nvidia_ls.gt_priors import GtPriorsConfig, write_gt_priors
from nvidia_ls.synth import (
    TWIN_BALL,
    TWIN_PERSON,
    TWIN_SHIFT,
    TWIN_SWEEP,
    SynthConfig,
    make_scene,
    render_view,
    write_raw_scene,
)
from worldtree.imageio import read_mask
from worldtree.infra.errors import UserError

W, H = 48, 27  # the 16:9 of the 960x540 capture
REAL = Path(__file__).resolve().parents[3] / "shared" / "real_nvidia" / "Balloon1" / "poses_bounds.npy"


def _balloon_like_rig(path: Path) -> Path:
    """A 12-camera rig laid out like Balloon1's (two rows of 6 in snake order, ~2.3 units apart, slightly
    rotated; near 40 / far 60..70) written as LLFF poses_bounds.npy."""
    rng = np.random.default_rng(3)
    w2cs = []
    xs = np.linspace(-5.0, 6.5, 6)
    for i in range(12):
        row, col = divmod(i, 6)
        x = xs[col] if row == 0 else xs[5 - col]
        centre = np.array([x, -0.9 + 2.0 * row, -1.0 + 2.8 * row]) + rng.normal(0, 0.1, 3)
        R = cv2.Rodrigues(rng.normal(0, 0.03, 3))[0]
        w = np.eye(4)
        w[:3, :3], w[:3, 3] = R, -R @ centre
        w2cs.append(w)
    K = np.array([[920.0, 0, 479.5], [0, 920.0, 269.5], [0, 0, 1]])
    bounds = np.stack([np.full(12, 40.0), np.linspace(60.0, 70.0, 12)], 1)
    np.save(path, llff.opencv_to_llff(np.stack(w2cs), np.stack([K] * 12), 540, 960, bounds))
    return path


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    return _balloon_like_rig(tmp_path_factory.mktemp("rig") / "poses_bounds.npy")


def _cfg(rig, **kw):
    return SynthConfig(kind="twin", poses=rig, steps=12, width=W, height=H, supersample=1, **kw)


def _to_rig(sc, X):
    """World points ``[..., 3]`` -> the twin's rig frame."""
    M = np.linalg.inv(sc.twin.rig_to_world)
    return X @ M[:3, :3].T + M[:3, 3]


def _backproject(K, w2c, depth):
    u, v = np.meshgrid(np.arange(depth.shape[1]), np.arange(depth.shape[0]))
    cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T * depth[..., None].astype(np.float64)
    return (cam - w2c[:3, 3]) @ w2c[:3, :3]


def test_twin_rig_is_the_files_rig(rig):
    sc = make_scene(_cfg(rig))
    Ks, w2cs, bounds = llff.llff_to_opencv(np.load(rig), W, H)
    np.testing.assert_allclose(sc.Ks, Ks, rtol=1e-12)
    np.testing.assert_allclose(sc.w2cs, w2cs, atol=1e-12)
    assert sc.twin.wall == pytest.approx(np.median(bounds[:, 1]))
    assert sc.twin.width_per_depth == pytest.approx(960 / 920.0)
    # The rig frame: origin at the mean camera centre, rotation orthonormal.
    centres = np.stack([-w[:3, :3].T @ w[:3, 3] for w in w2cs])
    np.testing.assert_allclose(_to_rig(sc, centres).mean(0), 0.0, atol=1e-9)
    R = sc.twin.rig_to_world[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0


def test_wall_person_and_ball_at_their_depths(rig):
    sc = make_scene(_cfg(rig))
    D = sc.twin.wall
    K, w2c = sc.Ks[0], sc.w2cs[0]  # camera 1, the test view
    v = render_view(sc, K, w2c, W, H, 0.0)
    assert (v.object_id >= 0).all()  # the wall and the floor close every view
    pts = _to_rig(sc, _backproject(K, w2c, v.depth))
    static = pts[v.object_id == 0]
    on_wall = np.abs(static[:, 2] - D) < 1e-4 * D
    assert on_wall.mean() > 0.3
    # The ball: every pixel on its sphere, the sphere at 0.3 D; the person (moving, id 2) at D / 2.
    T = sc.object_pose(0, 0.0)
    ball = _backproject(K, w2c, v.depth)[v.object_id == 1]
    assert len(ball) > 20
    np.testing.assert_allclose(np.linalg.norm(ball - T[:3, 3], axis=1), TWIN_BALL["radius"] * D, rtol=1e-4)
    assert _to_rig(sc, T[:3, 3])[2] == pytest.approx(TWIN_BALL["depth"] * D)
    person = pts[v.object_id == 2]
    assert len(person) > 20
    assert np.abs(person[:, 2] - TWIN_PERSON["depth"] * D).max() < 0.06 * D  # front face to sides, turned


def test_ball_moves_a_quarter_image_width_per_step(rig):
    sc = make_scene(_cfg(rig))
    K = sc.Ks[0]
    mean_w2c = np.linalg.inv(sc.twin.rig_to_world)  # a camera at the rig's mean pose

    def u(t):
        c = mean_w2c[:3, :3] @ sc.object_pose(0, t)[:3, 3] + mean_w2c[:3, 3]
        return (K[0, 0] * c[0] / c[2] + K[0, 2]) / W  # image widths

    def tri(s):  # the sweep as a triangle wave of the distance run, in image widths
        s = s % (2 * TWIN_SWEEP)
        return s if s <= TWIN_SWEEP else 2 * TWIN_SWEEP - s

    # Path length per step, integrated finely: exactly TWIN_SHIFT; net displacement too except where it turns.
    full = 0
    for t in range(11):
        fine = np.array([u(t + k / 200) for k in range(201)])
        assert np.abs(np.diff(fine)).sum() == pytest.approx(TWIN_SHIFT, rel=1e-9)
        net = abs(u(t + 1) - u(t))
        assert net == pytest.approx(abs(tri(TWIN_SHIFT * (t + 1)) - tri(TWIN_SHIFT * t)), abs=1e-12)
        full += net == pytest.approx(TWIN_SHIFT, rel=1e-9)
    assert full == 8  # the steps from 2, 5 and 8 turn (at 2.8, 5.6 and 8.4)
    xs = [u(t) - K[0, 2] / W for t in np.linspace(0, 11, 111)]
    assert min(xs) == pytest.approx(TWIN_BALL["u"] - TWIN_SWEEP / 2, abs=0.01)
    assert max(xs) == pytest.approx(TWIN_BALL["u"] + TWIN_SWEEP / 2, abs=0.01)


def test_person_is_static_with_one_object(rig):
    sc = make_scene(_cfg(rig, objects=1))
    assert len(sc.objects) == 1 and len(sc.static) == 3
    v = render_view(sc, sc.Ks[0], sc.w2cs[0], W, H, 3.0)
    pts = _to_rig(sc, _backproject(sc.Ks[0], sc.w2cs[0], v.depth))[v.object_id == 0]
    D = sc.twin.wall
    assert (np.abs(pts[:, 2] - (TWIN_PERSON["depth"] - TWIN_PERSON["half"][2]) * D) < 1e-4 * D).sum() > 20


@pytest.mark.parametrize(
    ("kw", "flag"),
    [({"kind": "twin"}, "--kind twin"), ({"kind": "twin", "poses": "x.npy", "rig": "arc"}, "--rig arc"),
     ({"kind": "twin", "poses": "x.npy", "motion": "fast"}, "--motion fast"), ({"poses": "x.npy"}, "--poses"),
     ({"kind": "tent"}, "SynthConfig.kind 'tent'")],
)  # fmt: skip
def test_bad_twin_options_are_one_line_errors(kw, flag):
    with pytest.raises(UserError) as e:
        SynthConfig(**kw).check()
    assert str(e.value).startswith(flag) and "\n" not in str(e.value)


def test_twin_needs_a_matching_rig_file(rig, tmp_path):
    with pytest.raises(UserError, match=r"expected \(6, 17\)"):
        make_scene(_cfg(rig, cameras=6))
    with pytest.raises(UserError, match="does not match the aspect"):
        make_scene(SynthConfig(kind="twin", poses=rig, width=48, height=48, supersample=1))
    with pytest.raises(UserError, match="no such file"):
        make_scene(SynthConfig(kind="twin", poses=tmp_path / "none.npy"))


def test_written_twin_is_self_contained_for_gt_priors(rig, tmp_path):
    own = tmp_path / "real.npy"
    own.write_bytes(rig.read_bytes())
    raw = write_raw_scene(tmp_path / "raw" / "Twin", _cfg(own, depth=True))
    own.unlink()  # gt-priors must not need the original file
    np.testing.assert_array_equal(np.load(raw / "gt" / "twin_poses_bounds.npy"), np.load(rig))
    meta = json.loads((raw / "gt" / "cameras.json").read_text())
    assert meta["config"]["kind"] == "twin"
    scene = build_scene(
        raw, tmp_path / "scenes", BuildConfig(poses=raw / "gt" / "poses_bounds.npy", frames=12)
    )
    out = write_gt_priors(raw, scene, cfg=GtPriorsConfig(track_stride=4, seed_every=4))
    man = json.loads((scene / "manifest.json").read_text())
    assert len(man["camera_order"]) == 12 and 1 not in man["camera_order"]  # one camera per frame, 1 = test
    for k, (cam, t) in enumerate(zip(man["camera_order"], man["source_times"], strict=True)):
        expect = read_mask(raw / "gt" / "masks" / f"{t:05d}" / f"cam{cam:02d}.png")
        np.testing.assert_array_equal(read_mask(out / "masks" / f"{k:05d}.png"), expect)
    # The exact depth of the scene (its world is the file's) equals the capture's ground truth.
    cam, t = man["camera_order"][3], man["source_times"][3]
    gt_depth = np.load(raw / "gt" / "depth" / f"{t:05d}" / f"cam{cam:02d}.npy")
    np.testing.assert_allclose(np.load(out / "depth" / "00003.npy"), gt_depth, rtol=1e-5)


@pytest.mark.skipif(not REAL.is_file(), reason="the shared Balloon1 capture is not here")
def test_twin_of_balloon1_shifts_the_ball_as_the_real_balloon():
    # Issue #28: at t = 5 camera 5 sees the balloon on the left, the test camera (0) on the right.
    sc = make_scene(SynthConfig(kind="twin", poses=REAL, steps=12, width=W, height=H, supersample=1))
    c = sc.object_pose(0, 5.0)[:3, 3]

    def u(ci):
        p = sc.w2cs[ci][:3, :3] @ c + sc.w2cs[ci][:3, 3]
        return (sc.Ks[ci][0, 0] * p[0] / p[2] + sc.Ks[ci][0, 2]) / W

    assert u(0) - u(5) > 0.4
    assert 0 < u(0) < 1  # in the test view
