"""The studio screenshots (docs/studio_setup.png, docs/studio_teleop.png: README, commands.md), by
headless Chromium over DevTools on the status page, Meshcat's controls open (the Scene folder
folded). Not a test (no test_ prefix): run it from the repository root,

    python -m tests.analyses.studio_screenshots PLAN docs/studio_setup.png docs/studio_teleop.png

PLAN: a plan folder (``implantplan demo``'s); it is copied, the copy receives the recording.
Teleop: feed in with W at 16.9 mm/s to 45 mm, roll with X (held at beta), then M (sliders) with
the feed slider at 3 mm/s and the roll slider at -2 deg/s for 2 s.
"""

import json
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

from implantplan.analyses import studio as st
from implantplan.systems.teleop.master_input import SLIDERS
from tests.analyses.browser import Browser, find_chromium
from tests.analyses.test_studio_browser import SET_SLIDER, press


def in_meshcat(browser: Browser, expression: str):
    """Evaluate in the embedded Meshcat frame (an isolated world shares its DOM)."""
    frame = browser.call("Page.getFrameTree")["frameTree"]["childFrames"][0]["frame"]["id"]
    ctx = browser.call("Page.createIsolatedWorld", frameId=frame)["executionContextId"]
    r = browser.call("Runtime.evaluate", expression=expression, contextId=ctx,
                     returnByValue=True)
    return r["result"].get("value")


OPEN_CONTROLS = """(() => {[...document.querySelectorAll('.close-button')].forEach(
  b => { if (b.innerText.includes('Open')) b.click(); });
  [...document.querySelectorAll('li.title')].filter(e => e.innerText.trim() === 'Scene')
  .forEach(e => e.click()); return true; })()"""


def _drive(studio, status, setup_png: Path, teleop_png: Path, done: threading.Event) -> None:
    browser = Browser(find_chromium())
    try:
        browser.call("Emulation.setDeviceMetricsOverride", width=1500, height=1060,
                     deviceScaleFactor=1, mobile=False)
        browser.open(status.url, settle=4.0)
        in_meshcat(browser, OPEN_CONTROLS)
        time.sleep(1.0)
        for kind in ("mousePressed", "mouseReleased"):  # focus the 3D view: keys go there
            browser.call("Input.dispatchMouseEvent", type=kind, x=500, y=850, button="left",
                         clickCount=1)
        time.sleep(0.5)
        browser.screenshot(setup_png)
        press(browser, "KeyT", "t")
        time.sleep(2.0)
        for _ in range(3):
            press(browser, "KeyE", "e")
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            press(browser, "KeyW", "w")
            time.sleep(0.2)
            with status.lock:
                if studio.teleop is not None and studio.teleop.state()["feed"] > 0.045:
                    break
        for _ in range(4):
            press(browser, "KeyX", "x")
            time.sleep(0.2)
        press(browser, "KeyM", "m")
        time.sleep(1.5)
        in_meshcat(browser, SET_SLIDER % (json.dumps(SLIDERS["feed"][0]), "3.0"))
        in_meshcat(browser, SET_SLIDER % (json.dumps(SLIDERS["roll"][0]), "-2.0"))
        time.sleep(2.0)
        browser.screenshot(teleop_png)
        with status.lock:
            print(json.dumps(studio.status()["teleop"], default=str))
        press(browser, "KeyT", "t")
        time.sleep(2.0)
    finally:
        browser.close()
        done.set()


def main(argv: list[str]) -> int:
    plan_dir, setup_png, teleop_png = (Path(a) for a in argv)
    folder = shutil.copytree(plan_dir, Path(tempfile.mkdtemp()) / "plan")
    studio, meshcat, status = st.open_studio(folder, realtime_rate=1.0)
    done = threading.Event()
    person = threading.Thread(target=_drive, args=(studio, status, setup_png, teleop_png, done),
                              daemon=True)
    person.start()
    try:
        studio.run(lock=status.lock, stop=done)  # Meshcat answers on this thread only
    finally:
        done.set()
        person.join(timeout=60)
        status.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
