"""`nvls import`: a generated capture written in the DynamicNeRF layout comes back as a scene whose frames,
cameras, test views and imported priors equal the generator's exact values; priors follow a run's size."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

from benchmarks.fixtures.planar_scene import PlanarScene, PlanarSceneConfig
from nvidia_ls.importer import ImportConfig, import_scene, run_args
from nvidia_ls.manifest import verify_scene
from tests.nvidia_ls.dynamicnerf_export import export_dynamicnerf
from worldtree.infra.errors import UserError
from worldtree.priors import PriorsConfig, compute_priors
from worldtree.priors.config import DepthImportConfig
from worldtree.priors.imported import read_depth, read_flows, read_masks, resize_flow
from worldtree.scene import load_scene

T = 5
CFG = PlanarSceneConfig(width=80, height=48, num_frames=T, supersample=1, baseline=0.4)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("dnerf") / "Planar"
    return root, export_dynamicnerf(PlanarScene(CFG), root, disp_scale=3.0, disp_shift=0.1)


@pytest.fixture(scope="module")
def imported(exported, tmp_path_factory):
    root, _ = exported
    # The source's own frame, so the cameras compare with the generator's as they are.
    cfg = ImportConfig(normalize="none")
    return import_scene(root, tmp_path_factory.mktemp("scenes"), cfg, log=lambda m: None)


def test_frames_cameras_and_test_views_round_trip(exported, imported):
    _, gt = exported
    sc = load_scene(imported)
    assert sc.images.dtype == torch.uint8 and sc.test_images.dtype == torch.uint8  # held as read
    np.testing.assert_array_equal(sc.images.numpy(), gt["rgb"])
    np.testing.assert_allclose(sc.Ks.numpy(), gt["Ks"], rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(sc.w2cs.numpy(), gt["w2cs"], atol=1e-5)
    # The 12-frame protocol: the test view is frame 0's camera at every time.
    np.testing.assert_allclose(sc.test_w2c.numpy(), gt["w2cs"][0], atol=1e-5)
    np.testing.assert_array_equal(sc.test_images.numpy(), gt["test"])
    assert sc.test_times.tolist() == list(range(T))
    assert verify_scene(imported) == []


def test_rig_frame_keeps_every_pixel_and_scales_metric_depth(exported, tmp_path):
    """The default world frame (rig): a source point seen at pixel p with depth z is, after the recorded
    similarity, seen at p with depth s * z by the imported camera; the camera centres average to the origin,
    the median sqrt(near * far) is 1, and metric depth maps are scaled by s (disparity is kept)."""
    root, gt = exported
    src = tmp_path / "src"
    shutil.copytree(root, src)
    shutil.rmtree(src / "disp")
    (src / "depth").mkdir()
    for t in range(T):
        np.save(src / "depth" / f"{t:03d}.npy", gt["depth"][t].astype(np.float32))
    out = import_scene(src, tmp_path / "o", ImportConfig(), log=lambda m: None)
    wt = json.loads((out / "cameras.json").read_text())["world_transform"]
    assert wt["mode"] == "rig" and json.loads((out / "manifest.json").read_text())["world_transform"] == wt
    s, R, t_w = wt["scale"], np.asarray(wt["R"]), np.asarray(wt["t"])
    sc = load_scene(out)
    H, W = CFG.height, CFG.width
    ys, xs = np.mgrid[4:H:9, 3:W:11]
    pix = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)], 0).astype(np.float64)
    for f in range(T):
        K, w2c = gt["Ks"][f], gt["w2cs"][f]
        z = gt["depth"][f][ys.ravel(), xs.ravel()]
        cam = np.linalg.inv(K) @ pix * z  # source camera coordinates
        X = w2c[:3, :3].T @ (cam - w2c[:3, 3:])  # source world
        Xn = s * R @ X + t_w[:, None]
        Kn, wn = sc.Ks[f].double().numpy(), sc.w2cs[f].double().numpy()
        cn = wn[:3, :3] @ Xn + wn[:3, 3:]
        np.testing.assert_allclose(cn[2], s * z, rtol=1e-5)
        np.testing.assert_allclose((Kn @ (cn / cn[2]))[:2], pix[:2], atol=1e-3)
    cams = json.loads((out / "cameras.json").read_text())["cameras"]  # every camera id, the test one too
    centres = np.stack([-np.asarray(c["w2c"])[:3, :3].T @ np.asarray(c["w2c"])[:3, 3] for c in cams])
    np.testing.assert_allclose(centres.mean(0), 0.0, atol=1e-6)
    np.testing.assert_allclose(np.median([np.sqrt(c["near"] * c["far"]) for c in cams]), 1.0, rtol=1e-6)
    d = read_depth(out / "imported" / "depth", T, H, W, DepthImportConfig(kind="depth"))
    np.testing.assert_allclose(d, s * gt["depth"], rtol=1e-5)
    assert json.loads((out / "imported.json").read_text())["priors"]["depth"]["scaled_by"] == s


def test_imported_priors_equal_the_exact_ones(exported, imported):
    _, gt = exported
    rec = json.loads((imported / "imported.json").read_text())
    assert rec["priors"]["depth"]["kind"] == "disparity"
    args = run_args(imported)
    assert args[args.index("--flow") + 1] == str((imported / "imported" / "flow").resolve())
    assert "priors.flow.import_missing=classical" in args  # the gaps of 3 frames the folder lacks
    # relative disparity is imported but not suggested (below the classical depth on real footage) ...
    assert "--depth-maps" not in args and not any("depth_import" in a for a in args)
    assert rec["optional_why"]
    # ... its options are kept apart: scaled to the stereo without a shift, only where stereo measures nothing
    opt = run_args(imported, optional=True)
    assert opt[opt.index("--depth-maps") + 1] == str((imported / "imported" / "disp").resolve())
    for s in ("kind=disparity", "fit_scale_shift=true", "fit_shift=false", "merge=fill", "fill_static=classical"):
        assert f"priors.depth_import.{s}" in opt, s
    H, W = CFG.height, CFG.width
    disp = read_depth(imported / "imported" / "disp", T, H, W, DepthImportConfig(kind="disparity"))
    np.testing.assert_allclose(disp, 3.0 / gt["depth"] + 0.1, rtol=1e-6)
    flows = read_flows(imported / "imported" / "flow", T, H, W)
    assert set(flows) == set(gt["flow"]) and len(flows) == 2 * (T - 1)
    for k, f in gt["flow"].items():
        np.testing.assert_allclose(flows[k], f, atol=1e-5)
    np.testing.assert_array_equal(read_masks(imported / "imported" / "masks", T, H, W), gt["mask"])


def test_run_args_follow_a_moved_scene_and_stay_inside_it(imported, tmp_path):
    import shutil

    moved = tmp_path / "moved"
    shutil.copytree(imported, moved)
    args = run_args(moved) + run_args(moved, optional=True)
    for opt in ("--depth-maps", "--flow", "--masks"):
        value = args[args.index(opt) + 1]
        assert value.startswith(str(moved.resolve())), (opt, value)
    rec = json.loads((moved / "imported.json").read_text())
    i = rec["wtbench_run_args"].index("--flow")
    for bad in ("/etc", "../../elsewhere"):
        rec["wtbench_run_args"][i + 1] = bad
        (moved / "imported.json").write_text(json.dumps(rec))
        with pytest.raises(UserError, match="imported.json"):
            run_args(moved)
    rec["wtbench_run_args"] = "--depth-maps"  # not a list
    (moved / "imported.json").write_text(json.dumps(rec))
    with pytest.raises(UserError, match="wtbench_run_args"):
        run_args(moved)
    rec["wtbench_run_args"] = []
    rec["wtbench_run_args_optional"] = "--depth-maps"  # not a list
    (moved / "imported.json").write_text(json.dumps(rec))
    with pytest.raises(UserError, match="wtbench_run_args_optional"):
        run_args(moved, optional=True)
    (moved / "imported.json").write_text("{not json")
    with pytest.raises(UserError, match="imported.json"):
        run_args(moved)


def test_import_at_half_size_scales_intrinsics_and_flow(exported, tmp_path):
    root, gt = exported
    out = import_scene(root, tmp_path, ImportConfig(size=(40, 24)), log=lambda m: None)
    sc = load_scene(out)
    K = gt["Ks"][0]
    # Pixel centres at integers: f halves, c' = (c + 0.5) / 2 - 0.5.
    np.testing.assert_allclose(sc.Ks[0, 0, 0].item(), K[0, 0] / 2, rtol=1e-6)
    np.testing.assert_allclose(sc.Ks[0, :2, 2].numpy(), (K[:2, 2] + 0.5) / 2 - 0.5, atol=1e-5)
    # Independent reference: the exact flow of the same scene generated at half size.
    half = PlanarScene(PlanarSceneConfig(width=40, height=24, num_frames=T, supersample=1, baseline=0.4))
    ref, valid = half.flow(1, 2)
    kind = half.render(*half.frame_pose(1), 1)["kind"]
    got = read_flows(out / "imported" / "flow", T, 24, 40)[(1, 2)]
    # Area averaging mixes vectors across the square's edge; compare away from it.
    edge = np.zeros_like(valid)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            edge |= np.roll(np.roll(kind, dy, 0), dx, 1) != kind
    keep = valid & ~edge
    assert keep.sum() > 300
    err = np.linalg.norm(got - ref, axis=-1)[keep]
    # Unscaled vectors would be off by half the flow: a median error above 0.15 px here.
    assert np.median(np.linalg.norm(ref[keep], axis=-1)) > 0.3
    assert np.median(err) < 0.05


def test_resize_flow_linear_field_closed_form():
    # A linear field u = a + b x, v = c + d y at 64x32, reduced to 16x8: at new pixel x' the field must equal
    # the old field at x = (x' + 0.5) * 4 - 0.5, divided by 4 (the displacement shrinks with the image).
    y, x = np.mgrid[0:32, 0:64].astype(np.float32)
    f = np.stack([2.0 + 0.5 * x, -1.0 + 0.25 * y], -1).astype(np.float32)
    got = resize_flow(f, 8, 16)
    yy, xx = np.mgrid[0:8, 0:16].astype(np.float64)
    X, Y = (xx + 0.5) * 4 - 0.5, (yy + 0.5) * 4 - 0.5
    np.testing.assert_allclose(got[..., 0], (2.0 + 0.5 * X) / 4, atol=1e-4)
    np.testing.assert_allclose(got[..., 1], (-1.0 + 0.25 * Y) / 4, atol=1e-4)
    up = resize_flow(got, 32, 64)  # enlarging multiplies the vectors back
    np.testing.assert_allclose(up[8:-8, 8:-8], f[8:-8, 8:-8], atol=1e-3)


def test_full_size_priors_follow_a_downscaled_run(imported, tmp_path):
    """The issue's refusal ("flow shape (48, 80, 2); expected [24, 40, 2]") is gone: full-size flow, depth and
    masks are resized to the working size under downscale 2 and the resize is recorded."""
    sc = load_scene(imported, downscale=2)
    d = imported / "imported"
    cfg = PriorsConfig(
        depth_source=str(d / "disp"), depth_import=DepthImportConfig(kind="disparity"),
        flow_source=str(d / "flow"), masks_source=str(d / "masks"),
    )  # fmt: skip
    pri = compute_priors(sc, cfg, tmp_path / "cache")
    assert pri.depth.shape == (T, 24, 40) and pri.flow[(0, 1)].flow.shape == (24, 40, 2)
    assert "flow resized 80x48 -> 40x24" in pri.sources["flow"]
    assert "depth resized 80x48 -> 40x24" in pri.sources["depth"]
    rec = json.loads((tmp_path / "cache" / "priors.json").read_text())
    assert rec["resized"]["flow"] == ["flow resized 80x48 -> 40x24 (vectors scaled)"]
    # Disparity 3/z + 0.1 without a fit inverts to a depth below the true one, never above it.
    assert np.all(pri.depth > 0)


def test_tracks_without_image_size_refer_to_the_stored_size(imported, tmp_path):
    sc = load_scene(imported, downscale=2)
    xy = np.tile(np.array([[[10.0, 20.0], [79.0, 47.0]]], np.float32), (T, 1, 1))
    np.save(tmp_path / "t.npy", xy)
    cfg = PriorsConfig(
        depth_source=str(imported / "imported" / "disp"), depth_import=DepthImportConfig(kind="disparity"),
        flow_source=str(imported / "imported" / "flow"), tracks_source=str(tmp_path / "t.npy"),
    )  # fmt: skip
    pri = compute_priors(sc, cfg, None)
    np.testing.assert_allclose(pri.tracks[0], (xy[0] + 0.5) / 2 - 0.5, atol=1e-6)
    assert "tracks rescaled 80x48 -> 40x24" in pri.sources["tracks"]


def test_bad_sources_fail_with_one_line(exported, tmp_path):
    root, _ = exported
    with pytest.raises(UserError, match="no such folder"):
        import_scene(tmp_path / "nope", tmp_path / "o", ImportConfig())
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "images").mkdir()
    (bad / "images" / "000.png").write_bytes((root / "images" / "000.png").read_bytes())
    with pytest.raises(UserError, match="poses_bounds.npy: missing"):
        import_scene(bad, tmp_path / "o", ImportConfig())
    np.save(bad / "poses_bounds.npy", np.zeros((4, 17)))
    with pytest.raises(UserError, match="4 pose rows for 1 frames"):
        import_scene(bad, tmp_path / "o", ImportConfig())
    with pytest.raises(UserError, match="^ImportConfig.layout 'llff': choose one of"):
        import_scene(root, tmp_path / "o", ImportConfig(layout="llff"))
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_cli_import_prints_the_run_command(exported, tmp_path):
    root, _ = exported
    r = subprocess.run(
        [sys.executable, "-m", "nvidia_ls.cli", "import", str(root), "-o", str(tmp_path), "--size", "40x24"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "wtbench run --scene" in r.stderr and "--flow" in r.stderr
    r = subprocess.run(
        [sys.executable, "-m", "nvidia_ls.cli", "import", str(root), "-o", str(tmp_path)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert r.returncode == 2 and r.stderr.strip().startswith("error:") and "--force" in r.stderr


def test_clip_without_poses(exported, tmp_path):
    root, gt = exported
    clip = tmp_path / "clip"
    (clip / "images").mkdir(parents=True)
    for p in sorted((root / "images").iterdir()):
        (clip / "images" / p.name).write_bytes(p.read_bytes())
    with pytest.raises(UserError, match="--no-poses"):
        import_scene(clip, tmp_path / "o", ImportConfig())
    out = import_scene(clip, tmp_path / "o", ImportConfig(no_poses=True), log=lambda m: None)
    sc = load_scene(out)
    np.testing.assert_array_equal(sc.images.numpy(), gt["rgb"])
    np.testing.assert_allclose(sc.w2cs.numpy(), np.tile(np.eye(4), (T, 1, 1)), atol=1e-9)
    np.testing.assert_allclose(sc.Ks[0, 0, 0].item(), 1.2 * CFG.width, rtol=1e-6)
    assert json.loads((out / "manifest.json").read_text())["poses"]["method"] == "none"
    assert verify_scene(out) == []


def _pb_rot(pb, f):
    m = pb[:, :15].reshape(-1, 3, 5).copy()
    m[:, :, :3] = f(m[:, :, :3])
    out = pb.copy()
    out[:, :15] = m.reshape(-1, 15)
    return out


# (name, mutation of the source folder, expected message): every one was imported (or a traceback) before.
_BAD_SOURCES = [
    (
        "rotation verify rejects",
        lambda d: np.save(
            d / "poses_bounds.npy", _pb_rot(np.load(d / "poses_bounds.npy"), lambda r: r * 1.0003)
        ),
        "rotation not orthonormal",
    ),  # fmt: skip
    (
        "zero rotation",
        lambda d: np.save(d / "poses_bounds.npy", _pb_rot(np.load(d / "poses_bounds.npy"), lambda r: 0 * r)),
        "rotation not orthonormal",
    ),  # fmt: skip
    (
        "focal 1e300",
        lambda d: np.save(
            d / "poses_bounds.npy", np.load(d / "poses_bounds.npy") * np.r_[[1] * 14, [1e300], [1, 1]]
        ),
        "bad intrinsics K: fx = [0-9.]+e\\+30[01] px outside",
    ),  # fmt: skip
    (
        "complex poses",
        lambda d: np.save(d / "poses_bounds.npy", np.load(d / "poses_bounds.npy") + 1j),
        "complex128 values",
    ),  # fmt: skip
    (
        "string poses",
        lambda d: np.save(d / "poses_bounds.npy", np.load(d / "poses_bounds.npy").astype(str)),
        "<U32 values",
    ),  # fmt: skip
    ("empty poses file", lambda d: (d / "poses_bounds.npy").write_bytes(b""), "empty file"),
    (
        "truncated poses file",
        lambda d: (d / "poses_bounds.npy").write_bytes((d / "poses_bounds.npy").read_bytes()[:90]),
        "not a readable .npy",
    ),  # fmt: skip
    ("no pose rows", lambda d: np.save(d / "poses_bounds.npy", np.zeros((0, 17))), "shape \\(0, 17\\)"),
    (
        "negative disparity",
        lambda d: [np.save(p, -np.abs(np.load(p))) for p in (d / "disp").iterdir()],
        "positive at only 0%",
    ),  # fmt: skip
    (
        "3e38 px flow",
        lambda d: [np.savez(p, flow=np.full_like(np.load(p)["flow"], 3e38)) for p in (d / "flow").iterdir()],
        "flow of 3e\\+38 px",
    ),  # fmt: skip
]


@pytest.mark.parametrize("name,mutate,match", _BAD_SOURCES, ids=[c[0] for c in _BAD_SOURCES])
def test_import_refuses_what_verify_rejects_in_one_line(exported, tmp_path, name, mutate, match):
    root, _ = exported
    src = tmp_path / "src"
    shutil.copytree(root, src)
    mutate(src)
    with pytest.raises(UserError, match=match) as e:
        import_scene(src, tmp_path / "o", ImportConfig(), log=lambda m: None)
    assert "\n" not in str(e.value)
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_verify_applies_the_checks_import_applies(imported, tmp_path):
    """One function per check (nvidia_ls.scene_checks): a scene changed after import to hold what import
    refuses is rejected by verify with the same words."""
    from nvidia_ls import scene_checks

    scene = tmp_path / "scene"
    shutil.copytree(imported, scene)
    cams = json.loads((scene / "cameras.json").read_text())
    w2c = np.array(cams["cameras"][0]["w2c"])
    w2c[:3, :3] *= 1.0003  # inside the old import tolerance (1e-3), outside verify's (1e-4)
    cams["cameras"][0]["w2c"] = w2c.tolist()
    cams["cameras"][1]["K"][0][0] = 1e300
    (scene / "cameras.json").write_text(json.dumps(cams))
    disp = sorted((scene / "imported" / "disp").iterdir())[0]
    np.save(disp, -np.abs(np.load(disp)))
    problems = verify_scene(scene, check_hashes=False)
    assert any("rotation not orthonormal" in p for p in problems), problems
    assert any("fx = 1e+300 px outside" in p for p in problems), problems
    assert any(p.startswith("imported/disp/") and "positive at only 0%" in p for p in problems), problems
    assert scene_checks.rotation_problem(w2c[:3, :3]) is not None
    assert scene_checks.rotation_problem(np.eye(3)) is None
    assert scene_checks.flow_problem(np.zeros((4, 5, 2), complex)) is not None
    assert scene_checks.depth_map_problem(np.ones((4, 5)), "depth") is None


def test_integer_poses_are_read_as_numbers(exported, tmp_path):
    """An LLFF file of integers (identity rotations, whole-number bounds) is a valid file, not a traceback."""
    root, _ = exported
    src = tmp_path / "src"
    shutil.copytree(root, src)
    rot = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]])  # OpenCV identity in LLFF's [down, right, back]
    rows = np.zeros((T, 17), np.int64)
    for t in range(T):
        m = np.concatenate([rot, [[t], [0], [0]], [[CFG.height], [CFG.width], [CFG.width]]], axis=1)
        rows[t, :15] = m.reshape(15)
        rows[t, 15:] = (1, 8)
    np.save(src / "poses_bounds.npy", rows)
    out = import_scene(src, tmp_path / "o", ImportConfig(normalize="none"), log=lambda m: None)
    assert verify_scene(out) == []
