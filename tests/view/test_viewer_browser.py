"""The viewer's page in a real browser: Debian's headless chromium driven by selenium.

WebGL runs on SwiftShader (software). The page is checked for pixels, a mouse drag, the tool's
force, a cut and its frame rates; ``pytest -s`` prints the measured rates.
"""

from __future__ import annotations

import base64
import io
import time

import numpy as np
import pytest
import torch

from tests.view.test_viewer_security import make_session
from torchdeform.view import browser

pytestmark = pytest.mark.slow  # the browser (selenium, headless chromium)

if browser.missing():
    pytest.skip(f"the browser tests need {browser.missing()}", allow_module_level=True)
pytest.importorskip("websockets", reason="the viewer needs websockets (pip install websockets)")
from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.by import By

from torchdeform.view.server import Viewer

BACKGROUND = (0x1E, 0x22, 0x27)
js = browser.js


@pytest.fixture(scope="module")
def driver(tmp_path_factory):
    try:
        d = browser.start(tmp_path_factory.mktemp("chromium-profile"))
    except TypeError:  # a wrong call is a failure of the test, not of the browser install
        raise
    except Exception as e:  # a broken browser install is not a failure of the viewer
        pytest.skip(f"headless chromium did not start: {str(e).splitlines()[0]}")
    yield d
    d.quit()


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    v = Viewer(make_session(n=16)).start()
    yield v
    v.stop()


def open_page(driver, viewer: Viewer, frames: int = 5, timeout: float = 30):
    browser.open_page(driver, viewer.url, frames=frames, timeout=timeout)


def canvas_pixels(driver, canvas: str = "view") -> np.ndarray:
    from PIL import Image

    url = js(driver, f"document.getElementById('{canvas}').toDataURL('image/png')")
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
    assert js(driver, "window.viewerStats.surface") == "lattice" and js(driver, "window.viewerStats.colored")
    assert js(driver, "window.viewerStats.tools") == []
    assert js(driver, "document.getElementById('scope').hidden") is True  # no [camera]: no endoscope pane
    assert js(driver, "window.viewerStats.endoscope.received") == 0
    img = canvas_pixels(driver)
    assert img.shape[0] > 100 and img.shape[1] > 100
    body = np.abs(img.astype(int) - BACKGROUND).sum(-1) > 30
    print(f"\ncanvas {img.shape[1]}x{img.shape[0]}: {body.mean():.1%} of the pixels show the body")
    assert body.mean() > 0.02
    centre = img[img.shape[0] // 2, img.shape[1] // 2]
    assert body[img.shape[0] // 2, img.shape[1] // 2], f"no body at the centre: {centre}"


def test_page_draws_embedded_surfaces_and_the_scene_tool(driver, tmp_path):
    """A label scene: its textured embedded surfaces and its probe, steel-grey, above the body at first."""
    from tests.view.test_viewer_scene import LABEL_SCENE, _labels
    from torchdeform.scene import load_scene
    from torchdeform.view.session import ViewerSession

    np.save(tmp_path / "labels.npy", _labels())
    (tmp_path / "scene.toml").write_text(LABEL_SCENE)
    session = ViewerSession(load_scene(tmp_path / "scene.toml"))
    session.command({"cmd": "pause"})  # the probe where it starts, above the body
    viewer = Viewer(session).start()
    try:
        open_page(driver, viewer, frames=1)
        assert wait_for(lambda: js(driver, "window.viewerStats.framesShown") >= 1, timeout=10)
        assert js(driver, "window.viewerStats.surface") == "embedded" and js(driver, "window.viewerStats.colored")
        assert js(driver, "window.viewerStats.tools") == ["probe"]
        assert js(driver, "window.viewerStats.vertices") == session.mesh()["vertices"]
        time.sleep(0.3)
        img = canvas_pixels(driver).astype(int)
    finally:
        viewer.stop()
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    steel = (np.abs(r - g) < 15) & (np.abs(g - b) < 25) & (r > 90)  # grey, lit
    tissue = (r > g + 25) & (r > 60)  # the liver texture: red-brown
    print(f"\nlabel scene: {steel.mean():.2%} steel, {tissue.mean():.1%} tissue pixels")
    assert steel.mean() > 0.002 and tissue.mean() > 0.02


def test_the_endoscope_pane_shows_the_scopes_view(driver):
    """scenes/endoscopy.toml: the round pane is shown, named after the tool, and holds the session's image."""
    from tests.view.test_endoscope_pane import SCENE, _session

    session = _session(SCENE)
    session.command({"cmd": "pause"})  # one state: the pane must show exactly its image
    scoped = session.endoscope()
    assert scoped is not None
    _, expected = scoped
    viewer = Viewer(session).start()
    try:
        open_page(driver, viewer, frames=1)
        assert wait_for(lambda: js(driver, "window.viewerStats.endoscope.shown") >= 1, timeout=15)
        assert js(driver, "document.getElementById('scope').hidden") is False
        assert js(driver, "window.viewerStats.endoscope.tool") == "scope"
        assert driver.find_element(By.ID, "scope-name").text == "endoscope: scope"
        box = driver.find_element(By.ID, "scope-view").rect
        img = canvas_pixels(driver, "scope-view")
    finally:
        viewer.stop()
    lit = (img.max(axis=2) > 30).mean()
    print(f"\nendoscope pane: {box['width']:.0f} x {box['height']:.0f} px on the page, {lit:.0%} lit")
    assert box["width"] > 100 and box["height"] > 100
    assert img.shape == expected.shape and lit > 0.2
    np.testing.assert_array_equal(img, expected)


def test_page_draws_several_bodies_each_in_its_colour(driver, tmp_path):
    """A scene of two bodies: one mesh per body, the lower one red, the upper one blue; no drag, tool, cut."""
    from tests.view.test_bodies_session import TWO
    from torchdeform.scene import load_scene
    from torchdeform.view.bodies import BodiesSession

    (tmp_path / "two.toml").write_text(TWO)
    session = BodiesSession(load_scene(tmp_path / "two.toml"))
    session.command({"cmd": "pause"})
    viewer = Viewer(session).start()
    try:
        open_page(driver, viewer, frames=1)
        assert wait_for(lambda: js(driver, "window.viewerStats.framesShown") >= 1, timeout=10)
        assert js(driver, "window.viewerStats.surface") == "bodies"
        assert js(driver, "window.viewerStats.parts") == ["lower", "upper"]
        assert js(driver, "window.viewerStats.mode") == "none"
        assert js(driver, "document.getElementById('mode-drag').parentElement.style.display") == "none"
        time.sleep(0.3)
        img = canvas_pixels(driver).astype(int)
    finally:
        viewer.stop()
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    red = (r > g + 30) & (r > b + 30)  # BODY_COLOURS[0], shaded
    blue = (b > r + 30) & (b > g + 10)  # BODY_COLOURS[1], shaded
    print(f"\ntwo bodies: {red.mean():.1%} red, {blue.mean():.1%} blue pixels")
    assert red.mean() > 0.01 and blue.mean() > 0.01
    rows = np.arange(img.shape[0])[:, None]
    assert rows[blue.any(1)].mean() < rows[red.any(1)].mean()  # the upper body above the lower one


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
    assert wait_for(lambda: displacement(session) < during, timeout=5)  # released: springs back


def test_tool_press_shows_a_force(driver, small):
    open_page(driver, small)
    driver.find_element(By.ID, "mode-tool").click()
    assert js(driver, "window.viewerStats.mode") == "tool"
    chain = centre_action(driver).move_by_offset(5, 5).click_and_hold()
    chain.move_by_offset(2, 0).pause(0.6).move_by_offset(2, 0).perform()
    force = wait_for(
        lambda: (
            (js(driver, "window.viewerStats.lastStats.force") or 0) > 0
            and js(driver, "window.viewerStats.lastStats.force")
        ),
        timeout=5,
    )
    shown = driver.find_element(By.ID, "force").text
    ActionChains(driver).release().perform()
    print(f"\ntool: force {force} N (readout {shown})")
    assert force and force > 0
    assert float(shown) > 0
    assert wait_for(lambda: small.session.stats()["force"] == 0.0, timeout=5)  # released: tool removed
    driver.find_element(By.ID, "mode-drag").click()


def test_cut_stroke_removes_springs(driver, small):
    open_page(driver, small)
    session = small.session
    springs, version = session.stats()["springs"], session.mesh_version
    driver.find_element(By.ID, "mode-cut").click()
    chain = centre_action(driver).move_by_offset(-200, 60).click_and_hold()  # below the panel
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


def test_bench_viewer_quick_json(capsys, tmp_path):
    """``torchdeform bench viewer --quick --json --out``: one row of real rates for the 16^3 body (the
    frame-rate target lives in the bench, not in a timed test), a CSV and a plot."""
    import json

    from torchdeform import cli
    from torchdeform.bench.viewer import viewer_cube
    from torchdeform.view.session import ViewerSession

    threads = torch.get_num_threads()
    assert cli.main(argv=["bench", "viewer", "--quick", "--json", "--out", str(tmp_path)]) == 0
    assert torch.get_num_threads() == threads  # restored
    doc = json.loads(capsys.readouterr().out)
    assert doc["bench"] == "viewer" and doc["met"] is None  # no 32^3 row in the quick run
    (row,) = doc["rows"]
    assert row["vertices"] == ViewerSession(viewer_cube(16)).mesh()["vertices"]
    assert row["fps"] > 0 and row["received"] > 0 and row["sim_hz"] > 0 and 0 < row["resolution"] <= 1
    assert row["frames_posted"] > 0
    assert (tmp_path / "viewer.csv").exists() and (tmp_path / "viewer.png").stat().st_size > 0
