"""Screenshots of `wtbench view` in headless chromium: the 3D canvas with the panel, at chosen times.

The viewer (:class:`benchmarks.viewer.server.Viewer`) serves the finished run in ``RUN_DIR`` from this process
on a free port; Debian's chromium, driven by Selenium with an explicit driver path (nothing is downloaded),
opens its page. The camera is a named camera of the run (``train_000``: the browser looks through it, as a
click on its frustum does) or ``free``: the browser's free camera placed behind and beside the first training
camera (``--back`` / ``--side`` in units of the cameras' spread), slightly off the training path. Each time is
set with the page's time slider (keyboard: Home, then one Right per step); once the viewer has sent that
time's full-size PNG and the panel names it, the browser's own screenshot of the window is saved as
``OUT_DIR/view_t<time>.png`` (``view_free_t<time>.png`` for the free camera).

Usage::

    python -m benchmarks.speed.viewer_screenshots RUN_DIR --times 0,40,79 --camera train_000 -o OUT_DIR \\
        [--width 960 --height 540] [--device cpu] [--max-size N] [--hide-cameras]

Needs chromium and chromedriver on PATH (``apt-get install chromium chromium-driver``) and Selenium
(``pip install selenium``); without them it stops with one line saying so.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

from worldtree.infra.errors import UserError

#: Seconds to wait for one full-size frame (a CPU render of a real clip's frame takes seconds).
TIMEOUT = 180.0


def _browser(profile: Path, width: int, height: int):
    """A headless chromium driver with a ``width`` x ``height`` window; UserError naming what is missing."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver_path = shutil.which("chromedriver")
    if not (chromium and driver_path):
        raise UserError(
            "no chromium/chromedriver on PATH (install: apt-get install chromium chromium-driver)"
        )
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.options import Options
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        raise UserError("selenium is not installed (pip install selenium)") from None
    opts = Options()
    opts.binary_location = chromium
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--hide-scrollbars", f"--window-size={width},{height}", f"--user-data-dir={profile}"):  # fmt: skip
        opts.add_argument(arg)
    driver = webdriver.Chrome(service=Service(executable_path=driver_path), options=opts)
    driver.set_page_load_timeout(60)
    # The window size includes the browser's frame: make the page itself width x height.
    driver.execute_cdp_cmd(
        "Emulation.setDeviceMetricsOverride",
        {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False},
    )
    return driver


def _client(viewer, timeout: float = TIMEOUT):
    """The one browser tab connected to ``viewer``."""
    deadline = time.monotonic() + timeout
    while not viewer.server.get_clients():
        if time.monotonic() > deadline:
            raise UserError("the page did not connect to the viewer")
        time.sleep(0.1)
    return next(iter(viewer.server.get_clients().values()))


def _set_time_in_page(driver, index: int) -> None:
    """Move the page's time slider to ``index`` with the keyboard (Home, then Right ``index`` times)."""
    try:
        from selenium.webdriver.common.keys import Keys
    except ImportError:  # only reached once the browser started, which needs selenium
        raise UserError("selenium is not installed (pip install selenium)") from None

    slider = driver.find_element("css selector", "[role=slider]")
    slider.send_keys(Keys.HOME)
    if index:
        slider.send_keys(Keys.ARROW_RIGHT * index)


def _panel_shows(driver, where: str, t) -> bool:
    text = driver.find_element("css selector", "body").text
    return f"{where} · time {t}" in text.replace("\n", " ")


def _close_notices(driver) -> None:
    """Close the page's notifications (headless chromium's "Software WebGL rendering detected")."""
    for button in driver.find_elements("css selector", ".mantine-Notification-closeButton"):
        try:
            button.click()
        except Exception:  # gone meanwhile, or not clickable: the notice stays in the screenshot
            pass


def _hide_cameras(driver) -> None:
    label = driver.find_element("xpath", "//label[normalize-space()='show cameras']")
    box = driver.find_element("id", label.get_attribute("for"))
    if box.is_selected():
        driver.execute_script("arguments[0].click();", box)


def _free_pose(viewer, base: str, back: float, side: float):
    """Viser ``(wxyz, position)`` of camera ``base`` moved ``back`` along its optical axis and ``side`` to its
    right (both times the cameras' spread), looking the same way."""
    from benchmarks.viewer.camera import quat_to_matrix, viser_from_w2c

    c = next(c for c in viewer.source.cameras if c.name == base)
    wxyz, centre = viser_from_w2c(c.w2c)
    R = quat_to_matrix(wxyz)  # columns: the camera's right, down and forward axes in the world
    return wxyz, centre + viewer.scale * (side * R[:, 0] - back * R[:, 2])


def _canvas_settled(driver, previous: bytes | None, timeout: float = 10.0) -> bytes:
    """The window's screenshot once two in a row are equal (the browser has painted the last image)."""
    deadline = time.monotonic() + timeout
    last = previous
    while True:
        time.sleep(0.4)
        png = driver.get_screenshot_as_png()
        if png == last or time.monotonic() > deadline:
            return png
        last = png


def screenshots(
    run_dir: Path,
    times: list[int],
    camera: str,
    out_dir: Path,
    width: int = 960,
    height: int = 540,
    device: str | None = "cpu",
    max_size: int | None = None,
    hide_cameras: bool = False,
    back: float = 1.0,
    side: float = 0.5,
) -> list[Path]:
    """Save the browser's screenshots of the viewer of ``run_dir`` at time indices ``times``; return the
    paths."""
    from benchmarks.viewer.server import Viewer
    from benchmarks.viewer.source import open_run

    source = open_run(run_dir, device)
    n = len(source.times)
    bad = [t for t in times if not 0 <= t < n]
    if bad:
        raise UserError(f"--times {bad}: the run has times 0..{n - 1}")
    names = [c.name for c in source.cameras]
    free = camera == "free"
    named = None if free else next((c for c in source.cameras if c.name == camera), None)
    if not free and named is None:
        raise UserError(f"--camera {camera}: not a camera of the run ({', '.join(names[:3])}, ... or free)")
    base = next((c.name for c in source.cameras if not c.is_test), names[0]) if free else camera
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="viewer-shots-") as profile:
        driver = _browser(Path(profile), width, height)
        viewer = Viewer(source, host="127.0.0.1", port=0, max_size=max_size)
        try:
            driver.get(viewer.url)
            client = _client(viewer)
            # The page opens on the test camera (or the first training camera), full size.
            first = viewer.wait_for_frame(lambda f: not f.preview, TIMEOUT)
            view = viewer._client_view(client)
            _close_notices(driver)
            if hide_cameras:
                _hide_cameras(driver)
            if free:
                time.sleep(1.2)  # past the viewer's grace for echoes of the pose it placed
                wxyz, position = _free_pose(viewer, base, back, side)
                with client.atomic():
                    client.camera.wxyz = wxyz
                    client.camera.position = position
                first = viewer.wait_for_frame(
                    lambda f, m=first.seq: f.seq > m and f.camera is None and not f.preview, TIMEOUT
                )
            elif first.camera != camera:
                view.look_through(named)
                first = viewer.wait_for_frame(
                    lambda f, m=first.seq: f.seq > m and f.camera == camera and not f.preview, TIMEOUT
                )
            wanted = None if free else camera
            where = "free camera" if free else camera
            paths, mark, png = [], 0, None
            for t in times:
                _set_time_in_page(driver, t)
                frame = viewer.wait_for_frame(
                    lambda f, t=t, m=mark: f.seq > m and f.time == t and f.camera == wanted and not f.preview,
                    TIMEOUT,
                )
                mark = frame.seq
                deadline = time.monotonic() + 30
                while not _panel_shows(driver, where, source.times[t]) and time.monotonic() < deadline:
                    time.sleep(0.2)
                png = _canvas_settled(driver, png)
                name = f"view_free_t{t:03d}.png" if free else f"view_t{t:03d}.png"
                path = out_dir / name
                path.write_bytes(png)
                print(
                    f"{path}: {where}, time {source.times[t]}, {frame.image.shape[1]}x{frame.image.shape[0]} "
                    f"{frame.format} rendered in {frame.seconds:.1f} s",
                    flush=True,
                )
                paths.append(path)
            if viewer.time_index() != times[-1]:
                raise UserError("the page's time slider did not reach the last time")
            return paths
        finally:
            driver.quit()
            viewer.stop()


def _times(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: comma-separated time indices, e.g. 0,40,79") from None


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="A finished run folder of `wtbench run`.")
    ap.add_argument("--times", type=_times, default=[0], help="Time indices, comma-separated (e.g. 0,40,79).")
    ap.add_argument("--camera", default="train_000", help="A camera of the run (train_000, ...) or 'free'.")
    ap.add_argument("-o", "--out", type=Path, required=True, help="Folder for view_t<time>.png.")
    ap.add_argument("--width", type=int, default=960, help="Browser window width, pixels.")
    ap.add_argument("--height", type=int, default=540, help="Browser window height, pixels.")
    ap.add_argument("--device", default="cpu", help="Where to render: auto, cpu, cuda (default cpu).")
    ap.add_argument("--max-size", type=int, default=None, help="The viewer's --max-size (free camera).")
    ap.add_argument("--hide-cameras", action="store_true", help="Untick 'show cameras' in the page.")
    ap.add_argument("--back", type=float, default=1.0, help="Free camera: behind the first training camera.")
    ap.add_argument("--side", type=float, default=0.5, help="Free camera: to its right.")
    args = ap.parse_args(argv)
    try:
        screenshots(args.run, args.times, args.camera, args.out, args.width, args.height, args.device,
                    args.max_size, args.hide_cameras, args.back, args.side)  # fmt: skip
    except (UserError, TimeoutError) as e:
        sys.exit(f"viewer_screenshots: {e}")


if __name__ == "__main__":
    main()
