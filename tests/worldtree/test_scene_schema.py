"""The scene contract: path confinement and the typed cameras.json document (worldtree.scene_schema)."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from nvidia_ls.writer import cameras_document
from worldtree.infra.errors import UserError
from worldtree.scene import load_scene
from worldtree.scene_schema import CamerasDoc, read_cameras, resolve_inside


def test_resolve_inside_accepts_relative_paths_and_refuses_escapes(tmp_path):
    root = tmp_path / "scene"
    (root / "images").mkdir(parents=True)
    assert resolve_inside(root, "images/00000.png") == (root / "images" / "00000.png").resolve()
    assert resolve_inside(root, "images/../gt.png") == (root / "gt.png").resolve()  # stays inside
    for bad in ("../outside.png", "images/../../x.png", str(tmp_path / "abs.png")):
        with pytest.raises(UserError, match="cameras.json"):
            resolve_inside(root, bad, root / "cameras.json")


@pytest.mark.skipif(not hasattr(os, "symlink"), reason="no symbolic links here")
def test_resolve_inside_refuses_a_link_that_leads_out(tmp_path):
    root = tmp_path / "scene"
    root.mkdir()
    (tmp_path / "secret").mkdir()
    (root / "images").symlink_to(tmp_path / "secret")
    with pytest.raises(UserError, match="leads outside"):
        resolve_inside(root, "images/00000.png")


def _writer_doc() -> dict:
    Ks = np.stack([np.array([[50.0, 0, 31.5], [0, 50.0, 17.5], [0, 0, 1]])] * 2)
    w2cs = np.stack([np.eye(4)] * 2)
    return cameras_document(
        width=64, height=36, cameras=[1, 2], test_camera=1, Ks=Ks, w2cs=w2cs,
        bounds=np.array([[0.5, 4.0], [0.7, 5.0]]), frame_cameras=[2, 2, 2], source_times=[0, 2, 4],
        has_masks=True, world_transform={"scale": 1.0},
    )  # fmt: skip


def test_writer_output_reads_back_field_for_field():
    doc = _writer_doc()
    # The reference: the documented layout (docs/scene_format.md), written out by hand.
    assert doc["schema"] == 1 and doc["near"] == 0.5 and doc["far"] == 5.0
    assert doc["test_frames"][2] == {
        "index": 2, "file": "gt_images/v001_t002.png", "mask": "masks/v001_t002.png", "camera": 1, "time": 2,
        "source_time": 4,
    }  # fmt: skip
    assert doc["frames"][1] == {"index": 1, "file": "images/00001.png", "camera": 2, "time": 1, "source_time": 2}
    assert doc["cameras"][1]["near"] == 0.7 and doc["cameras"][1]["far"] == 5.0
    parsed = CamerasDoc.from_json(json.loads(json.dumps(doc)), "cameras.json")
    assert parsed.to_json() == json.loads(json.dumps(doc))


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d.update(schema=2), "schema 2"),
        (lambda d: d.update(width=0), "'width' must be at least 1"),
        (lambda d: d["cameras"][0].update(K=[[1, 0], [0, 1]]), r"cameras\[0\].K must be a 3x3"),
        (lambda d: d["cameras"][1].update(w2c=[[float("nan")] * 4] * 4), r"cameras\[1\].w2c"),
        (lambda d: d["frames"][0].update(camera=9), "camera 9, which is not listed"),
        (lambda d: d["frames"][0].update(file="../../etc/passwd"), "leads outside"),
        (lambda d: d["test_frames"][0].update(mask="/abs/mask.png"), "is absolute"),
        (lambda d: d["test_frames"][0].update(time=-1), "'time' must be at least 0"),
        (lambda d: d.update(near="x"), "'near' must be a finite number"),
    ],
)
def test_bad_documents_are_one_line_errors_naming_the_file(tmp_path, edit, message):
    doc = json.loads(json.dumps(_writer_doc()))
    edit(doc)
    (tmp_path / "cameras.json").write_text(json.dumps(doc))
    with pytest.raises(UserError, match=message) as info:
        read_cameras(tmp_path)
    assert str(tmp_path / "cameras.json") in str(info.value) and "\n" not in str(info.value)


def test_load_scene_never_reads_outside_the_scene(tmp_path, write_tiny_scene):
    root = write_tiny_scene(tmp_path / "s", frames=2)
    meta = json.loads((root / "cameras.json").read_text())
    (tmp_path / "elsewhere.png").write_bytes((root / meta["frames"][0]["file"]).read_bytes())
    meta["frames"][0]["file"] = "../elsewhere.png"
    (root / "cameras.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match="leads outside"):
        load_scene(root)
