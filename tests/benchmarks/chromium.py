"""Headless Debian chromium for the browser tests (report and viewer), loaded by path like report_fixture.py.

``skip_without_browser()`` skips the calling test module with one reason when chromium, its driver or
Selenium is missing (`.ci/run` installs them when it can); ``start(profile, width, height, performance)``
opens a driver with an explicit driver path, so Selenium Manager (which would download one) never runs.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")


def skip_without_browser():
    """The ``selenium.webdriver`` module, or a module-level skip naming what is missing."""
    if not (CHROMIUM and CHROMEDRIVER):
        pytest.skip(
            "no chromium/chromedriver on PATH (install: apt-get install chromium chromium-driver)",
            allow_module_level=True,
        )
    return pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install selenium)")


def start(profile: Path, width: int, height: int, performance: bool = False):
    """A headless chromium driver with a ``width`` x ``height`` window and the browser console logged (and the
    network log with ``performance``); the caller quits it."""
    webdriver = skip_without_browser()
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    opts = Options()
    opts.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                f"--window-size={width},{height}", f"--user-data-dir={profile}"):  # fmt: skip
        opts.add_argument(arg)
    logs = {"browser": "ALL", **({"performance": "ALL"} if performance else {})}
    opts.set_capability("goog:loggingPrefs", logs)
    driver = webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER), options=opts)
    driver.set_page_load_timeout(60)
    return driver


def severe_errors(driver) -> list[str]:
    """The console messages of level SEVERE logged since the last read."""
    return [e["message"] for e in driver.get_log("browser") if e["level"] == "SEVERE"]
