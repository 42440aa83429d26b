"""Ranking marks (both directions, ties, NaN), markdown/LaTeX/CSV output, and the `wtbench table` command."""

from __future__ import annotations

import importlib.util
import io
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from benchmarks.cli import app
from benchmarks.reporting.results import collect_runs
from benchmarks.reporting.tables import build_wide, latex_escape, rank_marks, to_csv, to_latex, to_markdown


def _fixture():
    path = Path(__file__).with_name("runs_fixture.py")
    spec = importlib.util.spec_from_file_location("wt_tests_runs_fixture_format", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


rf = _fixture()


def test_rank_marks_directions_ties_nan():
    nan = math.nan
    assert rank_marks([1.0, 3.0, 2.0, nan, 3.0], higher_better=True) == [3, 1, 2, None, 1]
    assert rank_marks([1.0, 3.0, 2.0, nan, 3.0], higher_better=False) == [1, 3, 2, None, 3]
    # Shown with 3 decimals, 0.1 and 0.1004 look equal, so they tie.
    assert rank_marks([0.1, 0.1004, 0.2, 0.3, 0.05], False, decimals=3) == [2, 2, 3, None, 1]
    assert rank_marks([0.1, 0.1004], False, decimals=4) == [1, 2]
    assert rank_marks([5.0, nan], True) == [None, None]  # fewer than two values: nothing marked
    assert rank_marks([nan, nan], True) == [None, None]
    assert rank_marks([math.inf, 30.0, 20.0], True) == [1, 2, 3]


@pytest.mark.parametrize("higher", [True, False])
def test_rank_marks_match_pandas_dense_rank(higher):
    rng = np.random.default_rng(1 if higher else 2)
    for _ in range(50):
        v = rng.integers(0, 6, size=rng.integers(2, 9)).astype(float)
        v[rng.random(len(v)) < 0.2] = np.nan
        want = pd.Series(v).rank(method="dense", ascending=not higher)
        if (~np.isnan(v)).sum() < 2:
            want[:] = np.nan
        expect = [int(r) if r == r and r <= 3 else None for r in want]
        assert rank_marks(v, higher) == expect


@pytest.fixture(scope="module")
def ranked(tmp_path_factory):
    """Four configurations on scene my_scene: PSNR 20, 22, 22, 19 (higher better) and LPIPS 0.1, 0.2, 0.3,
    missing (lower better)."""
    root = tmp_path_factory.mktemp("runs")
    for name, psnr, lpips in (("a", 20.0, 0.1), ("b", 22.0, 0.2), ("c", 22.0, 0.3), ("d", 19.0, math.nan)):
        rf.write_run(root, "my_scene", "m", name, {"psnr": psnr, "lpips": lpips}, preset=name)
    return root


def _markdown_rows(text: str) -> tuple[list[str], dict[str, list[str]]]:
    lines = [ln for ln in text.splitlines() if ln.startswith("|")]
    split = [[c.strip() for c in ln.strip("|").split(" | ")] for ln in lines]
    header, rows = split[0], split[2:]
    assert all(len(r) == len(header) for r in rows)
    return header, {r[1]: r for r in rows}


def test_markdown_marks_in_the_right_cells(ranked):
    table = build_wide(collect_runs([ranked]).long, metrics=("psnr", "lpips"))
    text = to_markdown(table)
    header, rows = _markdown_rows(text)
    assert header[:2] == ["method", "configuration"]
    ps, lp = header.index("PSNR↑ my_scene"), header.index("LPIPS↓ mean")
    assert [rows[c][ps] for c in "abcd"] == ["<u>20.00</u>", "**22.00**", "**22.00**", "*19.00*"]
    assert [rows[c][lp] for c in "abcd"] == ["**0.100**", "<u>0.200</u>", "*0.300*", "-"]
    assert "mean = average over my_scene." in text


def test_latex_marks_escapes_and_shape(ranked):
    table = build_wide(collect_runs([ranked]).long, metrics=("psnr", "lpips"))
    text = to_latex(table)
    assert "\\definecolor{first}{RGB}{255, 204, 201}" in text
    spec = text.split("\\begin{tabular}{", 1)[1].split("}", 1)[0]
    n_cols = spec.count("l") + spec.count("c")
    assert n_cols == 2 + 2 * 2
    assert "my\\_scene" in text and "mean over my\\_scene" in text
    body = {}
    for ln in text.splitlines():
        cells = [c.strip() for c in ln.removesuffix("\\\\").split(" & ")]
        if cells[0] == "m":
            assert len(cells) == n_cols
            body[cells[1]] = cells
    assert (
        body["b"][2] == "\\cellcolor{first}\\textbf{22.00}"
        and body["c"][3] == "\\cellcolor{first}\\textbf{22.00}"
    )
    assert body["a"][2] == "\\cellcolor{second}20.00" and body["d"][2] == "\\cellcolor{third}19.00"
    assert body["a"][4] == "\\cellcolor{first}\\textbf{0.100}" and body["c"][5] == "\\cellcolor{third}0.300"
    assert body["d"][4] == "-"
    assert latex_escape("a_b & 50% #1 {x} ~^\\") == (
        "a\\_b \\& 50\\% \\#1 \\{x\\} \\textasciitilde{}\\textasciicircum{}\\textbackslash{}"
    )


def test_csv_round_trips_full_precision(ranked):
    table = build_wide(collect_runs([ranked]).long, metrics=("psnr", "lpips"))
    back = pd.read_csv(io.StringIO(to_csv(table)))
    assert list(back.columns) == list(table.frame.columns)
    np.testing.assert_allclose(back["lpips:my_scene"], [0.1, 0.2, 0.3, np.nan])


def test_cli_writes_wide_and_long(ranked, tmp_path):
    out = tmp_path / "t" / "table.md"
    res = CliRunner().invoke(
        app, ["table", str(ranked), "-o", str(out), "--metrics", "psnr"], catch_exceptions=False
    )
    assert res.exit_code == 0, res.output
    text = out.read_text()
    assert "**22.00**" in text and "PSNR↑ mean" in text and "LPIPS" not in text
    long = pd.read_csv(tmp_path / "t" / "table_long.csv")
    want = collect_runs([ranked]).long
    assert len(long) == len(want)
    np.testing.assert_allclose(
        long.sort_values(["tag", "metric"])["value"], want.sort_values(["tag", "metric"])["value"]
    )
    tex = tmp_path / "t.tex"
    res = CliRunner().invoke(
        app, ["table", str(ranked), "-o", str(tex), "--mean-only"], catch_exceptions=False
    )
    assert res.exit_code == 0 and tex.read_text().startswith("% wtbench table")
    csv = tmp_path / "w.csv"
    res = CliRunner().invoke(app, ["table", str(ranked), "-o", str(csv), "--group-by", "method"])
    assert res.exit_code == 0
    assert pd.read_csv(csv)["psnr:mean(my_scene)"].tolist() == pytest.approx([(20 + 22 + 22 + 19) / 4])


def test_cli_empty_runs_dir_is_one_line_error(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.cli", "table", str(tmp_path)], capture_output=True, text=True
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: RUNS_DIR") and "wtbench run" in lines[0]


def test_explicit_empty_metric_and_infinity(tmp_path):
    rf.write_run(tmp_path, "S", "m", "a", {"psnr": math.inf}, preset="a")
    rf.write_run(tmp_path, "S", "m", "b", {"psnr": 30.0}, preset="b")
    got = collect_runs([tmp_path])
    assert any("infinite psnr" in n for n in got.notes)
    table = build_wide(got.long, metrics=("psnr", "lpips"))
    assert table.frame["lpips:mean(S)"].isna().all()  # asked for, so kept, and empty
    _, rows = _markdown_rows(to_markdown(table))
    assert rows["a"][2:] == ["**inf**", "**inf**", "-", "-"]
    assert rows["b"][2:] == ["<u>30.00</u>", "<u>30.00</u>", "-", "-"]
    assert "inf" in to_csv(table).splitlines()[1]
