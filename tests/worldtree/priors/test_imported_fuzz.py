"""Property-based bad input for the imported-prior readers (tracks .npy/.npz/.pt, depth .npy/.png folders,
.flo flow, mask images): whatever the bytes or arrays, a reader returns a validated result or raises one
one-line :class:`UserError`; no other exception escapes."""

from __future__ import annotations

import io
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from worldtree.imageio import read_image, read_mask
from worldtree.infra.errors import UserError
from worldtree.priors.config import DepthImportConfig
from worldtree.priors.imported import read_depth, read_flo, read_masks, read_tracks

T, H, W = 3, 8, 12
# Derandomized: the same examples on every machine and run (the suite's results must not depend on luck).
FUZZ = settings(
    max_examples=40, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)

DTYPES = st.sampled_from(["f4", "f8", "i4", "i8", "u1", "u2", "?", "c8", "f2"])
ARRAYS = hnp.arrays(
    DTYPES,
    st.one_of(
        hnp.array_shapes(min_dims=0, max_dims=4, max_side=4),
        st.sampled_from([(T, 5, 2), (T, 5), (2, T, 5, 2), (T, H, W), (T, H, W, 1), (2,), (H, W)]),
    ),
)
KEYS = st.sampled_from(["tracks", "visibility", "image_size", "xy", "vis", "depth", "other"])


def _outcome(read: Callable[[], object]) -> object:
    """Run a reader: its result, or the one-line UserError it raised (any other exception fails the test)."""
    try:
        return read()
    except UserError as e:
        assert "\n" not in str(e) and str(e), repr(e)
        return e


def _npy(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    return buf.getvalue()


def _npz(arrs: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrs)
    return buf.getvalue()


def _pt(arrs: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    torch.save(
        {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in arrs.items() if v.dtype != np.uint16}, buf
    )
    return buf.getvalue()


def _mutate(data: bytes, cut: int, flips: list[int]) -> bytes:
    """A well-formed file cut short and/or with some bytes flipped."""
    out = bytearray(data[: max(0, len(data) - cut)])
    for i in flips:
        if out:
            out[i % len(out)] ^= 0xFF
    return bytes(out)


FILE_BYTES = st.one_of(
    st.binary(max_size=400),
    st.builds(_npy, ARRAYS),
    st.builds(_npz, st.dictionaries(KEYS, ARRAYS, max_size=3)),
    st.builds(_mutate, st.builds(_npz, st.dictionaries(KEYS, ARRAYS, min_size=1, max_size=2)),
              st.integers(0, 40), st.lists(st.integers(0, 10_000), max_size=3)),
)  # fmt: skip


@FUZZ
@given(data=FILE_BYTES, suffix=st.sampled_from([".npy", ".npz"]))
def test_tracks_reader_takes_any_numpy_file(data, suffix):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"tracks{suffix}"
        path.write_bytes(data)
        got = _outcome(lambda: read_tracks(path, T, H, W))
    if not isinstance(got, UserError):
        xy, vis = got
        assert xy.shape[0] == T and xy.shape[2] == 2 and vis.shape == xy.shape[:2] and np.isfinite(xy).all()


@FUZZ
@given(arrs=st.dictionaries(KEYS, ARRAYS, max_size=3), cut=st.integers(0, 30))
def test_tracks_reader_takes_any_torch_file(arrs, cut):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "tracks.pt"
        path.write_bytes(_mutate(_pt(arrs), cut, []))
        got = _outcome(lambda: read_tracks(path, T, H, W))
    if not isinstance(got, UserError):
        assert got[0].shape[0] == T


@FUZZ
@given(files=st.lists(FILE_BYTES, min_size=T, max_size=T), kind=st.sampled_from(["depth", "disparity"]))
def test_depth_reader_takes_any_folder_of_numpy_files(files, kind):
    with tempfile.TemporaryDirectory() as d:
        for i, data in enumerate(files):
            (Path(d) / f"{i:05d}.npy").write_bytes(data)
        got = _outcome(lambda: read_depth(d, T, H, W, DepthImportConfig(kind=kind)))
    if not isinstance(got, UserError):
        assert got.shape == (T, H, W) and np.isfinite(got).all() and (got >= 0).all()


@FUZZ
@given(data=st.one_of(st.binary(max_size=300), st.builds(
    lambda w, h, body: np.array([202021.25], "<f4").tobytes() + np.array([w, h], "<i4").tobytes() + body,
    st.integers(-3, 6), st.integers(-3, 6), st.binary(max_size=400))))  # fmt: skip
def test_flo_reader_takes_any_bytes(data):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "00000_00001.flo"
        path.write_bytes(data)
        got = _outcome(lambda: read_flo(path))
    if not isinstance(got, UserError):
        assert got.ndim == 3 and got.shape[2] == 2


def _png(arr: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", arr)
    assert ok
    return buf.tobytes()


IMAGE_BYTES = st.one_of(
    st.binary(max_size=300),
    st.builds(_png, hnp.arrays(st.sampled_from(["u1", "u2"]), st.sampled_from([(H, W), (H, W, 3), (H, W, 4), (4, 6)]))),
    st.builds(_mutate, st.builds(_png, hnp.arrays("u1", (H, W, 3))), st.integers(1, 60), st.lists(st.integers(0, 500), max_size=2)),
)  # fmt: skip


@FUZZ
@given(data=IMAGE_BYTES)
def test_image_and_mask_readers_take_any_bytes(data):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "x.png"
        path.write_bytes(data)
        img = _outcome(lambda: read_image(path))
        mask = _outcome(lambda: read_mask(path))
    if not isinstance(img, UserError):
        assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    if not isinstance(mask, UserError):
        assert mask.dtype == bool and mask.ndim == 2


@FUZZ
@given(files=st.lists(IMAGE_BYTES, min_size=T, max_size=T))
def test_mask_folder_reader_takes_any_images(files):
    with tempfile.TemporaryDirectory() as d:
        for i, data in enumerate(files):
            (Path(d) / f"{i:05d}.png").write_bytes(data)
        got = _outcome(lambda: read_masks(d, T, H, W))
    if not isinstance(got, UserError):
        assert got.shape == (T, H, W) and got.dtype == bool


def test_npz_with_an_unknown_compression_method_is_one_line(tmp_path):
    # Hypothesis found this one: a zip member naming a compression method zipfile does not implement.
    import zipfile

    buf = io.BytesIO()
    np.savez(buf, tracks=np.zeros((2, 3, 2), np.float32))
    raw = bytearray(buf.getvalue())
    for sig, off in ((b"PK\x03\x04", 8), (b"PK\x01\x02", 10)):  # local and central headers' method field
        i = raw.find(sig)
        assert i >= 0
        raw[i + off : i + off + 2] = (99).to_bytes(2, "little")
    path = tmp_path / "tracks.npz"
    path.write_bytes(bytes(raw))
    with zipfile.ZipFile(path) as z, pytest.raises(NotImplementedError):
        z.open(z.namelist()[0])  # the premise: zipfile itself refuses the member
    with pytest.raises(UserError, match="tracks.npz"):
        read_tracks(path, 3, 8, 8)
