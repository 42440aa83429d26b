"""`wtbench view` in a real headless browser: Debian's chromium and chromium-driver driven by Selenium.

A WorldTree run (smoke schedule) on the tiny analytic scene is loaded through ``benchmarks.api.load_run`` and
served on a free port from this process. Checked: the page loads with no console error and fetches nothing
but the local server, the canvas shows the rendered image, moving the time slider (keyboard, in the page)
changes the rendered pixels, dragging the camera sends small previews and then the full image, and the "Test
camera" button shows the run's own test render: the PNG the server sent, cropped out of its letterbox, equals
``RUN/renders/v001_tXXX.png`` exactly (both are the rasterizer's image rounded the same way; PNG is lossless).
Then a click on a training camera's frustum looks through it, Play/Pause and the render menu.
Skips with one reason where the browser or Selenium is missing (`.ci/run` installs both when it can).
"""

from __future__ import annotations

import importlib.util
import json
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch


def _load(name: str):
    path = Path(__file__).with_name(f"{name}.py")
    spec = importlib.util.spec_from_file_location(f"wt_tests_{name}_{Path(__file__).stem}", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


chromium = _load("chromium")
webdriver = chromium.skip_without_browser()

TIMEOUT = 30.0


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory, write_tiny_scene):
    from benchmarks.runner.runs import RunRequest, execute

    tmp = tmp_path_factory.mktemp("viewer")
    scene = write_tiny_scene(tmp / "scenes" / "tiny")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # LPIPS weights are not installed here: its columns stay empty
        res = execute(
            RunRequest(scene=scene, method="worldtree", runs_dir=tmp / "runs", preset="smoke", device="cpu",
                       progress=False)
        )  # fmt: skip
    torch.set_num_threads(1)
    return res.folder.root


@pytest.fixture(scope="module")
def viewer(run_dir):
    from benchmarks.viewer.server import Viewer
    from benchmarks.viewer.source import open_run

    v = Viewer(open_run(run_dir, "cpu"), host="127.0.0.1", port=0)
    yield v
    v.stop()


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    driver = chromium.start(tmp_path_factory.mktemp("chromium-profile"), 1280, 800, performance=True)
    yield driver
    driver.quit()


def _requested_urls(driver) -> list[str]:
    urls = []
    for entry in driver.get_log("performance"):
        msg = json.loads(entry["message"])["message"]
        if msg["method"] == "Network.requestWillBeSent":
            urls.append(msg["params"]["request"]["url"])
        elif msg["method"] == "Network.webSocketCreated":
            urls.append(msg["params"]["url"])
    return urls


def _canvas_pixels(driver) -> np.ndarray:
    """RGB ``uint8 [H, W, 3]`` of the 3D canvas as the browser shows it (a screenshot of the element)."""
    import cv2

    png = driver.find_element("css selector", "canvas").screenshot_as_png
    return np.ascontiguousarray(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1])


def _click_button(driver, label: str) -> None:
    # One XPath query: reading every button's text is a round trip each, slow while the page plays.
    driver.find_element("xpath", f"//button[normalize-space()='{label}']").click()


def _wait_canvas(driver, accept, timeout: float = TIMEOUT) -> np.ndarray:
    """Screenshots of the canvas until ``accept(pixels)`` (the browser paints a frame after it arrives)."""
    deadline = time.monotonic() + timeout
    while True:
        px = _canvas_pixels(driver)
        if accept(px) or time.monotonic() > deadline:
            return px
        time.sleep(0.2)


def test_viewer_in_the_browser(viewer, browser, run_dir):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    from worldtree.imageio import read_image

    browser.get(viewer.url)
    # The page opens on the test camera at the first time, full size.
    first = viewer.wait_for_frame(lambda f: not f.preview and f.camera == "test", TIMEOUT)
    assert first.time == 0 and first.format == "png"
    assert chromium.severe_errors(browser) == []

    # Nothing but the local server is fetched (viser's client is bundled in its wheel; no CDN).
    remote = [u for u in _requested_urls(browser) if u.split(":", 1)[0] in ("http", "https", "ws", "wss")
              and not u.startswith((viewer.url, viewer.url.replace("http", "ws", 1)))]  # fmt: skip
    assert remote == []

    # The canvas shows the rendered image: not blank, and where no panel, notice or frustum covers it, the
    # sent image stretched over the canvas (the browser scales it smoothly; hence a tolerance).
    # On a busy machine the canvas may settle its size after the first frame, and the viewer sends that time again
    # letterboxed anew: compare with the newest full image sent.
    shown = []  # the frames compared, newest last

    def shows_newest(p: np.ndarray) -> bool:
        shown.append(viewer.wait_for_frame(lambda f: not f.preview and f.camera == "test", TIMEOUT))
        return _uncovered_difference(p, shown[-1].sent) < 6

    px = _wait_canvas(browser, shows_newest)
    first = shown[-1]
    assert first.time == 0 and px.std() > 10 and len(np.unique(px.reshape(-1, 3), axis=0)) > 100
    assert _uncovered_difference(px, first.sent) < 6
    # The time slider, moved with the keyboard in the page, changes the rendered pixels.
    slider = browser.find_element("css selector", "[role=slider]")
    slider.click()
    slider.send_keys(Keys.END)
    last = len(viewer.source.times) - 1
    later = viewer.wait_for_frame(lambda f: f.seq > first.seq and f.time == last and not f.preview, TIMEOUT)
    assert later.camera == "test"
    changed = np.abs(later.image.astype(int) - first.image.astype(int)).sum(-1) > 30
    assert changed.sum() > 50  # the moving square is drawn elsewhere
    px_later = _wait_canvas(browser, lambda p: np.abs(p.astype(int) - px.astype(int)).sum(-1).max() > 60)
    assert (np.abs(px_later.astype(int) - px.astype(int)).sum(-1) > 60).sum() > 1000

    # Dragging the camera: small JPEG previews of the free camera, then the full image once it is still. The drag
    # lasts several times STILL_S in small steps, so a render thread that wakes late on a busy machine still
    # finds the camera moving; the previews outlive the drag among the frames the viewer keeps.
    from benchmarks.viewer.server import STILL_S

    canvas = browser.find_element("css selector", "canvas")
    drag = ActionChains(browser).move_to_element(canvas).click_and_hold()
    steps = 20
    for _ in range(steps):
        drag = drag.move_by_offset(4, 1).pause(8 * STILL_S / steps)
    drag.release().perform()
    preview = viewer.wait_for_frame(lambda f: f.seq > later.seq and f.camera is None and f.preview, TIMEOUT)
    assert preview.format == "jpeg"
    still = viewer.wait_for_frame(
        lambda f: f.seq > preview.seq and f.camera is None and not f.preview, TIMEOUT
    )
    assert still.format == "png" and still.image.shape[1] > preview.image.shape[1]

    # "Test camera" looks through the test camera again: the run's own test render, exactly.
    _click_button(browser, "Test camera")
    shot = viewer.wait_for_frame(
        lambda f: f.seq > still.seq and f.camera == "test" and not f.preview, TIMEOUT
    )
    assert shot.format == "png" and shot.time == last
    t = viewer.source.times[shot.time]
    expected = read_image(run_dir / "renders" / f"v001_t{t:03d}.png")
    sent = shot.box.crop(shot.sent, expected.shape[1], expected.shape[0])
    np.testing.assert_array_equal(sent, expected)
    assert (shot.sent.shape[0] == expected.shape[0]) or (shot.sent.shape[1] == expected.shape[1])

    # WorldTree: the tree node is named in the panel (a 6-frame scene keeps the root alone).
    assert "node 1" in browser.find_element("css selector", "body").text

    # Clicking a training camera's frustum looks through it. The browser camera is put (from Python) behind that
    # camera on its optical axis, so the frustum's image plane lies under the canvas centre; the click is the
    # page's.
    from benchmarks.viewer.camera import quat_to_matrix, viser_from_w2c

    target = next(c for c in viewer.source.cameras if c.name == "train_002")
    wxyz, centre = viser_from_w2c(target.w2c)
    client = next(iter(viewer.server.get_clients().values()))
    before = _canvas_pixels(browser)
    with client.atomic():  # one pose, not a rotation then a position the browser may echo late
        client.camera.wxyz = wxyz
        client.camera.position = centre - 0.3 * viewer.scale * quat_to_matrix(wxyz)[:, 2]
    # The page has moved its camera once the frusta drawn over the image have moved.
    _wait_canvas(browser, lambda p: (np.abs(p.astype(int) - before.astype(int)).sum(-1) > 30).sum() > 100)
    ActionChains(browser).move_to_element(canvas).click().perform()
    picked = viewer.wait_for_frame(lambda f: f.seq > shot.seq and f.camera == "train_002", TIMEOUT)
    assert picked.image.shape[:2] == (target.height, target.width) and not picked.preview

    # Play runs through the times (full images of the camera looked through), Pause stops.
    _click_button(browser, "Play")
    times = set()
    mark = picked.seq
    while len(times) < 3:
        f = viewer.wait_for_frame(lambda f, m=mark: f.seq > m and f.camera == "train_002", TIMEOUT)
        times.add(f.time)
        mark = f.seq
    _click_button(browser, "Pause")
    deadline = time.monotonic() + TIMEOUT
    while viewer.playing and time.monotonic() < deadline:  # the click reaches the server a moment later
        time.sleep(0.05)
    assert not viewer.playing

    # Render modes, picked in the page's menu: depth (turbo colours), the dynamic part alone, the tree node.
    images, current = {"colour": picked.image}, "colour"
    for mode in ("depth", "dynamic part", "tree node"):
        _choose(browser, current, mode)
        f = viewer.wait_for_frame(
            lambda f, m=mode: f.mode == m and f.camera == "train_002" and not f.preview, TIMEOUT
        )
        images[mode], current = f.image, mode
    for mode in ("depth", "dynamic part", "tree node"):
        assert images[mode].shape == picked.image.shape and not np.array_equal(images[mode], images["colour"])
    assert chromium.severe_errors(browser) == []


def _choose(driver, current: str, option: str) -> None:
    """Pick ``option`` in the viewer's menu that shows ``current`` (a Mantine select: open it, click the option)."""
    from selenium.webdriver.support.ui import WebDriverWait

    driver.find_element("xpath", f"//input[@value='{current}']").click()
    option = f"//*[@role='option' and normalize-space()='{option}']"
    WebDriverWait(driver, TIMEOUT).until(lambda d: d.find_elements("xpath", option))
    driver.find_element("xpath", option).click()


def _uncovered_difference(px: np.ndarray, sent: np.ndarray) -> float:
    """Mean absolute difference (grey levels) of the screenshot ``px`` and the ``sent`` image stretched to its
    size, over the canvas's lower middle: the GUI panel (right), the browser's notices (top left), the axes
    (bottom left) and the training cameras' frusta (upper half) lie outside it."""
    import cv2

    H, W = px.shape[:2]
    stretched = cv2.resize(sent, (W, H), interpolation=cv2.INTER_LINEAR)
    rows, cols = slice(int(0.45 * H), int(0.95 * H)), slice(int(0.1 * W), int(0.7 * W))
    return float(np.abs(px[rows, cols].astype(int) - stretched[rows, cols].astype(int)).mean())
