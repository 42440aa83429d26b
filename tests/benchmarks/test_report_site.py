"""`wtbench report` without a browser: what the site holds, run states, bad input, atomic replacement.
The page's behaviour in a real browser is tested in test_report_browser.py."""

from __future__ import annotations

import importlib.util
import json
import shutil
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from benchmarks.cli import app
from benchmarks.reporting.webreport import site
from benchmarks.reporting.webreport.images import ERROR_VMAX, error_map, fit_width, mask_view
from worldtree.infra.folder_lock import FolderLock


def _fixture():
    path = Path(__file__).with_name("report_fixture.py")
    spec = importlib.util.spec_from_file_location("wt_tests_report_fixture_site", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


fx = _fixture()


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    return fx.write_sweep(tmp_path_factory.mktemp("sweep"))


@pytest.fixture(scope="module")
def report(sweep, tmp_path_factory):
    """The report of the sweep, written by the command line."""
    out = tmp_path_factory.mktemp("report") / "report"
    res = CliRunner().invoke(app, ["report", str(sweep[0]), "-o", str(out)])
    assert res.exit_code == 0, res.output
    return out


@pytest.fixture
def no_plots(monkeypatch):
    """Skip matplotlib in tests about other things (the plots are drawn in the report fixture)."""
    monkeypatch.setattr(site, "_speed_plots", lambda *a, **k: ([], []))
    monkeypatch.setattr(site, "_curves", lambda *a, **k: False)


class _Rows(HTMLParser):
    """Text of each body row of the table with id ``table_id``, and every img src of the page."""

    def __init__(self, table_id: str):
        super().__init__()
        self.table_id, self.depth, self.in_body = table_id, 0, False
        self.rows: list[list[str]] = []
        self.imgs: list[str] = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.imgs.append(a["src"])
        if tag == "table" and a.get("id") == self.table_id:
            self.depth = 1
        elif tag == "table" and self.depth:
            self.depth += 1
        if self.depth == 1 and tag == "tbody":
            self.in_body = True
        if self.in_body and self.depth == 1 and tag == "tr":
            self.rows.append([])

    def handle_endtag(self, tag):
        if tag == "table" and self.depth:
            self.depth -= 1
        if tag == "tbody" and self.depth == 1:
            self.in_body = False

    def handle_data(self, data):
        if self.in_body and self.rows and data.strip():
            self.rows[-1].append(data.strip())


def _parse(path: Path, table_id: str) -> _Rows:
    p = _Rows(table_id)
    p.feed(path.read_text())
    return p


def test_report_lists_every_configuration_and_state(sweep, report):
    runs, out = sweep[0], report
    index = _parse(out / "index.html", "results-worldtree")
    # One row per configuration, keyed (method, configuration): the fixture's three, not the unfinished fourth.
    assert len(index.rows) == len(fx.CONFIGS)
    assert sorted(r[0] for r in index.rows) == sorted(c[0] for c in fx.CONFIGS)
    # Every image the page names exists in the report folder (self-contained: no absolute or remote path).
    for src in index.imgs:
        assert not src.startswith(("/", "http:", "https:", "file:")), src
        assert (out / src).is_file(), src
    runs_rows = _parse(out / "index.html", "runs-table").rows
    states = {r[3]: r[4] for r in runs_rows}  # folder -> state
    assert states["SceneA/base/quick"] == "unfinished"
    assert sum(s == "done" for s in states.values()) == len(fx.SCENES) * len(fx.CONFIGS)
    html = (out / "index.html").read_text()
    assert "out of memory" in html  # the sweep report's failure is listed
    # The hover text of the cells names each run's checksums, as its evaluation record holds them.
    record = json.loads((runs / "SceneA" / "static" / "quick" / "metrics.json").read_text())
    assert record["inputs"]["pred_sha256"] in html
    for scene in fx.SCENES:
        page = out / "scenes" / f"{scene}.html"
        parsed = _parse(page, "scene-worldtree")
        assert len(parsed.rows) == len(fx.CONFIGS)
        for src in parsed.imgs:
            assert (page.parent / src).resolve().is_file(), src
        # Viewer: every test frame (4 <= --viewer-frames), each with render | gt | mask | error for every run.
        text = page.read_text()
        assert text.count('class="frame"') == fx.FRAMES
        assert len(list((out / "img" / scene).glob("*_e*.jpg"))) == fx.FRAMES * len(fx.CONFIGS)


def test_video_is_reencoded_for_browsers(sweep, report, tmp_path):
    import cv2

    from benchmarks.reporting.video import to_webm

    webm = sorted((report / "videos").glob("*.webm"))
    assert len(webm) == 1
    cap = cv2.VideoCapture(str(webm[0]))
    n = 0
    while (frame := cap.read()[1]) is not None:
        assert frame.shape == (fx.HEIGHT, 3 * fx.WIDTH, 3)
        n += 1
    assert n == fx.FRAMES
    (tmp_path / "bad.mp4").write_bytes(b"not a video")
    assert to_webm(tmp_path / "bad.mp4", tmp_path / "bad.webm") == 0
    assert not (tmp_path / "bad.webm").exists()


def test_running_and_stopped_runs_are_named(sweep, tmp_path, no_plots):
    runs, _ = sweep
    run = runs / "SceneA" / "base" / "quick"
    with FolderLock(run, "run folder"):
        site.build_report([runs], tmp_path / "r", log=lambda s: None)
    rows = _parse(tmp_path / "r" / "index.html", "runs-table").rows
    assert {r[3]: r[4] for r in rows}["SceneA/base/quick"] == "running"
    # Stopped after a checkpoint: unfinished, with the step it resumes from.
    (run / "checkpoints").mkdir()
    for step in (4, 12):
        (run / "checkpoints" / f"ckpt_{step:07d}.pt").write_bytes(b"")
    try:
        site.build_report([runs], tmp_path / "r", log=lambda s: None)
    finally:
        shutil.rmtree(run / "checkpoints")
    rows = _parse(tmp_path / "r" / "index.html", "runs-table").rows
    row = next(r for r in rows if r[3] == "SceneA/base/quick")
    assert row[4] == "unfinished" and "step 12" in row[5]
    # A sweep job that failed (its job record, as `wtbench sweep` writes it): failed, with the error and job id.
    job = {"executor": "local", "job_id": "4242", "state": "failed", "error": "CUDA out of memory"}
    (run / "job.json").write_text(json.dumps({"jobs": [job]}))
    try:
        site.build_report([runs], tmp_path / "r", log=lambda s: None)
    finally:
        (run / "job.json").unlink()
    rows = _parse(tmp_path / "r" / "index.html", "runs-table").rows
    row = next(r for r in rows if r[3] == "SceneA/base/quick")
    assert row[4] == "failed" and "CUDA out of memory" in row[5] and "job 4242" in row[5]


def test_viewer_frames_are_evenly_spaced():
    assert site._pick(10, 0) == list(range(10))
    assert site._pick(10, 4) == [0, 3, 6, 9]
    assert site._pick(3, 5) == [0, 1, 2]


def test_error_map_scale_and_thumbnail_size():
    from matplotlib import colormaps

    gt = np.full((4, 6, 3), 100, np.uint8)
    pred = gt.copy()
    pred[0, 0] = 255  # error 155/255 > ERROR_VMAX: saturated
    pred[1, 1] = 100 + round(0.5 * ERROR_VMAX * 255)  # half the scale
    heat = error_map(pred, gt)
    cmap = colormaps["magma"]
    expect = lambda x: np.round(np.array(cmap(x)[:3]) * 255)  # noqa: E731
    assert np.abs(heat[2, 2] - expect(0.0)).max() <= 1
    assert np.abs(heat[0, 0] - expect(1.0)).max() <= 1
    assert np.abs(heat[1, 1] - expect(0.5)).max() <= 3  # the pixel's error is rounded to a grey level
    # Scaled down, the map shows the mean of the per-pixel errors (noise +-40 everywhere: 40/255), not the
    # error of scaled-down images (which would average the noise away).
    checker = np.where((np.indices((8, 8)).sum(0) % 2)[..., None] == 1, 140, 60).astype(np.uint8)
    small = error_map(np.repeat(checker, 3, axis=2), np.full((8, 8, 3), 100, np.uint8), width=4)
    assert small.shape == (4, 4, 3)
    assert np.abs(small - expect(40 / 255 / ERROR_VMAX)).max() <= 2
    assert fit_width(np.zeros((90, 160, 3), np.uint8), 80).shape == (45, 80, 3)
    # The mask column: scored pixels as they are, the others at a quarter of their value.
    m = np.zeros((4, 6), bool)
    m[1:3, 2:5] = True
    shown = mask_view(np.full((4, 6, 3), 200, np.uint8), m)
    assert (shown[m] == 200).all() and (shown[~m] == 50).all()
    assert fit_width(np.zeros((9, 16, 3), np.uint8), 80).shape == (9, 16, 3)  # never scaled up


def test_bad_input_is_one_line_and_writes_nothing(sweep, tmp_path, no_plots):
    runs, _ = sweep
    cli = CliRunner()
    res = cli.invoke(app, ["report", str(tmp_path / "nowhere"), "-o", str(tmp_path / "r")])
    assert res.exit_code != 0 and "RUNS_DIR" in str(res.exception or res.output)
    other = tmp_path / "mine"
    other.mkdir()
    (other / "keep.txt").write_text("x")
    with pytest.raises(Exception, match="not a wtbench report"):
        site.build_report([runs], other, log=lambda s: None)
    assert sorted(p.name for p in other.iterdir()) == ["keep.txt"]
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(Exception, match="no run folder"):
        site.build_report([empty], tmp_path / "r2", log=lambda s: None)
    assert not (tmp_path / "r2").exists()


def test_interrupted_build_leaves_the_old_report(sweep, report, tmp_path, monkeypatch):
    runs, _ = sweep
    out = tmp_path / "report"
    shutil.copytree(report, out)
    before = (out / "index.html").read_text()

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(site, "_speed_plots", boom)
    with pytest.raises(KeyboardInterrupt):
        site.build_report([runs], out, log=lambda s: None)
    assert (out / "index.html").read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["report"]  # no temporary folder left behind


def test_scenes_whose_names_slug_alike_get_a_page_each(sweep, tmp_path, no_plots):
    """``A b`` and ``A_b`` (and ``a_b`` on a case-insensitive file system) would share one page, one image
    folder and one set of viewer images if the file names were the slugs alone."""
    runs, _ = sweep
    mixed = tmp_path / "runs"
    for src, dst in (("SceneA", "A b"), ("SceneB", "A_b"), ("SceneB", "a_b")):
        shutil.copytree(runs / src, mixed / dst)
    site.build_report([mixed], tmp_path / "r", log=lambda s: None)
    index = (tmp_path / "r" / "index.html").read_text()
    pages = sorted(p.name for p in (tmp_path / "r" / "scenes").iterdir())
    assert len(pages) == 3, pages
    assert "A_b.html" in pages  # a name that is already safe keeps it
    for name in ("A b", "A_b", "a_b"):
        page = next(p for p in (tmp_path / "r" / "scenes").iterdir() if f"<h1>{name}</h1>" in p.read_text())
        assert f'href="scenes/{page.name}"' in index
        for src in _parse(page, "scene-worldtree").imgs:
            assert (page.parent / src).resolve().is_file(), src
    assert len(list((tmp_path / "r" / "img").iterdir())) == 3
    # Unique names: different texts never share one, safe texts keep theirs, hashed ones are stable.
    names = site.unique_slugs(["A b", "A_b", "a_b", "A:b", "x" * 300])
    assert len(set(n.lower() for n in names.values())) == 5 and names["A_b"] == "A_b"
    assert names == site.unique_slugs(reversed(list(names)))
    assert all(len(n) < 140 for n in names.values())


def test_nan_and_infinite_metrics_are_missing_and_said_once(sweep, tmp_path, no_plots):
    """NaN or infinite values written into runs (an infinite SSIM, a -inf wall time) are shown as missing,
    never ranked, with one note naming the runs; +inf PSNR (a render equal to its ground truth) stays."""
    import csv

    from benchmarks.reporting.results import collect_runs

    runs, _ = sweep
    bad = tmp_path / "runs"
    shutil.copytree(runs, bad)
    for scene in fx.SCENES:
        run = bad / scene / "static" / "quick"
        rows = list(csv.reader((run / "metrics.csv").open()))
        head = rows[0]
        for r in rows[1:]:
            r[head.index("psnr")], r[head.index("ssim")], r[head.index("mpsnr")] = "inf", "inf", "nan"
        with (run / "metrics.csv").open("w", newline="") as f:
            csv.writer(f).writerows(rows)
        timing = json.loads((run / "timing.json").read_text())
        timing.update(total_s=float("-inf"), sessions_s=[1.0])
        (run / "timing.json").write_text(json.dumps(timing))
    found = collect_runs([bad])
    v = found.long.set_index(["run", "metric"])["value"]
    run_a = str(bad / "SceneA" / "static" / "quick")
    assert v[(run_a, "psnr")] == float("inf")
    assert np.isnan(v[(run_a, "ssim")]) and np.isnan(v[(run_a, "mpsnr")]) and np.isnan(v[(run_a, "wall_time_s")])
    notes = site.build_report([bad], tmp_path / "r", log=lambda s: None)
    said = [n for n in notes if "NaN or infinite" in n]
    assert len(said) == 1 and "SceneA/static/quick (ssim, mpsnr, wall_time_s)" in said[0], notes
    # In the static row only the three PSNR cells (two scenes and the mean) are infinite; SSIM, mPSNR and
    # the wall time are missing ("-"), not inf or -inf.
    rows = _parse(tmp_path / "r" / "index.html", "results-worldtree").rows
    cells = next(r for r in rows if r[0] == "static")
    assert [c.lower() for c in cells].count("inf") == 3 and "-inf" not in [c.lower() for c in cells], cells


def test_partial_folders_of_a_killed_report_are_removed_next_time(sweep, tmp_path, no_plots):
    """A report killed while writing leaves ``.OUT.XXXXXXXX.partial``; the next report removes it once its
    writer (named in the folder's marker) is gone, and keeps a live writer's, an unmarked recent one and
    folders not named like its own."""
    import os
    import socket
    import subprocess
    import sys

    runs, _ = sweep
    out = tmp_path / "report"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()

    def partial(name: str, pid: int | None) -> Path:
        p = tmp_path / name
        (p / "scenes").mkdir(parents=True)
        if pid is not None:
            doc = {"pid": pid, "host": socket.gethostname(), "since": 0}
            (p / site.PARTIAL_MARKER).write_text(json.dumps(doc))
        return p

    killed = partial(".report.abcd1234.partial", dead.pid)
    live = partial(".report.live5678.partial", os.getpid())
    unmarked = partial(".report.zzzz0000.partial", None)
    other = partial(".report2.abcd1234.partial", dead.pid)
    old_unmarked = partial(".report.old00000.partial", None)
    os.utime(old_unmarked, (0, 0))
    site.build_report([runs], out, log=lambda s: None)
    assert not killed.exists() and not old_unmarked.exists()
    assert live.exists() and unmarked.exists() and other.exists()
    assert not (out / site.PARTIAL_MARKER).exists() and (out / site.MARKER).is_file()
