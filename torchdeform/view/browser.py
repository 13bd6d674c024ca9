"""A headless browser on the viewer's page: Debian's chromium driven by selenium.

What ``torchdeform bench viewer`` and the browser tests share: start chromium (WebGL on
SwiftShader, software, when there is no GPU), open a viewer's page, and read the page's own
counters (``window.viewerStats``: frames drawn per second, frames received, drawing resolution,
the server's last stats).

Needs ``apt-get install chromium chromium-driver`` and ``pip install selenium`` (both in the
test extras; neither is imported with the package).

Examples:
    >>> from torchdeform.view import browser
    >>> browser.missing() in (None, browser.missing())      # None where chromium and selenium are installed
    True
"""

from __future__ import annotations

import os
import statistics
import time

from ..errors import ConfigError

__all__ = ["CHROMIUM", "CHROMEDRIVER", "WIDTH", "HEIGHT", "missing", "start", "open_page", "js", "measure", "measured"]

CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
#: the window size (CSS pixels)
WIDTH, HEIGHT = 800, 600


def missing() -> str | None:
    """What is missing to drive a browser (one line naming how to install it), or None."""
    if not (os.path.exists(CHROMIUM) and os.path.exists(CHROMEDRIVER)):
        return (
            f"Debian's chromium and chromium-driver ({CHROMIUM}, {CHROMEDRIVER}): "
            "apt-get install chromium chromium-driver"
        )
    try:
        import selenium.webdriver  # noqa: F401
    except ImportError:
        return "selenium: pip install selenium"
    return None


def start(profile_dir, *, width: int = WIDTH, height: int = HEIGHT):
    """A headless chromium (selenium ``WebDriver``) with a fresh profile in ``profile_dir``.

    Raises:
        ConfigError: chromium, its driver or selenium is missing (:func:`missing`).
        Exception: whatever selenium raises when the browser does not start.
    """
    why = missing()
    if why is not None:
        raise ConfigError("browser", why, got="missing")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in (
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--no-first-run",
        "--disable-extensions",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        f"--window-size={width},{height}",
        f"--user-data-dir={profile_dir}",
    ):
        opts.add_argument(arg)
    driver = webdriver.Chrome(options=opts, service=Service(CHROMEDRIVER))
    driver.set_script_timeout(30)
    return driver


def js(driver, expr: str):
    """The value of the JavaScript expression ``expr`` on the page."""
    return driver.execute_script(f"return {expr};")


def open_page(driver, url: str, *, frames: int = 5, timeout: float = 30.0) -> None:
    """Load a viewer's ``url`` and wait until the page has received ``frames`` frames and a stats message."""
    from selenium.webdriver.support.ui import WebDriverWait

    driver.get(url)
    WebDriverWait(driver, timeout).until(
        lambda d: d.execute_script("return (window.viewerStats && window.viewerStats.framesReceived) || 0") >= frames
    )
    WebDriverWait(driver, timeout).until(
        lambda d: d.execute_script("return window.viewerStats && window.viewerStats.lastStats") is not None
    )


def measure(driver, *, seconds: float = 2.0) -> dict:
    """The page's rates over ``seconds``.

    ``fps`` (frames drawn per second, the page's own count), ``received`` (frames received per second), ``sim_hz`` (the server's steps per second) and
    ``resolution`` (the page's drawing resolution, a fraction of the canvas).
    """
    f0, t0 = js(driver, "[window.viewerStats.framesReceived, performance.now()]")
    time.sleep(seconds)
    f1, t1 = js(driver, "[window.viewerStats.framesReceived, performance.now()]")
    stats = js(driver, "window.viewerStats")
    return {
        "fps": float(stats["fps"]),
        "received": (f1 - f0) / ((t1 - t0) / 1000.0),
        "sim_hz": float(stats["lastStats"]["sim_hz"]),
        "resolution": float(stats["resolution"]),
    }


def measured(driver, *, windows: int = 3, seconds: float = 2.0, settle: float = 3.0) -> dict:
    """Medians of :func:`measure` over ``windows`` windows.

    The first starts after ``settle`` seconds, for the page to settle its drawing resolution.
    """
    time.sleep(settle)
    runs = [measure(driver, seconds=seconds) for _ in range(windows)]
    return {key: statistics.median(r[key] for r in runs) for key in runs[0]}
