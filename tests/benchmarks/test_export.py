"""`wtbench export`: the 3DGS PLY layout read by an independent reader (plyfile), values that round-trip, an
exported time rendered as a static Gaussian set equal to the method's render, the index, npz, bad input."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from benchmarks.api import load_run
from benchmarks.cli import app
from worldtree.gaussians import GaussianSet
from worldtree.infra.errors import UserError
from worldtree.render import rasterize
from worldtree.stages.cameras import centres

plyfile = pytest.importorskip("plyfile")

METHODS = ("static", "base", "worldtree")


def _export(*args: str):
    return CliRunner().invoke(app, ["export", *args])


def _ply_set(path) -> tuple[list[str], GaussianSet]:
    """The vertex property names of a PLY and the file as a GaussianSet, read with plyfile (not our reader)."""
    v = plyfile.PlyData.read(str(path))["vertex"]
    names = [p.name for p in v.properties]
    assert all(v.data.dtype[n] == np.dtype("<f4") for n in names)

    def cols(*keys: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.asarray(v[k]) for k in keys], -1).astype(np.float32))

    params = {
        "means": cols("x", "y", "z"),
        "quats": cols("rot_0", "rot_1", "rot_2", "rot_3"),
        "log_scales": cols("scale_0", "scale_1", "scale_2"),
        "opacity_logits": cols("opacity")[:, 0],
        "sh0": cols("f_dc_0", "f_dc_1", "f_dc_2"),
    }
    rest = [n for n in names if n.startswith("f_rest_")]
    if rest:  # channel-major: every red coefficient, then green, then blue
        k = len(rest) // 3
        params["shN"] = cols(*rest).reshape(-1, 3, k).transpose(1, 2).contiguous()
    return names, GaussianSet(params)


@pytest.fixture(scope="module")
def exported(api_runs, tmp_path_factory):
    """Every method's run exported as PLY at times 2 and 9 (and the static run at all times)."""
    out = {}
    for m in METHODS:
        folder = tmp_path_factory.mktemp(f"ply_{m}") / "export"
        res = _export(str(api_runs[m]), "-o", str(folder), "--times", "9,2", "--device", "cpu")
        assert res.exit_code == 0, res.output
        out[m] = folder
    return out


@pytest.mark.parametrize("method", METHODS)
def test_ply_layout_and_values(exported, api_runs, method):
    run = load_run(api_runs[method], device="cpu")
    index = json.loads((exported[method] / "index.json").read_text())
    for t in (2, 9):
        names, gs = _ply_set(exported[method] / index["times"][str(t)]["file"])
        frame = run.gaussians_at(t)
        rest = [f"f_rest_{i}" for i in range(9)] if method == "static" else []  # SH degree 1: 3 x 3
        assert names == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", *rest, "opacity",
                         "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]  # fmt: skip
        assert len(gs) == len(frame) == index["times"][str(t)]["gaussians"]
        assert torch.equal(gs.means, frame.means) and torch.equal(gs.params["sh0"], frame.sh0)
        assert torch.equal(gs.log_scales, frame.log_scales) and torch.equal(gs.params["quats"], frame.quats)
        # opacity is stored as a logit: sigmoid gives the activated value back
        torch.testing.assert_close(gs.opacities, frame.opacities, atol=1e-7, rtol=1e-6)
        if method == "static":
            assert torch.equal(gs.params["shN"], frame.shN)


@pytest.mark.parametrize("method", METHODS)
def test_an_exported_time_renders_what_the_method_renders(exported, api_runs, method):
    """The PLY loaded as a static Gaussian set, rasterized from the pose the method draws the test camera
    with (its refined test pose, in the model's frame), equals the method's own render at that time."""
    run = load_run(api_runs[method], device="cpu")
    index = json.loads((exported[method] / "index.json").read_text())
    cam = run.cameras["test"]
    for t in (2, 9):
        _, gs = _ply_set(exported[method] / index["times"][str(t)]["file"])
        pose = run.model_w2c("test", t)
        colours = gs.view_colors(centres(pose))
        with torch.no_grad():
            ours = rasterize(gs.means, gs.quats, gs.log_scales, gs.opacities, colours, cam.K, pose, cam.width,
                             cam.height).rgb.clamp(0, 1)  # fmt: skip
        want = run.render("test", t)
        assert float(want.std()) > 0.01  # a real picture, not an empty one
        torch.testing.assert_close(ours, want, atol=2e-5, rtol=0)


def test_index_names_run_method_digest_version(exported, api_runs):
    import worldtree

    for m in METHODS:
        index = json.loads((exported[m] / "index.json").read_text())
        record = json.loads((api_runs[m] / "config.json").read_text())
        canon = json.dumps(record["config"], sort_keys=True, separators=(",", ":"))
        assert index["method"] == m and index["format"] == "ply"
        assert index["config_digest"] == hashlib.sha256(canon.encode()).hexdigest()
        assert index["tool_version"] == worldtree.__version__ and index["run"] == str(api_runs[m].resolve())
        assert sorted(index["times"]) == ["2", "9"]
        files = sorted(p.name for p in exported[m].iterdir())
        assert files == sorted(
            {"index.json", *(e["file"] for e in index["times"].values())}
        )  # no temporaries
    tree = json.loads((exported["worldtree"] / "index.json").read_text())
    assert tree["times"]["2"]["node"] == 2 and tree["times"]["9"]["node"] == 3
    assert tree["times"]["2"]["file"] == "time_0002.ply" and tree["scene_to_model"]["scale"] > 0


def test_a_static_model_is_one_file_for_every_time(api_runs, tmp_path):
    res = _export(str(api_runs["static"]), "-o", str(tmp_path / "all"), "--device", "cpu")
    assert res.exit_code == 0, res.output
    index = json.loads((tmp_path / "all" / "index.json").read_text())
    assert sorted(map(int, index["times"])) == list(range(14))
    assert {e["file"] for e in index["times"].values()} == {"time_0000.ply"}


def test_npz_holds_the_frames_and_the_raw_model(api_runs, tmp_path):
    out = tmp_path / "npz"
    res = _export(
        str(api_runs["worldtree"]), "--format", "npz", "-o", str(out), "--times", "3", "--device", "cpu"
    )
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in out.iterdir()) == ["index.json", "model.npz"]
    z = np.load(out / "model.npz")  # no pickles: every entry is a plain array
    frame = load_run(api_runs["worldtree"], device="cpu").gaussians_at(3)
    for f in ("means", "quats", "log_scales", "opacities", "sh0", "dynamic"):
        np.testing.assert_array_equal(z[f"frames/0003/{f}"], getattr(frame, f).numpy())
    assert json.loads(str(z["model/model.json"]))["method"] == "worldtree"
    for key in ("model/tree/node2/dynamic/t_ref", "model/tree/node3/scaffold/tensors/pos",
                "model/scaffold_cameras/w2cs", "model/static_gaussians/means"):  # fmt: skip
        assert key in z.files, key
    assert json.loads((out / "index.json").read_text())["times"]["3"] == {
        "file": "model.npz", "key": "frames/0003", "gaussians": len(frame), "dynamic": int(frame.dynamic.sum()),
        "node": 2,
    }  # fmt: skip


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--times", "1,x"], "--times 1,x: 'x' is not a time index; give e.g. 0,5,10 or all"),
        (["--times", "3,14"], "--times 3,14: time 14 is not one of the run's times 0..13"),
        (["--format", "obj"], "--format obj: choose ply or npz"),
    ],
)
def test_bad_options_are_one_line_errors_and_write_nothing(api_runs, tmp_path, args, message):
    out = tmp_path / "new" / "out"
    res = _export(str(api_runs["base"]), "-o", str(out), "--device", "cpu", *args)
    assert isinstance(res.exception, UserError) and str(res.exception) == message
    assert not (tmp_path / "new").exists()


def test_missing_run_is_one_error_line_with_status_2(tmp_path):
    """Through the installed entry point: `error: ...` on one line, exit status 2, nothing created."""
    res = subprocess.run(
        [sys.executable, "-m", "benchmarks.cli", "export", str(tmp_path / "no_run"), "-o", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert res.returncode == 2
    assert res.stderr.strip() == (
        f"error: {tmp_path / 'no_run'}: no such run folder; give a folder written by `wtbench run` "
        "(RUNS/SCENE/METHOD/TAG)"
    )
    assert not (tmp_path / "out").exists()
