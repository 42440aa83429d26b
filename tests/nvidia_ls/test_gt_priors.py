"""`nvls gt-priors`: exact masks, depth and tracks of a scene built from a generated capture, checked against
the generator's own ground truth (raw gt/ files, gt_flow, objects.json) and independent reprojections."""

from __future__ import annotations

import json
import re
import shutil

import cv2
import numpy as np
import pytest

from nvidia_ls.build import BuildConfig, build_scene
from nvidia_ls.cli import app
from nvidia_ls.gt_priors import GtPriorsConfig, PixelMap, write_gt_priors
from nvidia_ls.manifest import verify_scene
from nvidia_ls.synth import SynthConfig, gt_flow, make_scene, read_gt_cameras, write_raw_scene
from worldtree.imageio import read_mask
from worldtree.infra.errors import UserError
from worldtree.priors import PriorsConfig, compute_priors
from worldtree.scene import load_scene

TINY = SynthConfig(cameras=6, steps=8, width=64, height=36, supersample=1, depth=True)


@pytest.fixture(scope="module")
def gen(tmp_path_factory):
    """Raw capture, a scene built from it with the true poses in a rig-normalised world (a non-trivial
    similarity away from the generator's), and its exact priors."""
    root = tmp_path_factory.mktemp("gtp")
    raw = write_raw_scene(root / "raw" / "Tiny", TINY)
    scene = build_scene(
        raw, root / "scenes", BuildConfig(poses=raw / "gt" / "poses_bounds.npy", normalize="rig")
    )
    out = write_gt_priors(raw, scene, cfg=GtPriorsConfig(track_stride=4, seed_every=3))
    return raw, scene, out


def _frames(scene):
    meta = json.loads((scene / "cameras.json").read_text())
    cams = {c["id"]: c for c in meta["cameras"]}
    fr = meta["frames"]
    Ks = [np.asarray(cams[f["camera"]]["K"]) for f in fr]
    w2cs = [np.asarray(cams[f["camera"]]["w2c"]) for f in fr]
    return fr, Ks, w2cs, json.loads((scene / "manifest.json").read_text())["world_transform"]


def _project(K, w2c, X):
    c = X @ w2c[:3, :3].T + w2c[:3, 3]
    p = c @ K.T
    return p[:, :2] / p[:, 2:], c[:, 2]


def _lift(K, w2c, px, z):
    cam = np.c_[px, np.ones(len(px))] @ np.linalg.inv(K).T * z[:, None]
    return (cam - w2c[:3, 3]) @ w2c[:3, :3]


def test_layout_and_record(gen):
    raw, scene, out = gen
    rec = json.loads((out / "gt_priors.json").read_text())
    assert out == scene / "gt_priors"
    assert len(sorted((out / "masks").glob("*.png"))) == 8 and len(sorted((out / "depth").glob("*.npy"))) == 8
    z = np.load(out / "tracks.npz")
    assert z["tracks"].dtype == np.float32 and z["visibility"].dtype == bool
    assert z["tracks"].shape[:2] == z["visibility"].shape and z["tracks"].shape[0] == 8
    assert z["image_size"].tolist() == [64, 36] and rec["image_size"] == [64, 36]
    # Seeds in frames 0, 3, 6 on the 4-px grid (16 x 9 points each, all of which hit the closed room).
    assert sorted(set(z["seed_frame"].tolist())) == [0, 3, 6] and z["tracks"].shape[1] == 3 * 16 * 9
    assert rec["counts"]["tracks"] == z["tracks"].shape[1] and rec["frames"] == 8
    assert rec["alignment"]["rms_residual_rel_rig"] < 1e-9
    man_scale = json.loads((scene / "manifest.json").read_text())["world_transform"]["scale"]
    assert man_scale != pytest.approx(1.0) and rec["alignment"]["scale"] == pytest.approx(man_scale, rel=1e-9)
    # The derived folder does not upset the scene's own checks.
    assert verify_scene(scene) == []


def test_masks_equal_generator_masks(gen):
    raw, scene, out = gen
    fr, *_ = _frames(scene)
    files = sorted((out / "masks").glob("*.png"))
    for f, path in zip(fr, files, strict=True):
        gt = read_mask(raw / "gt" / "masks" / f"{f['source_time']:05d}" / f"cam{f['camera']:02d}.png")
        got = read_mask(path)
        # The two renderers differ only in float32 vs float64 ray directions: at most a silhouette pixel.
        assert (got != gt).sum() <= 1
    assert any(read_mask(p).any() for p in files)


def test_depth_is_raw_depth_in_scene_units_and_reprojects_like_gt_flow(gen):
    raw, scene, out = gen
    fr, Ks, w2cs, world = _frames(scene)
    s = world["scale"]
    for k, f in enumerate(fr):
        d = np.load(out / "depth" / f"{k:05d}.npy")
        gt = np.load(raw / "gt" / "depth" / f"{f['source_time']:05d}" / f"cam{f['camera']:02d}.npy")
        assert d.dtype == np.float32 and d.shape == (36, 64)
        expect = np.where(np.isfinite(gt), gt * s, 0)
        assert np.array_equal(d == 0, expect == 0)
        # The raw files come from float32 ray directions: equal to 1e-5 except a grazing or silhouette pixel.
        rel = np.abs(d - expect) / np.maximum(expect, 1e-9)
        assert (rel > 1e-5).sum() <= 2 and np.median(rel) < 1e-6
    # Static pixels of frame a lifted with the scene's depth and cameras land in frame b where the generator's
    # own flow (its world, its cameras) sends them.
    a, b = 1, 5
    sc = make_scene(TINY)
    gK, gw = read_gt_cameras(raw)
    ca, cb, ta, tb = fr[a]["camera"], fr[b]["camera"], fr[a]["source_time"], fr[b]["source_time"]
    flow, oid = gt_flow(sc, gK[ca - 1], gw[ca - 1], ta, gK[cb - 1], gw[cb - 1], tb, 64, 36)
    d = np.load(out / "depth" / f"{a:05d}.npy")
    v, u = np.nonzero(oid == 0)
    X = _lift(Ks[a], w2cs[a], np.c_[u, v].astype(float), d[v, u].astype(np.float64))
    pb, _ = _project(Ks[b], w2cs[b], X)
    expect = np.c_[u, v] + flow[v, u]
    # float32 depth storage limits this to ~1e-4 px.
    assert np.abs(pb - expect).max() < 2e-3


def test_tracks_follow_static_geometry_and_object_motion(gen):
    raw, scene, out = gen
    fr, Ks, w2cs, _ = _frames(scene)
    z = np.load(out / "tracks.npz")
    xy, vis, seed, oid = z["tracks"], z["visibility"], z["seed_frame"], z["object_id"]
    gK, gw = read_gt_cameras(raw)
    objs = json.loads((raw / "gt" / "objects.json").read_text())["objects"]
    T = len(fr)
    checked_static = checked_moving = 0
    for n in range(xy.shape[1]):
        k0 = int(seed[n])
        p0 = xy[k0, n].astype(np.float64)
        assert vis[k0, n] and np.allclose(p0, np.round(p0), atol=1e-6)  # seeded on the grid, visible there
        u0, v0 = (int(round(c)) for c in p0)
        f0 = fr[k0]
        gt_d = np.load(raw / "gt" / "depth" / f"{f0['source_time']:05d}" / f"cam{f0['camera']:02d}.npy")
        if oid[n] == 0:
            # Static: the scene's own cameras and the stored depth say where it is in every frame.
            d = np.load(out / "depth" / f"{k0:05d}.npy")[v0, u0]
            X = _lift(Ks[k0], w2cs[k0], p0[None], np.array([d], np.float64))
            for k in range(T):
                pk, zk = _project(Ks[k], w2cs[k], X)
                if vis[k, n]:
                    assert zk[0] > 0 and np.abs(pk[0] - xy[k, n]).max() < 0.05
                    checked_static += 1
        else:
            # Moving: the generator's world, its cameras and objects.json's per-time poses.
            c0 = f0["camera"]
            X0 = _lift(gK[c0 - 1], gw[c0 - 1], p0[None], np.array([gt_d[v0, u0]], np.float64))
            P = np.asarray(objs[oid[n] - 1]["world_from_object"])
            for k in range(T):
                M = P[fr[k]["source_time"]] @ np.linalg.inv(P[f0["source_time"]])
                Xk = X0 @ M[:3, :3].T + M[:3, 3]
                ck = fr[k]["camera"]
                pk, _ = _project(gK[ck - 1], gw[ck - 1], Xk)
                if vis[k, n]:
                    assert np.abs(pk[0] - xy[k, n]).max() < 0.05
                    checked_moving += 1
    assert checked_static > 500 and checked_moving > 10


def test_points_behind_the_moving_object_are_invisible(gen):
    raw, scene, out = gen
    fr, Ks, w2cs, world = _frames(scene)
    z = np.load(out / "tracks.npz")
    xy, vis, seed, oid = z["tracks"], z["visibility"], z["seed_frame"], z["object_id"]
    hidden = seen = 0
    for k, f in enumerate(fr):
        gt_d = np.load(raw / "gt" / "depth" / f"{f['source_time']:05d}" / f"cam{f['camera']:02d}.npy")
        gt_m = read_mask(raw / "gt" / "masks" / f"{f['source_time']:05d}" / f"cam{f['camera']:02d}.png")
        for n in np.flatnonzero(oid == 0):
            k0 = int(seed[n])
            u0, v0 = (int(round(c)) for c in xy[k0, n])
            d0 = np.load(out / "depth" / f"{k0:05d}.npy")[v0, u0]
            X = _lift(Ks[k0], w2cs[k0], xy[k0, n][None].astype(np.float64), np.array([d0], np.float64))
            pk, zk = _project(Ks[k], w2cs[k], X)
            u, v = (int(round(c)) for c in pk[0])
            if not (0 <= u < 64 and 0 <= v < 36 and zk[0] > 0):
                continue
            surface = gt_d[v, u] * world["scale"]  # what the frame shows there, scene units
            if gt_m[v, u] and surface < 0.9 * zk[0]:  # a moving object stands in front of the point
                assert not vis[k, n]
                hidden += 1
            elif abs(surface - zk[0]) < 1e-3 * zk[0]:
                seen += int(vis[k, n])
    assert hidden > 0 and seen > 500


def test_pixel_map_matches_opencv_undistortion():
    K = np.array([[60.0, 0, 31.5], [0, 60.0, 17.5], [0, 0, 1]])
    dist = np.array([0.08, -0.02, 0.001, -0.002, 0.0])
    # The build remaps with initUndistortRectifyMap(K, dist, None, K) at raw size, then resizes to half size.
    mx, my = cv2.initUndistortRectifyMap(K, dist, None, K, (64, 36), cv2.CV_32FC1)
    pm = PixelMap(K, dist, (64, 36), (64, 36))
    u, v = np.meshgrid(np.arange(64.0), np.arange(36.0))
    q = pm.to_raw(np.stack([u, v], -1))
    assert np.abs(q[..., 0] - mx).max() < 1e-3 and np.abs(q[..., 1] - my).max() < 1e-3
    np.testing.assert_allclose(pm.from_raw(q), np.stack([u, v], -1), atol=1e-6)
    # Half size: pixel centres move as (x + 0.5) / 2 - 0.5, so cx = 32 / 2 - 0.5.
    half = PixelMap(np.array([[30.0, 0, 15.5], [0, 30.0, 8.5], [0, 0, 1]]), dist, (64, 36), (32, 18))
    np.testing.assert_allclose(half.K_raw, K)
    np.testing.assert_allclose(half.to_raw(np.array([[0.0, 0.0]])), pm.to_raw(np.array([[0.5, 0.5]])))


def test_bad_input(gen, tmp_path):
    raw, scene, out = gen
    not_gen = tmp_path / "plain"
    shutil.copytree(raw, not_gen, ignore=shutil.ignore_patterns("gt"))
    with pytest.raises(UserError, match="only for captures generated by `nvls synth`"):
        write_gt_priors(not_gen, scene, tmp_path / "o1")
    other = write_raw_scene(tmp_path / "raw" / "Other", SynthConfig(cameras=6, steps=5, width=64, height=36,
                                                                    supersample=1))  # fmt: skip
    with pytest.raises(UserError, match="not built from this raw folder"):
        write_gt_priors(other, scene, tmp_path / "o2")
    with pytest.raises(UserError, match="already exists; pass --force"):
        write_gt_priors(raw, scene)
    moved = tmp_path / "moved"
    shutil.copytree(scene, moved, ignore=shutil.ignore_patterns("gt_priors"))
    meta = json.loads((moved / "cameras.json").read_text())
    meta["cameras"][2]["w2c"][0][3] += 0.5  # one camera far from where the generator put it
    (moved / "cameras.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match="camera centres"):
        write_gt_priors(raw, moved, tmp_path / "o3")
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o3").exists()
    with pytest.raises(UserError, match="^GtPriorsConfig.track_stride 0: must be at least 1 pixel$"):
        write_gt_priors(raw, scene, tmp_path / "o4", GtPriorsConfig(track_stride=0))


def test_cli_force_replaces(gen, tmp_path, capsys):
    raw, scene, _ = gen
    dst = tmp_path / "cli"
    args = ["gt-priors", str(raw), str(scene), "--out", str(dst), "--track-stride", "16", "--seed-every", "8"]
    app(args, standalone_mode=False)
    assert np.load(dst / "tracks.npz")["tracks"].shape[1] == 4 * 2  # one seed frame, 4 x 2 grid at stride 16
    with pytest.raises(UserError, match="already exists"):
        app(args, standalone_mode=False)
    app([*args[:-4], "--track-stride", "8", "--force"], standalone_mode=False)
    assert json.loads((dst / "gt_priors.json").read_text())["settings"]["track_stride"] == 8


def test_imported_end_to_end_at_downscale_2(gen):
    _, scene_dir, out = gen
    scene = load_scene(scene_dir, downscale=2)
    cfg = PriorsConfig(
        masks_source=str(out / "masks"),
        depth_source=str(out / "depth"),
        tracks_source=str(out / "tracks.npz"),
    )
    pri = compute_priors(scene, cfg)
    z = np.load(out / "tracks.npz")
    T, N = z["visibility"].shape
    assert pri.depth.shape == (T, 18, 32) and pri.epi_mask.shape == (T, 18, 32)
    assert pri.tracks.shape == (T, N, 2)
    np.testing.assert_allclose(pri.tracks, (z["tracks"] + 0.5) / 2 - 0.5, atol=1e-5)
    assert pri.sources["masks"] == f"imported:{out / 'masks'}"
    # The rescale is recorded with the source (docs/priors.md).
    assert pri.sources["tracks"] == f"imported:{out / 'tracks.npz'} [tracks rescaled 64x36 -> 32x18]"
    assert pri.sources["depth"].startswith(f"imported:{out / 'depth'}")
    # Half-size depth of a flat wall region is the full-size depth (INTER_AREA averages equal values), times
    # the one factor that brings imported depth to the cameras' scale, which the source records.
    fitted = re.search(r", x([0-9.eE+-]+) to the cameras", pri.sources["depth"])
    factor = float(fitted.group(1)) if fitted else 1.0
    assert 0.5 < factor < 2.0  # the scene's SfM cameras are near the generator's scale
    full = np.load(out / "depth" / "00000.npy")
    expected = factor * float(full[18:20, 32:34].mean())
    assert abs(float(pri.depth[0, 9, 16]) - expected) < 1e-3 * float(full.max()) * factor
    assert pri.epi_mask.any() and pri.epi_mask.mean() < 0.5
