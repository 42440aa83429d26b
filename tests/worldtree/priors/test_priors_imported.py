"""Imported priors: every supported format reads back exactly; malformed files give clear UserErrors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from worldtree.infra.errors import UserError
from worldtree.priors.config import DepthImportConfig
from worldtree.priors.imported import (
    fit_scale_shift,
    imported_to_depth,
    read_depth,
    read_flo,
    read_flows,
    read_masks,
    read_tracks,
    write_flo,
)

T, H, W = 3, 12, 16


@pytest.fixture
def depth_maps():
    rng = np.random.default_rng(0)
    return (1.0 + 4.0 * rng.random((T, H, W))).astype(np.float32)


# ------------------------------------------------------------------------------------------------ depth
@pytest.mark.parametrize("fmt", ["npy", "npz", "png"])
def test_depth_folder_formats(tmp_path, depth_maps, fmt):
    for t in range(T):
        p = tmp_path / f"{t:05d}.{fmt}"
        if fmt == "npy":
            np.save(p, depth_maps[t])
        elif fmt == "npz":
            np.savez(p, depth=depth_maps[t])
        else:
            cv2.imwrite(str(p), np.round(depth_maps[t] * 1000).astype(np.uint16))
    got = read_depth(tmp_path, T, H, W, DepthImportConfig())
    tol = 5e-4 if fmt == "png" else 0
    np.testing.assert_allclose(got, depth_maps, atol=tol)


def test_depth_single_file_and_resize(tmp_path, depth_maps):
    np.save(tmp_path / "all.npy", depth_maps)
    np.testing.assert_array_equal(read_depth(tmp_path / "all.npy", T, H, W, DepthImportConfig()), depth_maps)
    # Same aspect ratio at half size: resized to the frames.
    small = np.ones((T, H // 2, W // 2), np.float32) * 2.0
    np.save(tmp_path / "small.npy", small)
    got = read_depth(tmp_path / "small.npy", T, H, W, DepthImportConfig())
    assert got.shape == (T, H, W)
    np.testing.assert_allclose(got, 2.0)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda d, p: [np.save(p / f"{t}.npy", d[t]) for t in range(T - 1)], "2 depth files"),
        (lambda d, p: np.save(p / "x.npy", np.where(np.arange(W) == 3, np.nan, d)), "NaN"),
        (lambda d, p: np.save(p / "x.npy", -d), "negative"),
        (lambda d, p: np.save(p / "x.npy", np.zeros((T, H, W + 9))), "aspect ratio"),
        (lambda d, p: np.save(p / "x.npy", np.zeros((T, H, W))), "every depth value is 0"),
        (lambda d, p: np.save(p / "x.npy", d[:2]), "expected [T=3"),
        (lambda d, p: (p / "x.npy").write_bytes(b"not numpy"), "cannot read"),
        (lambda d, p: np.savez(p / "x.npz", a=d, b=d), "holds arrays"),
    ],
)
def test_depth_malformed(tmp_path, depth_maps, make, message):
    make(depth_maps, tmp_path)
    files = sorted(tmp_path.iterdir())
    src = files[0] if len(files) == 1 else tmp_path
    with pytest.raises(UserError, match=message.replace("[", r"\[")):
        read_depth(src, T, H, W, DepthImportConfig())


def test_depth_png_must_be_16_bit(tmp_path):
    for t in range(T):
        cv2.imwrite(str(tmp_path / f"{t}.png"), np.zeros((H, W), np.uint8))
    with pytest.raises(UserError, match="16-bit"):
        read_depth(tmp_path, T, H, W, DepthImportConfig())


def test_missing_depth_source(tmp_path):
    with pytest.raises(UserError, match="no such file or folder"):
        read_depth(tmp_path / "nope", T, H, W, DepthImportConfig())


def test_disparity_and_scale_shift_fit(depth_maps):
    # Relative disparity = (1/depth) * 0.5 + 0.2: the fit in disparity space recovers metric depth exactly.
    disp = (0.5 / depth_maps + 0.2).astype(np.float32)
    cfg = DepthImportConfig(kind="disparity", fit_scale_shift=True)
    got = imported_to_depth(disp, cfg, depth_maps, np.ones_like(depth_maps))
    np.testing.assert_allclose(got, depth_maps, rtol=1e-4)
    # Depth off by scale 2 and shift 1.
    cfg = DepthImportConfig(kind="depth", fit_scale_shift=True)
    got = imported_to_depth(2 * depth_maps + 1, cfg, depth_maps, np.ones_like(depth_maps))
    np.testing.assert_allclose(got, depth_maps, rtol=1e-4)
    # Plain disparity inversion, with 0 = infinitely far clamped to the farthest finite depth.
    d = np.array([[[0.5, 0.0], [0.25, 1.0]]], np.float32)
    np.testing.assert_allclose(imported_to_depth(d, DepthImportConfig(kind="disparity")), [[[2, 4], [4, 1]]])


def test_fit_scale_shift_against_lstsq():
    rng = np.random.default_rng(4)
    x, y, w = rng.random(50), rng.random(50), rng.random(50)
    a, b = fit_scale_shift(x, y, w)
    A = np.stack([x, np.ones_like(x)], 1) * np.sqrt(w)[:, None]
    ref = np.linalg.lstsq(A, y * np.sqrt(w), rcond=None)[0]
    np.testing.assert_allclose([a, b], ref, rtol=1e-9)
    assert fit_scale_shift(np.ones(5), y[:5], np.ones(5)) == (1.0, 0.0)  # degenerate: constant input
    assert fit_scale_shift(x, y, np.zeros(50)) == (1.0, 0.0)


# ------------------------------------------------------------------------------------------------ tracks
@pytest.fixture
def cotracks():
    rng = np.random.default_rng(1)
    xy = (rng.random((T, 5, 2)) * [W - 1, H - 1]).astype(np.float32)
    vis = rng.random((T, 5)) > 0.3
    return xy, vis


@pytest.mark.parametrize("fmt", ["npz", "npz_pred", "npy3", "pt_dict", "pt_tuple", "batched"])
def test_tracks_formats(tmp_path, cotracks, fmt):
    xy, vis = cotracks
    if fmt == "npz":
        p = tmp_path / "t.npz"
        np.savez(p, tracks=xy, visibility=vis)
    elif fmt == "npz_pred":
        p = tmp_path / "t.npz"
        np.savez(p, pred_tracks=xy[None], pred_visibility=vis[None].astype(np.float32))
    elif fmt == "npy3":
        p = tmp_path / "t.npy"
        np.save(p, np.concatenate([xy, vis[..., None].astype(np.float32)], -1))
    elif fmt == "pt_dict":
        p = tmp_path / "t.pt"
        torch.save({"tracks": torch.from_numpy(xy), "visibility": torch.from_numpy(vis)}, p)
    elif fmt == "pt_tuple":
        p = tmp_path / "t.pt"
        torch.save((torch.from_numpy(xy)[None], torch.from_numpy(vis)[None]), p)
    else:
        p = tmp_path / "t.npz"
        np.savez(p, tracks=xy[None], visibility=vis[None, ..., None])
    gxy, gvis = read_tracks(p, T, H, W)
    np.testing.assert_array_equal(gxy, xy)
    np.testing.assert_array_equal(gvis, vis)


def test_tracks_outside_image_are_invisible(tmp_path, cotracks):
    xy, vis = cotracks
    xy = xy.copy()
    xy[1, 0] = [-5.0, 3.0]
    np.savez(tmp_path / "t.npz", tracks=xy, visibility=np.ones_like(vis))
    _, gvis = read_tracks(tmp_path / "t.npz", T, H, W)
    assert not gvis[1, 0] and gvis[0, 0]


@pytest.mark.parametrize(
    ("arrays", "message"),
    [
        (lambda xy, vis: {"tracks": xy[:2], "visibility": vis[:2]}, "span 2 frames"),
        (lambda xy, vis: {"tracks": xy, "visibility": vis[:, :3]}, "does not match"),
        (lambda xy, vis: {"tracks": xy * np.nan, "visibility": vis}, "NaN"),
        (lambda xy, vis: {"tracks": xy * 1000, "visibility": vis}, "normalised"),
        (lambda xy, vis: {"tracks": xy, "visibility": vis * 3.0}, "probabilities"),
        (lambda xy, vis: {"points": xy, "visibility": vis}, "expected 'tracks'"),
        (lambda xy, vis: {"tracks": xy[..., :1], "visibility": vis}, "positions have shape"),
    ],
)
def test_tracks_malformed(tmp_path, cotracks, arrays, message):
    np.savez(tmp_path / "t.npz", **arrays(*cotracks))
    with pytest.raises(UserError, match=message):
        read_tracks(tmp_path / "t.npz", T, H, W)


def test_tracks_bad_files(tmp_path):
    with pytest.raises(UserError, match="no such file"):
        read_tracks(tmp_path / "none.npz", T, H, W)
    (tmp_path / "t.csv").write_text("1,2")
    with pytest.raises(UserError, match="unsupported suffix"):
        read_tracks(tmp_path / "t.csv", T, H, W)
    (tmp_path / "t.pt").write_bytes(b"garbage")
    with pytest.raises(UserError, match="torch.load"):
        read_tracks(tmp_path / "t.pt", T, H, W)
    np.save(tmp_path / "t.npy", np.zeros((T, 4)))
    with pytest.raises(UserError, match=r"\[T, N, 2\]"):
        read_tracks(tmp_path / "t.npy", T, H, W)


# ------------------------------------------------------------------------------------------------ flow
def test_flo_roundtrip_and_layout(tmp_path):
    f = np.random.default_rng(2).normal(size=(H, W, 2)).astype(np.float32)
    write_flo(tmp_path / "0_1.flo", f)
    raw = (tmp_path / "0_1.flo").read_bytes()
    # Middlebury layout, checked byte by byte: magic, width, height, then row-major (u, v) pairs.
    assert np.frombuffer(raw[:4], "<f4")[0] == np.float32(202021.25)
    assert tuple(np.frombuffer(raw[4:12], "<i4")) == (W, H)
    assert np.frombuffer(raw[12:20], "<f4").tolist() == f[0, 0].tolist()
    np.testing.assert_array_equal(read_flo(tmp_path / "0_1.flo"), f)


def test_flow_folder(tmp_path):
    f = np.ones((H, W, 2), np.float32)
    write_flo(tmp_path / "00000_00001.flo", f)
    np.save(tmp_path / "00001_00000.npy", np.moveaxis(-f, -1, 0))  # [2, H, W] torch layout
    got = read_flows(tmp_path, T, H, W)
    assert set(got) == {(0, 1), (1, 0)}
    np.testing.assert_array_equal(got[(1, 0)], -f)


@pytest.mark.parametrize(
    ("name", "data", "message"),
    [
        ("0_1.flo", b"JUNK" + b"\0" * 8, "bad magic"),  # "PIEH" is the valid magic
        (
            "0_1.flo",
            np.array([202021.25], "<f4").tobytes() + np.array([4, 4], "<i4").tobytes(),
            "header says",
        ),
        ("flow0.npy", None, "must be named"),
        ("0_7.npy", None, "outside"),
        ("0_1.npy", "shape", "expected"),
        ("0_1.npy", "nan", "NaN"),
    ],
)
def test_flow_malformed(tmp_path, name, data, message):
    if isinstance(data, bytes):
        (tmp_path / name).write_bytes(data)
    elif data == "shape":
        np.save(tmp_path / name, np.zeros((H + 1, W, 2), np.float32))
    elif data == "nan":
        np.save(tmp_path / name, np.full((H, W, 2), np.nan, np.float32))
    else:
        np.save(tmp_path / name, np.zeros((H, W, 2), np.float32))
    with pytest.raises(UserError, match=message):
        read_flows(tmp_path, T, H, W)


def test_flow_empty_or_missing(tmp_path):
    with pytest.raises(UserError, match="no <i>_<j>"):
        read_flows(tmp_path, T, H, W)
    with pytest.raises(UserError, match="not a folder"):
        read_flows(tmp_path / "x", T, H, W)


# ------------------------------------------------------------------------------------------------ masks
def test_masks(tmp_path):
    m = np.zeros((T, H, W), bool)
    m[1, 2:5, 3:9] = True
    for t in range(T):
        cv2.imwrite(str(tmp_path / f"{t:03d}.png"), m[t].astype(np.uint8) * 255)
    np.testing.assert_array_equal(read_masks(tmp_path, T, H, W), m)
    # Double size, same aspect: nearest-neighbour resize gives the same mask back.
    big = tmp_path / "big"
    big.mkdir()
    for t in range(T):
        cv2.imwrite(str(big / f"{t:03d}.png"), np.kron(m[t], np.ones((2, 2))).astype(np.uint8) * 255)
    np.testing.assert_array_equal(read_masks(big, T, H, W), m)
    with pytest.raises(UserError, match="one mask per frame"):
        read_masks(tmp_path, T + 1, H, W)
    with pytest.raises(UserError, match="not a folder"):
        read_masks(tmp_path / "none", T, H, W)
