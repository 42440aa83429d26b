"""benchmarks.speed.object_size_depth: mask pieces in closed form, and the size + path cues on a tiny generated
scene against its own ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest
from typer.testing import CliRunner

from benchmarks.speed.object_size_depth import main, measure_scene, object_pieces
from nvidia_ls.cli import app


def _disc(mask: np.ndarray, cx: float, cy: float, r: float) -> None:
    yy, xx = np.mgrid[: mask.shape[0], : mask.shape[1]]
    mask |= (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r


def test_pieces_take_their_nearest_object_and_skip_merges_noise_and_flag_the_border():
    m = np.zeros((40, 80), bool)
    _disc(m, 20, 20, 5)
    _disc(m, 60, 20, 3)
    m[35:37, 40:42] = True  # 4 px of noise: below MIN_AREA
    got = object_pieces(m, np.array([[21.0, 19.0], [59.0, 21.0]]))
    assert set(got) == {0, 1}
    (c0, a0, b0), (c1, a1, b1) = got[0], got[1]
    np.testing.assert_allclose(c0, [20, 20], atol=1e-9)  # symmetric disc: centroid at its centre
    assert a0 == m[:, :40].sum() and not b0
    np.testing.assert_allclose(c1, [60, 20], atol=1e-9)
    assert a1 == np.count_nonzero(m[:, 50:]) and not b1
    # both centres inside one piece: neither object is measured this frame
    assert object_pieces(m, np.array([[19.0, 20.0], [22.0, 21.0]])) == {}
    # a piece cut by the image border is kept but flagged
    e = np.zeros((40, 80), bool)
    _disc(e, 2, 20, 6)
    assert object_pieces(e, np.array([[3.0, 20.0]]))[0][2] is True
    assert object_pieces(np.zeros((40, 80), bool), np.array([[3.0, 20.0]])) == {}


@pytest.fixture(scope="module")
def family(tmp_path_factory):
    """A 12-frame arc rig with a sphere and a box on straight paths, 64x36, exact poses and priors."""
    root = tmp_path_factory.mktemp("size_family")
    raw, scenes = root / "raw" / "tiny", root / "scenes"
    r = CliRunner()
    for args in (
        ["synth", str(raw), "--steps", "12", "--width", "64", "--height", "36", "--rig", "arc"]
        + ["--path", "straight", "--depth", "--supersample", "1"],
        ["build", str(raw), "-o", str(scenes), "--name", "tiny", "--frames", "12"]
        + ["--poses", str(raw / "gt" / "poses_bounds.npy")],
        ["gt-priors", str(raw), str(scenes / "tiny")],
    ):
        res = r.invoke(app, args)
        assert res.exit_code == 0, res.output
    return root


def test_a_sphere_on_a_straight_path_is_placed_by_its_size_and_its_path(family):
    rows = {r["object"]: r for r in measure_scene(family / "scenes" / "tiny", family / "raw" / "tiny")}
    s = rows["sphere"]
    assert s["frames"] >= 4
    # a sphere's outline is its depth up to a factor (a pixel-counted area at 64x36: a few per cent)
    assert s["size"] < 0.05
    # the arc's cameras accelerate: the path measures the factor, and says it could
    assert s["path_exact"] < 0.05 and s["path_exact_fit"] > 0.95
    assert s["path"] < 0.1 and s["path_fit"] > 0.9
    assert math.isfinite(rows["box"]["size"])


def test_cli_prints_a_row_per_object_and_refuses_a_folder_without_scenes(family, tmp_path, capsys):
    main([str(family), "tiny", "--json", str(tmp_path / "rows.json")])
    out = capsys.readouterr().out
    assert "| tiny | sphere |" in out and "| tiny | box |" in out
    assert (tmp_path / "rows.json").is_file()
    (tmp_path / "scenes").mkdir()
    with pytest.raises(SystemExit, match="no scenes"):
        main([str(tmp_path)])
