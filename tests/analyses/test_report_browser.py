"""report.html in a real browser: every plot loads, the 3D scene renders, no console errors.

Skipped (with the reason) when no Chromium is installed; CI installs Debian's chromium."""

import functools
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer

import pytest

from tests.analyses.browser import Browser, find_chromium

CHROMIUM = find_chromium()
pytestmark = [pytest.mark.browser,
              pytest.mark.skipif(CHROMIUM is None, reason="no chromium on this machine "
                                 "(apt-get install chromium)")]


class _Quiet(SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


@pytest.fixture()
def served(demo_plan):
    """The plan folder over HTTP on loopback (an ephemeral port): one origin for the page and
    its iframe, as when a user serves the folder."""
    server = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Quiet,
                                                                     directory=str(demo_plan)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()


def test_report_loads_without_errors(served, tmp_path):
    browser = Browser(CHROMIUM)
    try:
        browser.open(f"{served}/report.html", settle=4.0)
        images = browser.evaluate(
            "Array.from(document.images).map(i => [i.getAttribute('src'), i.complete, "
            "i.naturalWidth])")
        assert len(images) >= 10
        broken = [src for src, complete, width in images if not (complete and width > 0)]
        assert broken == []
        # the Meshcat scene in the iframe has drawn into a WebGL canvas
        canvases = browser.evaluate(
            "(() => { const f = document.querySelector('iframe'); "
            "return f.contentDocument.querySelectorAll('canvas').length; })()")
        assert canvases >= 1
        # the site scene holds the scan, the FPSM, the fixture, the rod and the arm + actuator
        tree = browser.evaluate(
            "(() => { const v = document.getElementById('site-frame').contentWindow.viewer; "
            "const kids = p => Object.keys(v.scene_tree.find(p).children); "
            "return JSON.stringify({case: kids(['case']), "
            "drake: kids(['drake', 'visualizer'])}); })()")
        tree = __import__("json").loads(tree)
        assert {"scan", "fpsm", "site", "implant_path", "feeding_target", "fixture",
                "rod"} <= set(tree["case"])
        assert {"aubo", "actuator"} <= set(tree["drake"])
        # the selector switches the frame to the other site's scene
        src = browser.evaluate(
            "(() => { const s = document.getElementById('site-scene'); s.selectedIndex = 1; "
            "s.dispatchEvent(new Event('change')); "
            "return document.getElementById('site-frame').getAttribute('src'); })()")
        assert src == "scene_46.html"
        browser.screenshot(tmp_path / "report.png")
        # it prints: a multi-page PDF without the interactive frames
        import base64

        pdf = base64.b64decode(browser.call("Page.printToPDF", printBackground=False)["data"])
        assert pdf[:5] == b"%PDF-" and pdf.count(b"/Type /Page") - pdf.count(b"/Type /Pages") > 3
        assert browser.errors == []
    finally:
        browser.close()
