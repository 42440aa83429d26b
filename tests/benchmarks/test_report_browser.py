"""`wtbench report` in a real headless browser: Debian's chromium and chromium-driver driven by Selenium.

The report of a generated sweep (report_fixture.py) is opened from the file system; checked: no console
error, one table row per configuration, every image loads, clicking a column header sorts the rows, the frame
viewer steps through frames, the run's video loads. Skips with one reason where the browser or Selenium is missing (`.ci/run`
installs both with apt-get/pip when it can).
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from benchmarks.cli import app


def _load(name: str):
    path = Path(__file__).with_name(f"{name}.py")
    spec = importlib.util.spec_from_file_location(f"wt_tests_{name}_browser", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


chromium = _load("chromium")
webdriver = chromium.skip_without_browser()
fx = _load("report_fixture")


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    runs, _ = fx.write_sweep(tmp_path_factory.mktemp("sweep"))
    out = tmp_path_factory.mktemp("site") / "report"
    res = CliRunner().invoke(app, ["report", str(runs), "-o", str(out)])
    assert res.exit_code == 0, res.output
    return runs, out


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    driver = chromium.start(tmp_path_factory.mktemp("chromium-profile"), 1280, 900)
    yield driver
    driver.quit()


def _open(driver, page: Path) -> None:
    driver.get(page.resolve().as_uri())
    driver.get_log("browser")  # what earlier pages logged is not this page's
    driver.refresh()


def _all_images_load(driver) -> int:
    """Scroll every visible image into view (lazy loading), wait for it, return how many loaded."""
    from selenium.webdriver.support.ui import WebDriverWait

    images = [i for i in driver.find_elements("css selector", "img") if i.is_displayed()]
    for img in images:
        driver.execute_script("arguments[0].scrollIntoView()", img)
        WebDriverWait(driver, 120).until(lambda d, i=img: d.execute_script("return arguments[0].complete", i))
        width = driver.execute_script("return arguments[0].naturalWidth", img)
        assert width > 0, f"image did not load: {img.get_attribute('src')}"
    return len(images)


def _column(driver, table_id: str, col: int) -> list[str]:
    return driver.execute_script(
        "return Array.from(document.getElementById(arguments[0]).tBodies[0].rows)"
        ".map(r => r.cells[arguments[1]].getAttribute('data-v') ?? r.cells[arguments[1]].textContent.trim())",
        table_id,
        col,
    )


def test_main_page(report, browser):
    runs, out = report
    _open(browser, out / "index.html")
    assert chromium.severe_errors(browser) == []
    rows = browser.find_elements("css selector", "#results-worldtree tbody tr")
    assert len(rows) == len(fx.CONFIGS)
    # Plots (one per metric with values) and the scene thumbnails all load.
    assert _all_images_load(browser) >= len(fx.SCENES) + 1

    # Sorting: the PSNR mean column, best first, is the fixture's configurations by rising noise
    # (an independent order: the renders are the ground truth plus that much noise).
    header = browser.find_element(
        "xpath", "//table[@id='results-worldtree']//th[contains(@title, 'PSNR: mean')]"
    )
    col = int(header.get_attribute("data-col"))
    by_noise = [c[0] for c in sorted(fx.CONFIGS, key=lambda c: c[3])]
    header.click()
    assert [float(v) for v in _column(browser, "results-worldtree", col)] == sorted(
        (float(v) for v in _column(browser, "results-worldtree", col)), reverse=True
    )
    assert _column(browser, "results-worldtree", 0) == by_noise
    header.click()  # again: reversed
    assert _column(browser, "results-worldtree", 0) == by_noise[::-1]

    # The unfinished run and the sweep's failure are listed with their state.
    states = dict(zip(_column(browser, "runs-table", 3), _column(browser, "runs-table", 4), strict=True))
    assert states["SceneA/base/quick"] == "unfinished"
    assert "out of memory" in browser.find_element("css selector", "table.failures").text

    # Hovering a cell tells its runs' protocol and checksums (the title attribute).
    record = json.loads((runs / "SceneA" / "static" / "quick" / "metrics.json").read_text())
    title = browser.find_element("css selector", "#results-worldtree td.m-psnr").get_attribute("title")
    assert "protocol: worldtree" in title and record["inputs"]["gt_sha256"][:16] in title
    # ... and the row's runs list holds them whole.
    details = browser.find_element("css selector", "#results-worldtree details.runs")
    details.click()
    assert record["inputs"]["pred_sha256"] in details.text
    assert chromium.severe_errors(browser) == []


def test_scene_page_viewer(report, browser):
    _, out = report
    _open(browser, out / "scenes" / "SceneA.html")
    assert chromium.severe_errors(browser) == []
    assert len(browser.find_elements("css selector", "#scene-worldtree tbody tr")) == len(fx.CONFIGS)
    shown = lambda: [f for f in browser.find_elements("css selector", ".frame") if f.is_displayed()]  # noqa: E731
    assert [f.get_attribute("data-name") for f in shown()] == ["v001_t000"]
    # Per frame and run: render, ground truth, mask and error map, plus the curves and the colour bar.
    assert _all_images_load(browser) == 4 * len(fx.CONFIGS) + 2
    browser.execute_script(
        "const r = document.querySelector('.frame-range'); r.value = r.max;"
        "r.dispatchEvent(new Event('input'))"
    )
    assert [f.get_attribute("data-name") for f in shown()] == [f"v001_t{fx.FRAMES - 1:03d}"]
    assert _all_images_load(browser) == 4 * len(fx.CONFIGS) + 2
    # The run's video plays here: its metadata loads, three panels (render | ground truth | mask) wide.
    from selenium.webdriver.support.ui import WebDriverWait

    video = browser.find_element("css selector", "#videos video")
    browser.execute_script("arguments[0].scrollIntoView(); arguments[0].load()", video)
    WebDriverWait(browser, 120).until(
        lambda d: d.execute_script("return arguments[0].readyState", video) >= 1
    )
    size = browser.execute_script("return [arguments[0].videoWidth, arguments[0].videoHeight]", video)
    assert size == [3 * fx.WIDTH, fx.HEIGHT]
    assert chromium.severe_errors(browser) == []


# ------------------------------------------------------------------------------- long configuration names


@pytest.fixture(scope="module")
def long_report(tmp_path_factory):
    """The fixture's sweep with imported priors and --set overrides: configuration names of 150+ characters."""
    runs, _ = fx.write_sweep(tmp_path_factory.mktemp("sweep-long"), long_names=True)
    out = tmp_path_factory.mktemp("site-long") / "report"
    res = CliRunner().invoke(app, ["report", str(runs), "-o", str(out)])
    assert res.exit_code == 0, res.output
    return runs, out


def _box(driver, element) -> dict:
    return driver.execute_script(
        "const r = arguments[0].getBoundingClientRect();"
        "return {left: r.left, right: r.right, width: r.width, height: r.height, inner: window.innerWidth}",
        element,
    )


def test_long_names_stay_legible_at_1400px(long_report, browser, tmp_path):
    """At 1400 px, with names of 150+ characters: every score column of the scene page's table is on screen,
    the per-frame plot is visible within the viewport, and the key lists every full name."""
    from benchmarks.reporting.results import describe_configuration

    runs, out = long_report
    names = {describe_configuration(json.loads(p.read_text())) for p in runs.glob("SceneA/*/*/config.json")}
    assert min(len(n) for n in names) >= 150
    browser.set_window_size(1400, 1000)
    try:
        _open(browser, out / "scenes" / "SceneA.html")
        assert browser.execute_script("return window.innerWidth") <= 1400
        assert chromium.severe_errors(browser) == []
        assert browser.execute_script("return document.documentElement.scrollWidth <= window.innerWidth")
        table = browser.find_element("css selector", "#scene-worldtree")
        scores = table.find_elements("css selector", "th.m-psnr, th[data-type='num'], td.num")
        assert len(scores) >= len(fx.CONFIGS) + 1
        for el in scores:
            assert el.is_displayed()
            box = _box(browser, el)
            assert box["width"] > 0 and box["left"] >= 0 and box["right"] <= box["inner"], box
        # The configuration column is the shortened, wrapped name; the full one is the hover text.
        keys = table.find_elements("css selector", "tbody td.key:nth-child(2)")
        assert {k.get_attribute("title") for k in keys} <= {f"{c[0]} {n}" for c in fx.CONFIGS for n in names}
        assert all(len(k.text) < 60 for k in keys)
        # The key lists every configuration on this page with its full name.
        full = [td.text for td in browser.find_elements("css selector", "table.key-table td.full")]
        assert set(full) == {f"{e.split('/')[1]} {n}" for e, n in _runs_and_names(runs)}
        # The per-frame plot: an image of real size, inside the viewport horizontally.
        img = browser.find_element("css selector", "img.curves")
        browser.execute_script("arguments[0].scrollIntoView()", img)
        from selenium.webdriver.support.ui import WebDriverWait

        WebDriverWait(browser, 60).until(lambda d: d.execute_script("return arguments[0].complete", img))
        assert browser.execute_script("return arguments[0].naturalWidth", img) > 0
        box = _box(browser, img)
        assert img.is_displayed() and box["left"] >= 0 and box["right"] <= box["inner"], box
        assert box["width"] >= 300 and box["height"] >= 150, box
        browser.save_screenshot(str(tmp_path / "scene_long_names.png"))
        assert chromium.severe_errors(browser) == []
    finally:
        browser.set_window_size(1280, 900)


def _runs_and_names(runs: Path) -> list[tuple[str, str]]:
    """(scene/method/tag, configuration name) of SceneA's run folders."""
    from benchmarks.reporting.results import describe_configuration

    return [
        (str(p.parent.relative_to(runs)), describe_configuration(json.loads(p.read_text())))
        for p in sorted(runs.glob("SceneA/*/*/config.json"))
    ]
