"""Images are refused by their header size before decoding (issue #30: two 20000x20000 PNGs of 1.2 MB each
grew `wtbench eval` to 9.7 GB; `nvls import --size 160000x90000` asked for 43 GB), and output sizes are
positive and under the same limit ($WTBENCH_MAX_MEGAPIXELS, default 100)."""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from nvidia_ls.build import parse_size
from worldtree import imageio
from worldtree.imageio import image_size, read_image, write_image
from worldtree.infra.errors import UserError


def _png_header(path: Path, width: int, height: int) -> Path:
    """A PNG whose header says ``width`` x ``height`` (its pixel data is a stub: it must never be decoded)."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    chunk = struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk + b"\x00" * 64)
    return path


@pytest.mark.parametrize("ext", [".png", ".jpg", ".bmp"])
def test_header_size_of_real_files(tmp_path, ext):
    img = np.zeros((37, 53, 3), np.uint8)
    ok, buf = cv2.imencode(ext, img)
    assert ok
    assert image_size(buf.tobytes()) == (53, 37)


def test_unknown_format_has_no_size():
    assert image_size(b"GIF89a....") is None and image_size(b"") is None


def test_huge_image_is_refused_before_decoding(tmp_path, monkeypatch):
    path = _png_header(tmp_path / "big.png", 20000, 20000)

    def no_decode(*a, **k):
        raise AssertionError("decoded")

    monkeypatch.setattr(imageio.cv2, "imdecode", no_decode)
    with pytest.raises(UserError) as err:
        read_image(path)
    msg = str(err.value)
    assert msg.startswith(f"{path}: 20000x20000 is 400 megapixels, over the 100-megapixel limit")
    assert "WTBENCH_MAX_MEGAPIXELS=400" in msg and "\n" not in msg


def test_limit_is_raised_by_the_environment(tmp_path, monkeypatch):
    path = _png_header(tmp_path / "big.png", 12000, 10000)
    monkeypatch.setenv("WTBENCH_MAX_MEGAPIXELS", "200")
    with pytest.raises(UserError, match="cannot decode"):  # past the size check, the stub does not decode
        read_image(path)
    monkeypatch.setenv("WTBENCH_MAX_MEGAPIXELS", "100")
    with pytest.raises(UserError, match="over the 100-megapixel limit"):
        read_image(path)
    monkeypatch.setenv("WTBENCH_MAX_MEGAPIXELS", "lots")
    with pytest.raises(UserError, match=r"\$WTBENCH_MAX_MEGAPIXELS='lots'"):
        read_image(path)


def test_small_images_still_read(tmp_path):
    img = np.arange(36 * 64 * 3, dtype=np.uint8).reshape(36, 64, 3)
    for ext in (".png", ".jpg"):
        write_image(tmp_path / f"a{ext}", img)
        assert read_image(tmp_path / f"a{ext}").shape == (36, 64, 3)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("0x0", "must be positive"),
        ("-480x270", "must be positive"),
        ("480x0", "must be positive"),
        ("160000x90000", "14400 megapixels, over the 100-megapixel limit"),
        ("480x270x3", "expected WxH"),
    ],
)
def test_bad_output_sizes_are_refused(text, needle):
    with pytest.raises(UserError, match=needle) as err:
        parse_size(text)
    assert str(err.value).startswith("--size ") and "\n" not in str(err.value)


def _cli(args: list[str], **env: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", *args], capture_output=True, text=True,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), **env},
    )  # fmt: skip


def test_eval_and_import_cli_refuse_in_one_line(tmp_path):
    for side in ("pred", "gt"):
        _png_header(tmp_path / side / "v000_t000.png", 20000, 20000)
    out = _cli(["benchmarks.cli", "eval", str(tmp_path / "pred"), "--gt", str(tmp_path / "gt")])
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "over the 100-megapixel limit; set WTBENCH_MAX_MEGAPIXELS=400" in lines[0], (
        lines
    )
    out = _cli(
        ["nvidia_ls.cli", "import", str(tmp_path / "src"), "-o", str(tmp_path / "box"), "--size", "0x0"]
    )
    assert out.returncode == 2 and out.stderr.strip().splitlines() == [
        "error: --size 0x0: width and height must be positive, e.g. 480x270"
    ]
    assert not (tmp_path / "box").exists()
