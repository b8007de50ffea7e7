"""Benchmark: the studio's responsiveness (targets: slider change -> updated indices
<= 100 ms; the teleop loop >= 5x real time at rate 1.0).

Run: ``python -m implantplan.analyses.bench_studio --plan DIR [--moves N] [--seconds T]``
(DIR: a plan folder, e.g. ``implantplan demo``'s ``out/implantplan-demo``).

Prints, in one run on the same plan:

- **slider -> indices**: N random base moves within 30 mm of the plan's base, each through
  Meshcat's API (``SetSliderValue`` then the studio's ``poll``, as a browser's slider message
  arrives): the time from the poll's start to the new layout's indices, percentiles, fast arm
  clearance and SceneGraph confirmation (analyses.live_setup.evaluate_layout + confirm_layout),
  median and max; then the whole poll (drawing the arm) and the capability view drawn when the
  slider rests (new voxels built on the way), median and max, and the fast part alone.
- **teleop headroom**: the live teleop diagram (fixture, supervisor, estimator, diff IK) stepped
  in 50 ms turns with no real-time pacing: simulated seconds per wall second (the headroom the
  loop has at target rate 1.0), after one warm-up run, side by side for the keyboard master (the
  feed key held), the keyboard with the feed and roll keys held, and the sliders master (Meshcat
  sliders read at every 5 ms sample: feed 5 mm/s, roll 2 deg/s).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--plan", type=Path, required=True, help="plan folder")
    ap.add_argument("--moves", type=int, default=40, help="slider moves (default 40)")
    ap.add_argument("--seconds", type=float, default=10.0, help="teleop seconds (default 10)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    from implantplan.analyses import live_setup as ls
    from implantplan.analyses import studio as st
    from implantplan.systems.teleop.master_input import SLIDERS, KeyboardMaster, SliderMaster

    studio, meshcat, status = st.open_studio(args.plan, realtime_rate=0.0, scan=False)
    try:
        sp = studio.sp
        rng = np.random.default_rng(args.seed)
        polls, caps, fast = [], [], []
        n0 = len(studio.latency)
        for _ in range(args.moves):
            xyz = np.clip(sp.base_xyz + rng.uniform(-0.03, 0.03, 3), sp.sc.lower, sp.sc.upper)
            for name, v in zip(st.BASE_SLIDERS, xyz, strict=True):
                meshcat.SetSliderValue(name, float(np.round(1e3 * v)))
            t0 = time.perf_counter()
            studio.poll()
            polls.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            studio.poll()  # the slider rests: the capability view
            caps.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            ls.evaluate_layout(sp, studio.layout.xyz)
            fast.append(time.perf_counter() - t0)
        lat = np.array(studio.latency[n0:])
        print(f"slider -> indices + SceneGraph ({len(lat)} moves): median "
              f"{1e3 * np.median(lat):.1f} ms, max {1e3 * lat.max():.1f} ms (target <= 100 ms)")
        print(f"  whole poll incl. drawing the arm: median "
              f"{1e3 * np.median(polls):.1f} ms, max {1e3 * max(polls):.1f} ms")
        print(f"  capability view when the slider rests: median "
              f"{1e3 * np.median(caps):.1f} ms, max {1e3 * max(caps):.1f} ms")
        print(f"  fast evaluation alone: median {1e3 * np.median(fast):.1f} ms, "
              f"max {1e3 * max(fast):.1f} ms")

        case = sp.teleop_case(0)
        sliders = SliderMaster(meshcat, add=False)

        def run(master: str):
            kb = KeyboardMaster()
            keys = {"keyboard": ("feed_in",), "keyboard + roll": ("feed_in", "roll+")}
            source = kb
            if master == "sliders":
                sliders.add()
                meshcat.SetSliderValue(SLIDERS["feed"][0], 5.0)
                meshcat.SetSliderValue(SLIDERS["roll"][0], 2.0)
                source = sliders
            lt = ls.LiveTeleop(case, source, realtime_rate=0.0)
            t0 = time.perf_counter()
            while lt.time < args.seconds - 1e-9:
                for key in keys.get(master, ()):
                    kb.press(key, lt.time)
                lt.advance(0.05)
                lt.state()
            wall = time.perf_counter() - t0
            sliders.remove()
            return lt.time, wall

        run("keyboard")  # warm-up
        for master in ("keyboard", "keyboard + roll", "sliders"):
            sim, wall = run(master)
            print(f"teleop loop, {master}: {sim:.1f} s simulated in {wall:.2f} s wall: "
                  f"{sim / wall:.1f}x real time (target >= 5x at rate 1.0)")
    finally:
        status.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
