"""The viewer's page in a real browser: Debian's headless chromium driven by selenium.

WebGL runs on SwiftShader (software). The page is checked for pixels, a mouse drag, the tool's
force, a cut and its frame rates; ``pytest -s`` prints the measured rates.
"""
from __future__ import annotations

import base64
import io
import os
import time

import numpy as np
import pytest
import torch

from tests.view.test_viewer_security import make_session

CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
if not (os.path.exists(CHROMIUM) and os.path.exists(CHROMEDRIVER)):
    pytest.skip(f"the browser tests need Debian's chromium and chromium-driver ({CHROMIUM}, {CHROMEDRIVER}): "
                "apt-get install chromium chromium-driver", allow_module_level=True)
webdriver = pytest.importorskip("selenium.webdriver", reason="the browser tests need selenium (pip install selenium)")
pytest.importorskip("websockets", reason="the viewer needs websockets (pip install websockets)")
from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.common.action_chains import ActionChains  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402

from torchdeform.view.server import Viewer  # noqa: E402

BACKGROUND = (0x1e, 0x22, 0x27)
WIDTH, HEIGHT = 800, 600


@pytest.fixture(scope="module")
def driver(tmp_path_factory):
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--no-first-run", "--disable-extensions", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                f"--window-size={WIDTH},{HEIGHT}",
                f"--user-data-dir={tmp_path_factory.mktemp('chromium-profile')}"):
        opts.add_argument(arg)
    try:
        d = webdriver.Chrome(options=opts, service=Service(CHROMEDRIVER))
    except Exception as e:          # a broken browser install is not a failure of the viewer
        pytest.skip(f"headless chromium did not start: {str(e).splitlines()[0]}")
    d.set_script_timeout(30)
    yield d
    d.quit()


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    v = Viewer(make_session(tmp_path_factory.mktemp("small"), n=16)).start()
    yield v
    v.stop()


def open_page(driver, viewer: Viewer, frames: int = 5, timeout: float = 30):
    driver.get(viewer.url)
    WebDriverWait(driver, timeout).until(
        lambda d: d.execute_script("return (window.viewerStats && window.viewerStats.framesReceived) || 0") >= frames)
    WebDriverWait(driver, timeout).until(
        lambda d: d.execute_script("return window.viewerStats && window.viewerStats.lastStats") is not None)


def js(driver, expr: str):
    return driver.execute_script(f"return {expr};")


def canvas_pixels(driver) -> np.ndarray:
    from PIL import Image
    url = js(driver, "document.getElementById('view').toDataURL('image/png')")
    data = base64.b64decode(url.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def centre_action(driver) -> ActionChains:
    """Actions starting with the mouse at the canvas's centre (where the camera looks: the body)."""
    canvas = driver.find_element(By.ID, "view")
    return ActionChains(driver, duration=20).move_to_element_with_offset(canvas, 0, 0)


def displacement(session) -> float:
    """The largest node displacement (m)."""
    return float((session.state.x - session.model.X).norm(dim=1).max())


def wait_for(predicate, timeout: float = 10.0, step: float = 0.05):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(step)
    return predicate()


def test_page_draws_the_body(driver, small):
    open_page(driver, small)
    assert js(driver, "window.viewerStats.vertices") == small.session.mesh()["vertices"]
    assert js(driver, "window.viewerStats.meshVersion") == small.session.mesh_version
    img = canvas_pixels(driver)
    assert img.shape[0] > 100 and img.shape[1] > 100
    body = np.abs(img.astype(int) - BACKGROUND).sum(-1) > 30
    print(f"\ncanvas {img.shape[1]}x{img.shape[0]}: {body.mean():.1%} of the pixels show the body")
    assert body.mean() > 0.02
    centre = img[img.shape[0] // 2, img.shape[1] // 2]
    assert body[img.shape[0] // 2, img.shape[1] // 2], f"no body at the centre: {centre}"


def test_mouse_drag_moves_the_body(driver, small):
    open_page(driver, small)
    session = small.session
    time.sleep(0.3)
    before = displacement(session)
    chain = centre_action(driver).click_and_hold()
    for _ in range(8):
        chain.move_by_offset(0, -12)
    chain.pause(0.8).perform()
    during = displacement(session)
    held = js(driver, "window.viewerStats.lastStats.drag_force")
    ActionChains(driver).release().perform()
    spacing = 0.002
    print(f"\ndrag: largest displacement {before * 1e3:.3f} mm -> {during * 1e3:.3f} mm, drag force {held}")
    assert during > before + spacing, (before, during)
    assert wait_for(lambda: displacement(session) < during, timeout=5)          # released: springs back


def test_tool_press_shows_a_force(driver, small):
    open_page(driver, small)
    driver.find_element(By.ID, "mode-tool").click()
    assert js(driver, "window.viewerStats.mode") == "tool"
    chain = centre_action(driver).move_by_offset(5, 5).click_and_hold()
    chain.move_by_offset(2, 0).pause(0.6).move_by_offset(2, 0).perform()
    force = wait_for(lambda: (js(driver, "window.viewerStats.lastStats.force") or 0) > 0
                     and js(driver, "window.viewerStats.lastStats.force"), timeout=5)
    shown = driver.find_element(By.ID, "force").text
    ActionChains(driver).release().perform()
    print(f"\ntool: force {force} N (readout {shown})")
    assert force and force > 0
    assert float(shown) > 0
    assert wait_for(lambda: small.session.stats()["force"] == 0.0, timeout=5)    # released: tool removed
    driver.find_element(By.ID, "mode-drag").click()


def test_cut_stroke_removes_springs(driver, small):
    open_page(driver, small)
    session = small.session
    springs, version = session.stats()["springs"], session.mesh_version
    driver.find_element(By.ID, "mode-cut").click()
    chain = centre_action(driver).move_by_offset(-200, 60).click_and_hold()     # below the panel
    for _ in range(10):
        chain.move_by_offset(40, 0)
    chain.release().perform()
    assert wait_for(lambda: session.stats()["springs"] < springs, timeout=10), "no springs cut"
    after = session.stats()["springs"]
    assert session.mesh_version > version
    assert wait_for(lambda: js(driver, "window.viewerStats.meshVersion") == session.mesh_version, timeout=10)
    assert js(driver, "window.viewerStats.vertices") == session.mesh()["vertices"]
    print(f"\ncut: springs {springs} -> {after}, mesh version {version} -> {session.mesh_version}")
    assert torch.isfinite(session.state.x).all()
    driver.find_element(By.ID, "mode-drag").click()


def test_page_reports_its_frame_rate(driver, small):
    open_page(driver, small)
    fps = wait_for(lambda: js(driver, "window.viewerStats.fps"), timeout=5)
    assert fps and fps > 0
    assert wait_for(lambda: small.page_fps is not None and small.page_fps > 0, timeout=5)
    assert wait_for(lambda: (js(driver, "window.viewerStats.lastStats.page_fps") or 0) > 0, timeout=5)
    assert float(driver.find_element(By.ID, "fps").text) > 0
    driver.find_element(By.ID, "pause").click()
    assert wait_for(lambda: not small.session.stats()["playing"], timeout=5)
    driver.find_element(By.ID, "play").click()
    assert wait_for(lambda: small.session.stats()["playing"], timeout=5)


def measure(driver, seconds: float = 2.0) -> tuple[float, float, float, float]:
    """(page frame rate, frames received per second, sim rate, drawing resolution) over ``seconds``."""
    f0, t0 = js(driver, "[window.viewerStats.framesReceived, performance.now()]")
    time.sleep(seconds)
    f1, t1 = js(driver, "[window.viewerStats.framesReceived, performance.now()]")
    stats = js(driver, "window.viewerStats")
    return stats["fps"], (f1 - f0) / ((t1 - t0) / 1000), stats["lastStats"]["sim_hz"], stats["resolution"]


def measured(driver, windows: int = 3) -> tuple[float, float, float, float]:
    """Medians over ``windows`` measurements, after 3 s for the page to settle its resolution."""
    time.sleep(3.0)
    return tuple(float(np.median(col)) for col in zip(*(measure(driver) for _ in range(windows))))


@pytest.mark.slow
def test_frame_rate_of_a_32_cube(driver, small, tmp_path):
    """The page draws a 32^3 body's surface at >= 30 fps on 2 cores, every drawn frame a fresh one.

    The simulation runs with :func:`~torchdeform.view.commands.default_threads` threads (as
    ``torchdeform view`` does): all cores but one, which the browser needs to draw.
    """
    from torchdeform.view.commands import default_threads
    open_page(driver, small)
    fps16, received16, hz16, res16 = measured(driver, windows=1)
    print(f"\n16^3 ({js(driver, 'window.viewerStats.vertices')} vertices): page {fps16:.1f} fps at "
          f"{res16:.0%} resolution, received {received16:.1f} frames/s, sim {hz16:.0f} steps/s")
    small.session.command({"cmd": "pause"})          # its worker would compete for the 2 cores
    threads = torch.get_num_threads()
    torch.set_num_threads(default_threads())
    t = time.perf_counter()
    v = Viewer(make_session(tmp_path, n=32)).start()
    try:
        built = time.perf_counter() - t
        open_page(driver, v)
        fps, received, hz, res = measured(driver)
        print(f"32^3 ({js(driver, 'window.viewerStats.vertices')} vertices, session built in {built:.1f} s, "
              f"{os.cpu_count()} cores, {torch.get_num_threads()} sim threads): page {fps:.1f} fps at "
              f"{res:.0%} resolution, received {received:.1f} frames/s, sim {hz:.0f} steps/s, "
              f"server posted {v.frames} frames")
        assert fps >= 30, f"the page drew {fps:.1f} fps (received {received:.1f} frames/s)"
        assert received >= 30, f"the page received {received:.1f} frames/s (drew {fps:.1f} fps)"
    finally:
        v.stop()
        torch.set_num_threads(threads)
