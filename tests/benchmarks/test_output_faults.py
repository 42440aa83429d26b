"""`wtbench table` and `wtbench eval` under bad files: an output path under a regular file is refused before
any work, and a run with an unreadable metrics.csv or timing.json is named and skipped."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks.reporting.results import collect_runs
from worldtree.imageio import write_image
from worldtree.infra.errors import UserError

_spec = importlib.util.spec_from_file_location(
    "wt_tests_runs_fixture_faults", Path(__file__).with_name("runs_fixture.py")
)
rf = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(rf)

MEANS = {"psnr": 24.5, "ssim": 0.81, "mpsnr": 18.0, "mssim": 0.6}


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "benchmarks.cli", *args], capture_output=True, text=True)


def _one_line_error(out: subprocess.CompletedProcess, needle: str) -> str:
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1, out.stderr
    assert lines[0].startswith("error: ") and needle in lines[0], out.stderr
    return lines[0]


def test_garbage_metrics_csv_is_named_when_it_was_the_only_run(tmp_path):
    run = rf.write_run(tmp_path, "Truck", "static", "quick", MEANS)
    run.metrics_csv.write_bytes(b"\x00\xff garbage \x89PNG\n,,,\n")
    with pytest.raises(
        UserError, match=r"no readable finished run; skipped .*Truck/static/quick \(metrics\.csv"
    ):
        collect_runs([tmp_path])


def test_corrupt_timing_json_is_named_and_that_run_skipped(tmp_path):
    rf.write_run(tmp_path, "Balloon1", "static", "quick", MEANS)
    bad = rf.write_run(tmp_path, "Truck", "static", "quick", MEANS)
    bad.timing_json.write_text('{"stages_s": {"train": 1')  # cut short
    got = collect_runs([tmp_path])
    assert set(got.long["scene"]) == {"Balloon1"}
    assert any("Truck" in n and "unreadable timing.json" in n for n in got.notes), got.notes
    # A run without timing.json at all is still listed (its cost columns stay empty).
    bad.timing_json.unlink()
    got = collect_runs([tmp_path])
    assert set(got.long["scene"]) == {"Balloon1", "Truck"}


def test_table_output_under_a_regular_file_is_refused(tmp_path):
    rf.write_run(tmp_path / "runs", "Truck", "static", "quick", MEANS)
    (tmp_path / "file").write_text("keep")
    _one_line_error(
        _cli("table", str(tmp_path / "runs"), "-o", str(tmp_path / "file" / "t.csv")), "is a file"
    )
    assert (tmp_path / "file").read_text() == "keep"


def test_eval_output_under_a_regular_file_is_refused_before_scoring(tmp_path):
    rng = np.random.default_rng(0)
    for d in ("pred", "gt"):
        (tmp_path / d).mkdir()
        write_image(tmp_path / d / "v001_t000.png", rng.integers(0, 256, (24, 32, 3), dtype=np.uint8))
    (tmp_path / "file").write_text("keep")
    out = _cli(
        "eval",
        str(tmp_path / "pred"),
        "--gt",
        str(tmp_path / "gt"),
        "--out",
        str(tmp_path / "file" / "m.csv"),
    )
    _one_line_error(out, "is a file")
    assert "scoring" not in out.stdout + out.stderr.replace("error:", "")
