"""benchmarks.reporting.plots: Pareto front against brute force, metric fallback, points, PNG output, `wtbench plot`."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from benchmarks.cli import app
from benchmarks.reporting.plots import (
    Panel,
    draw,
    figure,
    make_panel,
    pareto_front,
    resolve_y,
    short_labels,
    with_derived,
)
from benchmarks.reporting.results import collect_runs
from worldtree.infra.errors import UserError


def _fixture():
    path = Path(__file__).with_name("runs_fixture.py")
    spec = importlib.util.spec_from_file_location("wt_tests_runs_fixture_plot", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


rf = _fixture()


def _brute_front(x, y, x_higher, y_higher):
    sx, sy = (-1 if x_higher else 1), (-1 if y_higher else 1)
    out = []
    for i in range(len(x)):
        if math.isnan(x[i]) or math.isnan(y[i]):
            out.append(False)
            continue
        dominated = any(
            not (math.isnan(x[j]) or math.isnan(y[j]))
            and sx * x[j] <= sx * x[i]
            and sy * y[j] <= sy * y[i]
            and (sx * x[j] < sx * x[i] or sy * y[j] < sy * y[i])
            for j in range(len(x))
        )
        out.append(not dominated)
    return out


@pytest.mark.parametrize("x_higher,y_higher", [(False, False), (False, True), (True, False), (True, True)])
def test_pareto_front_matches_brute_force(x_higher, y_higher):
    rng = np.random.default_rng(3 + 2 * x_higher + y_higher)
    for _ in range(200):
        n = int(rng.integers(1, 12))
        x = rng.integers(0, 5, n).astype(float)  # small integer ranges: many ties and duplicates
        y = rng.integers(0, 5, n).astype(float)
        x[rng.random(n) < 0.1] = np.nan
        got = pareto_front(x, y, x_higher, y_higher)
        assert got.tolist() == _brute_front(x.tolist(), y.tolist(), x_higher, y_higher)


def test_pareto_front_small_cases():
    assert pareto_front([], []).tolist() == []
    assert pareto_front([1.0, 2.0, 3.0], [3.0, 2.0, 1.0]).tolist() == [True, True, True]
    assert pareto_front([1.0, 2.0], [1.0, 2.0]).tolist() == [True, False]
    assert pareto_front([1.0, 1.0], [2.0, 2.0]).tolist() == [True, True]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Three configurations on two scenes, no LPIPS: (train seconds, mPSNR, PSNR) per scene."""
    root = tmp_path_factory.mktemp("runs")
    spec = {
        "fast": {"A": (5.0, 14.0, 20.0), "B": (7.0, 15.0, 21.0)},
        "slow": {"A": (50.0, 18.0, 24.0), "B": (70.0, 17.0, 23.0)},
        "bad": {"A": (60.0, 13.0, 19.0), "B": (80.0, 12.0, 18.0)},
    }
    for preset, scenes in spec.items():
        for scene, (t, mpsnr, psnr) in scenes.items():
            rf.write_run(
                root,
                scene,
                "m",
                preset,
                {"mpsnr": mpsnr, "psnr": psnr},
                preset=preset,
                train_s=t,
                other_stages_s=0.0,
            )
    return root, spec


def test_fallback_and_points(runs):
    root, spec = runs
    long = with_derived(collect_runs([root]).long)
    y, notes = resolve_y(long, None, "mavge")
    assert y == "mmse" and "plotting mmse instead" in notes[0]
    assert resolve_y(long, None, "lpips")[0] == "mse"
    with pytest.raises(UserError, match="--y lpips"):
        resolve_y(long, "lpips", "lpips")
    panel = make_panel(long, "wall_time_s", "mmse")
    assert panel.scenes == ("A", "B")
    pts = panel.points.set_index("configuration")
    for preset, scenes in spec.items():
        # Independent: per-scene masked MSE 10^(-mPSNR/10), then the mean over scenes; time likewise.
        want_y = np.mean([10 ** (-v[1] / 10) for v in scenes.values()])
        want_x = np.mean([v[0] for v in scenes.values()])
        assert pts.loc[preset, "y"] == pytest.approx(want_y)
        assert pts.loc[preset, "x"] == pytest.approx(want_x)
    assert pts["pareto"].to_dict() == {"bad": False, "fast": True, "slow": True}
    # PSNR (higher is better) on y: "slow" still dominates "bad".
    p2 = make_panel(long, "wall_time_s", "psnr").points.set_index("configuration")
    assert p2["pareto"].to_dict() == {"bad": False, "fast": True, "slow": True}


def test_draw_png(runs, tmp_path):
    root, _ = runs
    long = with_derived(collect_runs([root]).long)
    out = tmp_path / "p" / "speed.png"
    draw([make_panel(long, "wall_time_s", "mmse"), make_panel(long, "wall_time_s", "mse")], out, dpi=60)
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[1] > img.shape[0] > 100  # two panels side by side
    assert img.std() > 0  # something was drawn
    with pytest.raises(UserError, match="-o"):
        draw([make_panel(long, "wall_time_s", "mse")], tmp_path / "p.jpg2")


def test_short_labels_keep_what_differs():
    labels = ["worldtree quick depth=0 split=binary masks=m", "worldtree quick depth=auto split=binary masks=m",
              "worldtree quick depth=2 split=flow masks=m"]  # fmt: skip
    assert short_labels(labels) == ["depth=0 split=binary", "depth=auto split=binary", "depth=2 split=flow"]
    assert short_labels(["static quick", "worldtree quick"]) == ["static", "worldtree"]
    # One label, or labels with nothing of their own, stay whole.
    assert short_labels(["worldtree quick"]) == ["worldtree quick"]
    assert short_labels(["a b", "b a"]) == ["a b", "b a"]


def test_long_labels_do_not_shrink_the_axes():
    # Session 5's sweep labels ran to ~90 characters and squeezed each axes into a sliver of its panel.
    tail = " split=binary depth_maps=depth masks=masks tracks=tracks.npz" * 3
    points = pd.DataFrame(
        {"method": ["worldtree"] * 3, "configuration": [f"quick depth={d}{tail}" for d in ("0", "1", "auto")],
         "x": [278.0, 477.0, 253.0], "y": [17.11, 16.89, 17.29], "pareto": [False, False, True]}
    )  # fmt: skip
    points["label"] = points["method"] + " " + points["configuration"]
    fig = figure(
        [Panel(points, "wall_time_s", "mpsnr", ("s",)), Panel(points, "n_gaussians", "mpsnr", ("s",))]
    )
    fig.canvas.draw()
    for ax in fig.axes:
        assert ax.get_position().width > 0.3  # of the figure: each axes keeps most of its half
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert sorted(texts) == ["depth=0", "depth=1", "depth=auto"]
    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:  # every label, the rightmost point's included, lies inside the figure
        for t in ax.texts:
            box = t.get_window_extent(renderer)
            assert (
                fig.bbox.x0 <= box.x0
                and box.x1 <= fig.bbox.x1
                and fig.bbox.y0 <= box.y0
                and box.y1 <= fig.bbox.y1
            )


def test_cli_plot(runs, tmp_path):
    root, _ = runs
    out = tmp_path / "sve.png"
    res = CliRunner().invoke(app, ["plot", str(root), "-o", str(out)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert out.read_bytes()[:4] == b"\x89PNG"
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("  ")]
    starred = sorted(ln.split()[2] for ln in lines if ln.lstrip().startswith("*"))
    assert starred == ["fast", "fast", "slow", "slow"]  # two panels (mmse, mse), same front
    res = CliRunner().invoke(
        app, ["plot", str(root), "-o", str(tmp_path / "x.svg"), "--y", "psnr", "--x", "n_gaussians"]
    )
    assert res.exit_code == 0 and (tmp_path / "x.svg").read_text().lstrip().startswith("<?xml")
    res = CliRunner().invoke(
        app,
        ["plot", str(root), "-o", str(tmp_path / "t.svg"), "--y", "psnr", "--x", "wall_time_s,n_gaussians"],
    )
    assert res.exit_code == 0, res.output
    heads = [ln for ln in res.stdout.splitlines() if " vs " in ln]
    assert [h.split(" (")[0] for h in heads] == ["wall_time_s vs psnr", "n_gaussians vs psnr"]


def test_plot_cpu_time_axis(tmp_path):
    # "loaded" ran on a busy machine: longer wall time, less CPU than "idle", at the same score.
    for tag, wall, cpu, psnr in (("loaded", 90.0, 20.0, 20.0), ("idle", 30.0, 30.0, 20.0)):
        rf.write_run(tmp_path, "A", "m", tag, {"psnr": psnr}, preset=tag, train_s=wall, other_stages_s=0.0,
                     train_cpu_s=cpu)  # fmt: skip
    long = collect_runs([tmp_path]).long
    cpu = make_panel(long, "cpu_time_s", "psnr").points.set_index("configuration")
    wall = make_panel(long, "wall_time_s", "psnr").points.set_index("configuration")
    # CPU seconds: load 0.5 + train (eval left out); wall: train only (other stages 0, eval left out).
    assert cpu.loc["loaded", "x"] == pytest.approx(20.5) and cpu.loc["idle", "x"] == pytest.approx(30.5)
    assert wall.loc["loaded", "x"] == pytest.approx(90.0)
    assert bool(cpu.loc["loaded", "pareto"]) and not bool(cpu.loc["idle", "pareto"])
    assert bool(wall.loc["idle", "pareto"]) and not bool(wall.loc["loaded", "pareto"])
    res = CliRunner().invoke(
        app, ["plot", str(tmp_path), "-o", str(tmp_path / "c.svg"), "--y", "psnr", "--x", "wall_time_s,cpu_time_s"]
    )
    assert res.exit_code == 0, res.output
    heads = [ln for ln in res.stdout.splitlines() if " vs " in ln]
    assert [h.split(" (")[0] for h in heads] == ["wall_time_s vs psnr", "cpu_time_s vs psnr"]
