"""The screenshot of the viewer guide: the page of ``torchdeform view scenes/demo.toml`` in headless chromium.

Run from the repository root: ``python3 docs/figures/viewer_screenshot.py docs/guide/viewer.png``
(needs Debian's ``chromium`` and ``chromium-driver``, selenium and websockets: ``pip install -e
".[test]"``). The page draws with software WebGL (SwiftShader) when there is no GPU.
"""

import sys
import tempfile
import time

import torchdeform as td
from torchdeform.view import browser
from torchdeform.view.server import Viewer
from torchdeform.view.session import ViewerSession


def main(path: str) -> None:
    """Serve the demo scene, open its page, let it run 6 s and save a screenshot to ``path``."""
    viewer = Viewer(ViewerSession(td.load_scene("scenes/demo.toml", surfaces=True))).start()
    with tempfile.TemporaryDirectory() as profile:
        driver = browser.start(profile, width=900, height=600)
        try:
            browser.open_page(driver, viewer.url)
            time.sleep(6)
            driver.save_screenshot(path)
        finally:
            driver.quit()
            viewer.stop()


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "viewer.png")
