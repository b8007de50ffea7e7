"""The studio in headless Chromium over the DevTools protocol (loopback): the page loads, a base
slider moved in the page moves the base and changes the indices, the feed keys pressed in the page
drive the tool along the feed to the fixture's stop, the roll key turns it (held at beta by the
fixture), G hides the FPSM slices, M hands the master to the sliders and a slider moved in the page
backs the tool out; the run is recorded and replays to the same end pose and orientation; the
status page shows the numbers. Assertions on the server side.

Skipped (with the reason) when no Chromium is installed; CI installs Debian's chromium."""

import json
import shutil
import threading
import time

import numpy as np
import pytest

from implantplan.analyses import studio as st
from implantplan.analyses.cli import main
from implantplan.systems.teleop.master_input import SLIDERS
from tests.analyses.browser import Browser, find_chromium

CHROMIUM = find_chromium()
pytestmark = [pytest.mark.browser,
              pytest.mark.skipif(CHROMIUM is None, reason="no chromium on this machine "
                                 "(apt-get install chromium)")]

SET_SLIDER = """(function(name, value) {
  const li = [...document.querySelectorAll('li.cr.number')].find(
      e => e.querySelector('.property-name').innerText === name);
  if (!li) return false;
  const input = li.querySelector('input');
  input.value = String(value);
  input.dispatchEvent(new Event('change'));
  return true;
})(%s, %s)"""


def press(browser: Browser, code: str, key: str) -> None:
    for kind in ("keyDown", "keyUp"):
        browser.call("Input.dispatchKeyEvent", type=kind, code=code, key=key,
                     windowsVirtualKeyCode=ord(key.upper()))


def wait_for(condition, seconds: float = 20.0) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.1)
    return False


def _drive(studio, meshcat_url, status, x0, tmp_path, seen: dict) -> None:
    """The person at the browser (a thread: Meshcat itself is served from the test's thread,
    which runs the studio's loop). Records what it saw in ``seen``."""
    browser = None
    try:
        browser = Browser(CHROMIUM)
        browser.open(meshcat_url, settle=3.0)
        with status.lock:
            before = studio.layout
        seen["before"] = before
        seen["slider_found"] = browser.evaluate(SET_SLIDER % (json.dumps(st.BASE_SLIDERS[0]),
                                                              json.dumps(x0 + 15.0)))
        wait_for(lambda: studio.layout is not before)
        with status.lock:
            seen["after"] = studio.layout
        time.sleep(1.0)
        browser.screenshot(tmp_path / "setup.png")

        press(browser, "KeyT", "t")  # teleop on
        wait_for(lambda: studio.mode == "teleop")
        for _ in range(3):
            press(browser, "KeyE", "e")  # faster: 16.9 mm/s
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            press(browser, "KeyW", "w")
            time.sleep(0.2)
            with status.lock:
                s = studio.status()["teleop"]
            if s["to_target_mm"] < 1.0 and s["t_s"] > 5.0:
                break
        for _ in range(5):  # keep pushing: the fixture holds the tool at its end
            press(browser, "KeyW", "w")
            time.sleep(0.2)
        with status.lock:
            seen["teleop"] = studio.status()["teleop"]
        for _ in range(5):  # roll about the feed axis (the fixture holds it at beta)
            press(browser, "KeyX", "x")
            time.sleep(0.2)
        press(browser, "KeyG", "g")  # hide the FPSM slices
        wait_for(lambda: not studio.slices_visible, 5.0)
        with status.lock:
            seen["rolled"] = studio.teleop.state()
            seen["slices_visible"] = studio.slices_visible
        press(browser, "KeyM", "m")  # the sliders drive now
        wait_for(lambda: studio.master == "sliders", 5.0)
        t_out = time.monotonic()
        seen["feed_slider_found"] = browser.evaluate(
            SET_SLIDER % (json.dumps(SLIDERS["feed"][0]), json.dumps(-5.0)))
        time.sleep(1.0)  # 1 s back out at 5 mm/s
        press(browser, "KeyP", "p")  # the sliders back to zero
        wait_for(lambda: studio.sliders.last["feed"] == 0.0, 5.0)
        seen["out_seconds"] = time.monotonic() - t_out  # the slider's wall time at -5 mm/s
        with status.lock:
            seen["backed"] = studio.teleop.state()
            seen["end"] = studio.teleop.state()["X_WE"]
            seen["master"] = studio.master
        browser.screenshot(tmp_path / "teleop.png")
        press(browser, "KeyT", "t")  # teleop off: the run is saved
        wait_for(lambda: studio.mode == "setup" and studio.saved)
        # the status page serves the numbers
        browser.open(status.url, settle=1.5)
        for _ in range(40):  # the page polls the status; on a loaded machine it takes longer
            seen["shown_mode"] = browser.evaluate(
                "window.studioStatus && window.studioStatus.mode")
            if seen["shown_mode"] is not None:
                break
            time.sleep(0.25)
        seen["errors"] = list(browser.errors)
    except Exception as exc:  # noqa: BLE001 - reported by the test's assertions
        seen["exception"] = repr(exc)
    finally:
        if browser is not None:
            browser.close()
        seen["done"] = True


def test_studio_in_a_browser(demo_plan, tmp_path):
    folder = shutil.copytree(demo_plan, tmp_path / "plan")
    studio, meshcat, status = st.open_studio(folder, realtime_rate=1.0)
    x0 = meshcat.GetSliderValue(st.BASE_SLIDERS[0])
    url = meshcat.web_url()  # Meshcat answers only on the thread that made it
    seen: dict = {}
    stop = threading.Event()
    def person_at_the_browser():
        try:
            _drive(studio, url, status, x0, tmp_path, seen)
        finally:
            stop.set()

    person = threading.Thread(target=person_at_the_browser, daemon=True)
    person.start()
    try:
        studio.run(lock=status.lock, stop=stop)
    finally:
        stop.set()
        person.join(timeout=60)
        status.close()
    assert seen.get("done") and "exception" not in seen, seen.get("exception")
    assert seen["slider_found"]
    before, after = seen["before"], seen["after"]
    assert after is not before
    assert after.xyz[0] == pytest.approx(1e-3 * (x0 + 15.0))
    assert not np.array_equal(after.indices, before.indices)
    s = seen["teleop"]
    assert s["feed_mm"] > s["feed_length_mm"] - 1.0
    assert s["feed_mm"] < s["feed_length_mm"] + 0.5  # stopped at the fixture's end
    assert not s["alarm"]
    beta = studio.sp.plan["sites"][0]["vf"]["angle_tolerance"]
    assert seen["rolled"]["roll"] == pytest.approx(beta, abs=1e-6)
    assert seen["slices_visible"] is False
    assert seen["master"] == "sliders"
    assert seen["feed_slider_found"]
    backed = seen["rolled"]["feed"] - seen["backed"]["feed"]
    # about 1 s at 5 mm/s out, stopped by P: the simulation runs at most real time, so no
    # further than 5 mm/s for as long as the slider stood at -5 (longer on a loaded machine)
    assert 0.002 < backed < 0.005 * seen["out_seconds"] + 0.001
    assert seen["shown_mode"] == "setup"
    assert seen["errors"] == []
    assert studio.saved
    out = tmp_path / "replay"
    assert main(["simulate", "feeding", "--csv", str(studio.saved[0]), "--out", str(out)]) == 0
    rep = json.loads((out / "feeding.json").read_text())
    assert np.asarray(rep["end_X_WE"]) == pytest.approx(seen["end"], abs=1e-6)
    assert rep["end_angle_difference_rad"] < 1e-6
