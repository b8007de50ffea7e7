"""report.html in a real browser: every plot loads, the 3D scene renders, no console errors.

Skipped (with the reason) when no Chromium is installed; CI installs Debian's chromium."""

import functools
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
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


def test_the_first_screen_shows_every_implants_card(served, demo_plan, tmp_path):
    """At 1400 x 900 CSS px the report's first screen holds every card whole."""
    import json

    plan = json.loads((demo_plan / "plan.json").read_text())
    browser = Browser(CHROMIUM)
    try:
        browser.call("Emulation.setDeviceMetricsOverride", width=1400, height=900,
                     deviceScaleFactor=1, mobile=False)
        browser.open(f"{served}/report.html", settle=1.0)
        boxes = json.loads(browser.evaluate(
            "JSON.stringify(Array.from(document.querySelectorAll('section.card')).map(c => {"
            "const r = c.getBoundingClientRect(); return {site: c.dataset.site, top: r.top, "
            "bottom: r.bottom, left: r.left, right: r.right, "
            "text: c.innerText}; }))"))
        assert [b["site"] for b in boxes] == [c["site"] for c in plan["cards"]]
        for b, card in zip(boxes, plan["cards"], strict=True):
            assert 0 <= b["top"] and b["bottom"] <= 900, b  # whole, on the first screen
            assert 0 <= b["left"] and b["right"] <= 1400, b
            assert f"tooth {card['tooth_fdi']} (FDI)" in b["text"]
            assert card["next_step"] in b["text"]
        shot = browser.screenshot(tmp_path / "first_screen.png")
        from PIL import Image

        with Image.open(shot) as im:
            assert im.size == (1400, 900)
            # the cards are drawn: the verdict colours appear in the card's band
            band = np.asarray(im.convert("RGB"))[int(boxes[0]["top"]):int(boxes[0]["bottom"])]
            assert band.std() > 10
        assert browser.errors == []
    finally:
        browser.close()
