"""A scene folder is a boundary, and its documents are validated: manifest.json / cameras.json entries that
lead outside the scene (absolute, ``..``, a link out) stop `nvls verify` and `load_scene` with one line naming
the entry, before anything outside is opened; any JSON or bytes in those files gives a validated result or
one one-line UserError (property-based)."""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nvidia_ls.manifest import verify_scene
from worldtree.infra.errors import UserError
from worldtree.scene import load_scene

FUZZ = settings(
    max_examples=40, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, write_tiny_scene) -> Path:
    scene = write_tiny_scene(tmp_path_factory.mktemp("doc") / "tiny", frames=2, width=16, height=12)
    files = {p.relative_to(scene).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
             for p in sorted(scene.rglob("*")) if p.is_file()}  # fmt: skip
    (scene / "manifest.json").write_text(json.dumps({"schema": 1, "files": files}))
    return scene


def _copy(tiny: Path, d: str) -> Path:
    dst = Path(d) / "tiny"
    shutil.copytree(tiny, dst, symlinks=True)
    return dst


@pytest.mark.parametrize(
    "entry", ["/etc/passwd", "../outside.txt", "images/../../outside.txt", "link/secret"]
)
def test_manifest_entries_outside_the_scene_stop_verify(tiny, tmp_path, entry):
    scene = _copy(tiny, str(tmp_path))
    outside = tmp_path / "outside.txt"
    outside.write_text("secret")
    (tmp_path / "secretdir").mkdir()
    (tmp_path / "secretdir" / "secret").write_text("secret")
    (scene / "link").symlink_to(tmp_path / "secretdir")
    man = json.loads((scene / "manifest.json").read_text())
    target = Path(entry) if entry.startswith("/") else scene / entry
    man["files"][entry] = hashlib.sha256(
        target.read_bytes()
    ).hexdigest()  # the true digest: it would "verify"
    (scene / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(UserError, match="outside|absolute") as e:
        verify_scene(scene)
    assert "\n" not in str(e.value) and repr(entry) in str(e.value)


@pytest.mark.parametrize("field", ["file", "mask"])
@pytest.mark.parametrize("entry", ["/etc/hostname", "../outside.png"])
def test_cameras_json_paths_outside_the_scene_stop_the_loader_and_verify(tiny, tmp_path, field, entry):
    scene = _copy(tiny, str(tmp_path))
    shutil.copy(scene / "gt_images" / "v001_t000.png", tmp_path / "outside.png")
    meta = json.loads((scene / "cameras.json").read_text())
    meta["test_frames"][0][field] = entry
    (scene / "cameras.json").write_text(json.dumps(meta))
    for read in (lambda: load_scene(scene), lambda: verify_scene(scene, check_hashes=False)):
        with pytest.raises(UserError, match="outside|absolute") as e:
            read()
        assert "\n" not in str(e.value) and entry in str(e.value)


JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-5, 5) | st.floats(allow_nan=True) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=12,
)


def _mutations(tiny: Path, name: str):
    """The real document with one key replaced by arbitrary JSON, or arbitrary JSON, or arbitrary bytes."""
    real = json.loads((tiny / name).read_text())
    keys = sorted(real) + ["files", "frames", "test_frames", "cameras", "counts"]

    def replace(key: str, value):
        doc = dict(real)
        doc[key] = value
        return json.dumps(doc).encode()

    return st.one_of(
        st.builds(replace, st.sampled_from(keys), JSON),
        JSON.map(lambda v: json.dumps(v).encode()),
        st.binary(max_size=200),
    )


def _outcome(read):
    try:
        return read()
    except UserError as e:
        assert str(e) and "\n" not in str(e), repr(e)
        return e


@FUZZ
@given(data=st.data())
def test_verify_takes_any_manifest(tiny, data):
    payload = data.draw(_mutations(tiny, "manifest.json"))
    with tempfile.TemporaryDirectory() as d:
        scene = _copy(tiny, d)
        (scene / "manifest.json").write_bytes(payload)
        got = _outcome(lambda: verify_scene(scene, check_hashes=False))
    assert isinstance(got, UserError) or all(isinstance(p, str) for p in got)


@FUZZ
@given(data=st.data())
def test_loader_and_verify_take_any_cameras_json(tiny, data):
    payload = data.draw(_mutations(tiny, "cameras.json"))
    with tempfile.TemporaryDirectory() as d:
        scene = _copy(tiny, d)
        (scene / "cameras.json").write_bytes(payload)
        got = _outcome(lambda: load_scene(scene))
        _outcome(lambda: verify_scene(scene, check_hashes=False))
    if not isinstance(got, UserError):
        assert got.images.shape[0] >= 1 and got.images.shape[-1] == 3
