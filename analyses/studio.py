"""``implantplan studio [CASE.yaml | --plan DIR] [--port N] [--host 127.0.0.1]``: the planning
studio (DESIGN.md section 10), a live 3D planner in the browser with a person at the master device.

Drake's Meshcat is the 3D view and the controls; the numbers are on a small status page served
beside it (Meshcat's controls have buttons and sliders but no text element; a status page is
plain HTML that any browser shows, the Meshcat view embedded on its left). From a case file the
studio plans first (``implantplan plan``'s pipeline, with its progress, into ``--out``); from a
plan folder it opens the plan. It runs until Ctrl-C or the Quit button.

**Setup mode.** Sliders: the base position x/y/z in Oral (mm, within the scenario's bounds), the
Pareto member (sets the base to that member of the plan's front) and the site (whose feed the arm
shows). On every change (analyses.live_setup): each site's IK branch, the three MOPRP indices
(worst over the sites) and their percentiles, the fast model's arm clearance and SceneGraph's
along every feed, the capability index at each target (the voxels around the targets drawn in
HSV, red 0 to blue 1) and the tool's clearances. The arm turns red when a clearance is below the
scenario's margin. "Keep layout" writes the layout into the plan folder's plan.json (atomically)
with the layout's checks recomputed.

**Teleop mode** (button or key T): the teleop diagram (fixture, supervisor, estimator, diff IK,
arm) of the selected site at the current base, driven at real time by the keyboard
(:data:`KEYS`: feed in/out W/S, lateral x A/D, lateral y R/F, roll about the feed axis Z/X, tilt
about the lateral axes I/K and J/L, faster/slower E/Q, pause P) or by the sliders
(systems.teleop.master_input.SLIDERS: feed, lateral x/y in mm/s and roll in deg/s, zero in the
middle,
in the controls from the start and read only by the sliders master;
"Master keyboard/sliders" or key M switches, also during a run; P then puts the sliders back to
zero). The fixture holds the tool's orientation within beta (0.5 deg) of the planned one, roll
and tilt alike. The fixture's force is drawn as an orange arrow at the tool while it acts
(the tool held at the fixture's wall and pushed out: the damping on the outward command, 10 mm
per N), the estimator's alarm turns the tool marker red. Leaving teleop mode (T) or "Save
recording" (V) writes the run as a MasterDevice CSV (``t_s,x_m,y_m,z_m,rx_rad,ry_rad,rz_rad``)
in the plan folder's ``recordings/`` (with ``<name>.json`` naming the case), which
``implantplan simulate feeding --csv FILE --out DIR`` replays. "FPSM slices on/off" (key G)
shows or hides the FPSM's slices in either mode.

The event handling is :class:`Studio` (``poll()`` once per loop turn), driven through Meshcat's
API in the tests.
"""

from __future__ import annotations

import argparse
import colorsys
import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np

from implantplan.analyses import live_setup as ls
from implantplan.analyses import out_folder
from implantplan.systems.capability import maps as cm
from implantplan.systems.errors import InputError
from implantplan.systems.files import to_jsonable, write_json
from implantplan.systems.robot import moprp
from implantplan.systems.teleop.master_input import SLIDERS, KeyboardMaster, SliderMaster

BASE_SLIDERS = ("base x (mm)", "base y (mm)", "base z (mm)")
PARETO_SLIDER = "Pareto member"
SITE_SLIDER = "site"
KEEP, QUIT, TELEOP, SAVE = "Keep layout", "Quit", "Teleop on/off [T]", "Save recording [V]"
MASTER, SLICES = "Master keyboard/sliders [M]", "FPSM slices on/off [G]"
MASTERS = ("keyboard", "sliders")
# teleop keys: action -> (button label, key code)
KEYS = {
    "feed_in": ("Feed in [W]", "KeyW"),
    "feed_out": ("Feed out [S]", "KeyS"),
    "lateral_x-": ("Lateral x- [A]", "KeyA"),
    "lateral_x+": ("Lateral x+ [D]", "KeyD"),
    "lateral_y+": ("Lateral y+ [R]", "KeyR"),
    "lateral_y-": ("Lateral y- [F]", "KeyF"),
    "roll-": ("Roll - [Z]", "KeyZ"),
    "roll+": ("Roll + [X]", "KeyX"),
    "tilt_x+": ("Tilt x+ [I]", "KeyI"),
    "tilt_x-": ("Tilt x- [K]", "KeyK"),
    "tilt_y-": ("Tilt y- [J]", "KeyJ"),
    "tilt_y+": ("Tilt y+ [L]", "KeyL"),
    "faster": ("Faster [E]", "KeyE"),
    "slower": ("Slower [Q]", "KeyQ"),
    "pause": ("Pause [P]", "KeyP"),
}
ARM_OK = (0.75, 0.75, 0.8, 1.0)
ARM_RED = (0.9, 0.1, 0.1, 1.0)


def hsv_colour(index: float) -> tuple[float, float, float]:
    """Capability index 0..1 -> RGB on the HSV hue from red (0) to blue (1)."""
    return colorsys.hsv_to_rgb(float(np.clip(index, 0.0, 1.0)) * (2.0 / 3.0), 0.9, 0.95)


def _mm(x):
    return None if x is None else np.round(np.asarray(x, dtype=float) * 1e3, 2)


class Studio:
    """The studio's state and event handling on one Meshcat (see the module docstring).

    Args:
        sp: the opened plan (analyses.live_setup.load_plan).
        meshcat: a pydrake.geometry.Meshcat.
        scan: the opened scan (mesh frame) to draw, or None.
        realtime_rate: the teleop Simulator's target real-time rate (1.0; tests use 0).
        teleop_step: simulated seconds per poll in teleop mode.
        master: the teleop master to start with, "keyboard" or "sliders" (key M switches).
    """

    def __init__(self, sp: ls.StudioPlan, meshcat, *, scan=None, realtime_rate: float = 1.0,
                 teleop_step: float = 0.05, master: str = "keyboard"):
        if master not in MASTERS:
            raise InputError("--master", f"expected one of {', '.join(MASTERS)}, got {master!r}")
        self.sp = sp
        self.meshcat = meshcat
        self.realtime_rate = realtime_rate
        self.teleop_step = teleop_step
        self.master = master
        self.sliders: SliderMaster  # made with the controls (_add_controls)
        self.slices_visible = True
        self.mode = "setup"
        self.site = 0
        self.layout: ls.Layout | None = None
        self.capability = ls.CapabilityView(sp)
        self.teleop: ls.LiveTeleop | None = None
        self.keyboard: KeyboardMaster | None = None
        self.saved: list[Path] = []
        self.kept: list[Path] = []
        self.latency: list[float] = []  # s, slider change -> indices updated (fast + SceneGraph)
        self.messages: list[str] = []
        self._clicks: dict[str, int] = {}
        self._draw_case(scan)
        self._add_controls()
        self._build_setup_arm()
        self.update(sp.base_xyz)
        self.show_capability()

    # -- scene and controls ---------------------------------------------------------------------
    def _draw_case(self, scan) -> None:
        from types import SimpleNamespace

        from implantplan.analyses.figures.scene import draw_site
        from implantplan.systems.placement.fixture import VirtualFixture

        for k, s in enumerate(self.sp.plan["sites"]):
            pl = s["placement"]
            placement = SimpleNamespace(
                X_CH=np.asarray(pl["X_CH"], dtype=float), X_CT=np.asarray(pl["X_CT"], float),
                line1=pl["line1"], line2=pl["line2"], vf=VirtualFixture.from_dict(s["vf"]))
            draw_site(self.meshcat, opened=scan, fpsm=self.sp.fpsm,
                      X_WCenter=self.sp.X_WCenter, placement=placement,
                      prefix=f"/case/{s['name']}", scan=scan is not None and k == 0,
                      slices=k == 0)
        target = self.sp.X_WCenter[:3, 3]
        base = self.sp.sc.X_WO @ moprp.base_pose(self.sp.base_xyz)
        away = target - base[:3, 3]
        away[2] = 0.0
        away /= max(np.linalg.norm(away), 1e-9)
        # from the side away from the robot, a little above the mouth (the arm comes from above)
        self.meshcat.SetCameraPose(target + np.array([0.0, 0.0, 0.25]) + 0.8 * away, target)

    def _add_controls(self) -> None:
        m, sc = self.meshcat, self.sp.sc
        for k, name in enumerate(BASE_SLIDERS):
            m.AddSlider(name, 1e3 * sc.lower[k], 1e3 * sc.upper[k], 1.0,
                        1e3 * self.sp.base_xyz[k])
        P = max(len(self.sp.pareto_xyz), 1)
        m.AddSlider(PARETO_SLIDER, 0, P - 1, 1, self._nearest_member(self.sp.base_xyz))
        m.AddSlider(SITE_SLIDER, 0, len(self.sp.names) - 1, 1, 0)
        for name, key in ((KEEP, ""), (TELEOP, "KeyT"), (SAVE, "KeyV"), (MASTER, "KeyM"),
                          (SLICES, "KeyG"), (QUIT, "")):
            m.AddButton(name, key)
        for label, key in KEYS.values():
            m.AddButton(label, key)
        # the master sliders are there from the start, at 0 (still) unless they drive: a slider
        # added while a busy page is live could be missed by it until a reload
        self.sliders = SliderMaster(m)
        self._clicks = {n: m.GetButtonClicks(n) for n in m.GetButtonNames()}
        self._sliders = self._slider_values()

    def _nearest_member(self, xyz) -> int:
        if len(self.sp.pareto_xyz) == 0:
            return 0
        return int(np.argmin(np.linalg.norm(self.sp.pareto_xyz - xyz, axis=1)))

    def _slider_values(self) -> dict:
        return {n: self.meshcat.GetSliderValue(n) for n in
                (*BASE_SLIDERS, PARETO_SLIDER, SITE_SLIDER)}

    def _build_setup_arm(self) -> None:
        """The plant at the current base for setup mode (moved by a parent transform after)."""
        from implantplan.diagrams.plant import build_plant

        xyz = self.sp.base_xyz if self.layout is None else self.layout.xyz
        self._arm_X_WB = self.sp.sc.X_WO @ moprp.base_pose(xyz)
        self._arm = build_plant(scenario=self.sp.sc, X_WBase=self._arm_X_WB,
                                limits=self.sp.sc.limits, tool=True, meshcat=self.meshcat)
        self._arm_context = self._arm[0].CreateDefaultContext()
        self.meshcat.SetProperty("/drake/visualizer/patient", "visible", False)

    def _show_arm(self, layout: ls.Layout) -> None:
        from pydrake.math import RigidTransform

        diagram, plant, _, handles = self._arm
        k = self.site
        if layout.branch[k] >= 0:
            plant.SetPositions(plant.GetMyMutableContextFromRoot(self._arm_context), handles.arm,
                               layout.q[k])
        diagram.ForcedPublish(self._arm_context)
        offset = RigidTransform((self.sp.sc.X_WO @ moprp.base_pose(layout.xyz))
                                @ np.linalg.inv(self._arm_X_WB))
        for model in ("aubo", "actuator", "cart"):
            self.meshcat.SetTransform(f"/drake/visualizer/{model}", offset)
        ok = layout.clear and layout.confirmed is not False
        colour = ARM_OK if ok else ARM_RED
        for model in ("aubo", "actuator"):
            self.meshcat.SetProperty(f"/drake/visualizer/{model}", "color", list(colour))

    def _show_capability(self, cap: dict) -> None:
        from pydrake.geometry import Rgba, Sphere
        from pydrake.math import RigidTransform

        self.meshcat.Delete("/studio/capability")
        for i, (p, idx) in enumerate(zip(cap["centres_W"], cap["voxel_index"], strict=True)):
            path = f"/studio/capability/v{i}"
            self.meshcat.SetObject(path, Sphere(0.004), Rgba(*hsv_colour(idx), 0.8))
            self.meshcat.SetTransform(path, RigidTransform(p))

    @property
    def slices_path(self) -> str:
        """The Meshcat path of the FPSM slices (drawn with the first site)."""
        return f"/case/{self.sp.names[0]}/fpsm"

    def show_slices(self, visible: bool) -> None:
        """Show or hide the FPSM slices."""
        self.slices_visible = bool(visible)
        self.meshcat.SetProperty(self.slices_path, "visible", self.slices_visible)

    # -- setup ------------------------------------------------------------------------------------
    def update(self, xyz) -> ls.Layout:
        """Evaluate the base ``xyz`` (m, Oral), show it, and return the layout."""
        t0 = time.perf_counter()
        layout = ls.evaluate_layout(self.sp, xyz)
        ls.confirm_layout(self.sp, layout)
        self.latency.append(time.perf_counter() - t0)
        self.layout = layout
        self._show_arm(layout)
        self._capability_due = True  # drawn once the base rests for a poll (see poll)
        return layout

    def show_capability(self) -> dict:
        """The capability around the targets from the current base, drawn (new voxels are
        built: up to ~0.5 s, so it waits until a slider rests)."""
        cap = self.capability.at(self.layout)
        self._show_capability(cap)
        self._capability_due = False
        return cap

    def keep(self) -> Path:
        """Write the current layout into the plan folder's plan.json (atomically), with the
        layout's checks recomputed; returns the path."""
        from implantplan.analyses import cards
        from implantplan.analyses import checks as checks_

        lay, sp = self.layout, self.sp
        if not lay.feasible:
            self.messages.append("keep: not kept, a site has no IK branch at this base")
            raise InputError("Keep layout", "expected a base where every site has an IK branch")
        plan = json.loads(json.dumps(to_jsonable(sp.plan)))
        base = plan["base"]
        base["xyz_in_oral"] = lay.xyz
        base["X_WBase"] = sp.sc.X_WO @ moprp.base_pose(lay.xyz)
        base["indices_worst_over_sites"] = dict(zip(moprp.INDEX_NAMES, lay.indices.tolist(),
                                                    strict=True))
        base["percentiles"] = dict(zip(moprp.INDEX_NAMES, lay.percentiles.tolist(), strict=True))
        base["rule"] = "kept in the studio (the planned knee point was " \
            f"{np.round(1e3 * sp.base_xyz, 1).tolist()} mm)"
        cap = lay.capability or self.show_capability()
        checks = [c for c in plan["checks"] if c["id"] not in checks_.LAYOUT_CHECK_IDS]
        for k, s in enumerate(plan["sites"]):
            feed = lay.confirmation[k]
            s["ik"].update({
                "branch": int(lay.branch[k]), "q": lay.q[k], "q_pre": lay.q_pre[k],
                "indices": dict(zip(moprp.INDEX_NAMES, lay.site_indices[k].tolist(),
                                    strict=True)),
                **checks_.scene_graph_fields(lay.confirmation, k)})
            s["feeding_target"]["X_BaseEnd"] = moprp.target_pose(lay.xyz, sp.X_OT[k])
            s["capability"] = checks_.capability_fields(
                cap["params"], reachable=cap["map_reachable"][k], source=cap["map_source"][k],
                index=cap["index"][k], neighbourhood_index=cap["neighbourhood_index"][k],
                ik_branches=cap["ik_branches"][k])
            if s.get("simulation") is not None:
                s["simulation"]["layout"] = "the planned base (not re-simulated in the studio)"
            n = s["name"]
            checks += checks_.layout_checks(n, feed, ik_branches=cap["ik_branches"][k],
                                            neighbourhood_index=cap["neighbourhood_index"][k])
        plan["checks"] = checks
        plan["passed"] = checks_.passed(checks)
        plan["cards"] = cards.surgeon_cards(to_jsonable(plan))
        plan.pop("schema_version", None)
        plan.pop("kind", None)
        path = write_json(sp.folder / "plan.json", plan, kind="plan")
        sp.plan = json.loads(path.read_text())
        self.kept.append(path)
        self.messages.append(f"kept the layout at {np.round(1e3 * lay.xyz, 1).tolist()} mm: "
                             f"checks {'pass' if plan['passed'] else 'FAIL'}")
        return path

    # -- teleop -----------------------------------------------------------------------------------
    def start_teleop(self) -> None:
        lay = self.layout
        if lay.branch[self.site] < 0:
            self.messages.append("teleop: this site has no IK branch at this base")
            return
        case = self.sp.teleop_case(self.site, lay.xyz, q_pre=lay.q_pre[self.site])
        self.keyboard = KeyboardMaster()
        self.meshcat.Delete("/studio/capability")
        self.teleop = ls.LiveTeleop(case, self.keyboard, meshcat=self.meshcat,
                                    realtime_rate=self.realtime_rate)
        self.meshcat.SetProperty("/drake/visualizer/patient", "visible", False)
        self.mode = "teleop"
        self.set_master(self.master)
        self.messages.append(f"teleop: site {self.sp.names[self.site]}, "
                             + ("keys W/S feed" if self.master == "keyboard" else
                                "sliders feed/lateral/roll"))

    def set_master(self, kind: str) -> None:
        """Drive teleop with the keyboard or the sliders (a running run switches at once: the
        live device asks its new source from the next control period on)."""
        if kind not in MASTERS:
            raise InputError("master", f"expected one of {', '.join(MASTERS)}, got {kind!r}")
        self.master = kind
        if self.teleop is None:
            return
        if kind == "sliders":
            self.teleop.device.source = self.sliders
        else:
            self.sliders.stop()
            self.keyboard.release()
            self.teleop.device.source = self.keyboard

    def stop_teleop(self) -> None:
        if self.teleop is not None and self.teleop.time > 0:
            self.save_recording()
        self.teleop = None
        self.sliders.stop()
        self.mode = "setup"
        self.meshcat.Delete("/drake")
        self.meshcat.Delete("/studio/force")
        self.meshcat.Delete("/studio/tool")
        self._build_setup_arm()
        self.update(self.layout.xyz)
        self.show_capability()

    def save_recording(self) -> Path:
        """Write the teleop run so far as MasterDevice CSV in ``recordings/`` with its case."""
        folder = self.sp.folder / "recordings"
        folder.mkdir(exist_ok=True)
        name = f"teleop_site{self.sp.names[self.site]}_{time.strftime('%Y%m%d-%H%M%S')}"
        n = sum(1 for _ in folder.glob(name + "*.csv"))
        path = folder / (f"{name}_{n}.csv" if n else f"{name}.csv")
        self.teleop.save(path)
        case = self.teleop.case
        write_json(path.with_suffix(".json"), {
            "plan": "..", "site": self.sp.names[self.site], "base_xyz": self.layout.xyz,
            "q_start": case.q_start, "duration_s": self.teleop.time,
            "end_X_WE": self.teleop.state()["X_WE"]}, kind="teleop_recording")
        self.saved.append(path)
        self.messages.append(f"recorded {path.name}")
        return path

    def _teleop_turn(self, pressed: list[str]) -> None:
        from pydrake.geometry import Rgba, Sphere
        from pydrake.math import RigidTransform

        t = self.teleop
        for action in pressed:
            if action == "pause" and self.master == "sliders":
                self.sliders.stop()
            else:
                self.keyboard.press(action, t.time)
        t.advance(self.teleop_step)
        st = t.state()
        p = st["p_WE"]
        self._draw_force(p, st["F_W_fixture"])
        self.meshcat.SetObject("/studio/tool", Sphere(0.002),
                               Rgba(0.9, 0.1, 0.1, 1) if st["alarm"] else Rgba(0.1, 0.8, 0.2, 1))
        self.meshcat.SetTransform("/studio/tool", RigidTransform(p))

    def _draw_force(self, p_WE, F_W) -> None:
        """The fixture's force at the tool as an orange arrow (shaft and cone, 10 mm per N, at
        most 6 cm; a WebGL line would be 1 px whatever its width), hidden while it does not act
        (below :data:`FORCE_SHOWN_N`)."""
        from pydrake.geometry import Cylinder, MeshcatCone, Rgba
        from pydrake.math import RigidTransform, RotationMatrix

        F = np.asarray(F_W, dtype=float)
        size = float(np.linalg.norm(F))
        shown = size >= FORCE_SHOWN_N
        self.meshcat.SetProperty("/studio/force", "visible", shown)
        if not shown:
            return
        length = min(FORCE_MM_PER_N * 1e-3 * size, 0.06)
        head = min(0.006, 0.5 * length)
        orange = Rgba(1.0, 0.5, 0.0, 1.0)
        R = RotationMatrix.MakeFromOneVector(F / size, 2)  # z along the force
        self.meshcat.SetObject("/studio/force/shaft", Cylinder(0.0012, length - head), orange)
        self.meshcat.SetTransform("/studio/force/shaft",
                                  RigidTransform(R, p_WE + R.col(2) * 0.5 * (length - head)))
        self.meshcat.SetObject("/studio/force/head", MeshcatCone(head, 0.003, 0.003), orange)
        # Meshcat's cone has its apex at the origin and opens along +z: flip it onto the tip
        self.meshcat.SetTransform("/studio/force/head", RigidTransform(
            R @ RotationMatrix.MakeXRotation(np.pi), p_WE + R.col(2) * length))

    # -- the loop -----------------------------------------------------------------------------
    def _new_clicks(self) -> dict[str, int]:
        out = {}
        for name in self.meshcat.GetButtonNames():
            c = self.meshcat.GetButtonClicks(name)
            if c != self._clicks.get(name, 0):
                out[name] = c - self._clicks.get(name, 0)
            self._clicks[name] = c
        return out

    def poll(self) -> bool:
        """Handle what changed since the last call; False once Quit was pressed."""
        clicks = self._new_clicks()
        if QUIT in clicks:
            return False
        if clicks.get(SLICES, 0) % 2:
            self.show_slices(not self.slices_visible)
        if clicks.get(MASTER, 0) % 2:
            self.set_master(MASTERS[1 - MASTERS.index(self.master)])
        if self.mode == "teleop":
            if TELEOP in clicks:
                self.stop_teleop()
                return True
            if SAVE in clicks:
                self.save_recording()
            pressed = [a for a, (label, _) in KEYS.items() for _ in range(clicks.get(label, 0))]
            self._teleop_turn(pressed)
            return True
        values = self._slider_values()
        changed = {n for n, v in values.items() if v != self._sliders.get(n)}
        if PARETO_SLIDER in changed and len(self.sp.pareto_xyz):
            xyz = self.sp.pareto_xyz[int(round(values[PARETO_SLIDER]))]
            for name, v in zip(BASE_SLIDERS, xyz, strict=True):
                self.meshcat.SetSliderValue(name, float(np.round(1e3 * v)))
            values = self._slider_values()
        if SITE_SLIDER in changed:
            self.site = int(round(values[SITE_SLIDER]))
        self._sliders = values
        if changed:
            self.update(np.array([values[n] for n in BASE_SLIDERS]) * 1e-3)
        elif self._capability_due:
            self.show_capability()
        if KEEP in clicks:
            try:
                self.keep()
            except InputError:
                pass
        if TELEOP in clicks:
            self.start_teleop()
        return True

    def status(self) -> dict:
        """What the status page shows (mm, deg, %), JSON-able."""
        lay, sp = self.layout, self.sp
        out = {"mode": self.mode, "site": sp.names[self.site], "sites": sp.names,
               "margin_mm": 1e3 * sp.sc.clearance, "messages": self.messages[-5:],
               "master": self.master, "fpsm_slices": self.slices_visible, "keys": help_keys()}
        if lay is not None:
            out["setup"] = {
                "base_mm": _mm(lay.xyz), "feasible": lay.feasible,
                "branch": lay.branch, "why": lay.reasons,
                "indices": dict(zip(moprp.INDEX_NAMES, lay.indices.tolist(), strict=True)),
                "percentiles": dict(zip(moprp.INDEX_NAMES, lay.percentiles.tolist(),
                                        strict=True)),
                "arm_clearance_fast_mm": _mm(lay.arm_clearance),
                "arm_clearance_scene_graph_mm": _mm([c["distance"] for c in lay.confirmation]
                                                    if lay.confirmation else None),
                "clear": lay.clear, "confirmed": lay.confirmed,
                "joint_headroom_deg": None if not lay.confirmation else
                [float(np.rad2deg(np.min(c["headroom"]))) for c in lay.confirmation],
                "cart_clearance_mm": _mm(lay.cart_clearance),
                "capability_index": None if lay.capability is None else
                lay.capability["index"],
                "capability_neighbourhood": None if lay.capability is None else
                lay.capability["neighbourhood_index"],
                "capability_reachable": None if lay.capability is None else
                [{"reachable": bool(r), "answer": cm.SOURCES[int(src)]} for r, src in
                 zip(lay.capability["map_reachable"], lay.capability["map_source"],
                     strict=True)],
                "tool_clearance_mm": [{k: _mm(v) for k, v in c.items()}
                                      for c in sp.tool_clearances()],
                "latency_ms": 1e3 * self.latency[-1] if self.latency else None,
            }
        if self.teleop is not None:
            st = self.teleop.state()
            out["teleop"] = {"t_s": st["t"], "feed_mm": 1e3 * st["feed"],
                             "feed_length_mm": 1e3 * st["feed_length"],
                             "to_target_mm": 1e3 * st["to_target"],
                             "fixture_force_N": st["F_W_fixture"], "alarm": st["alarm"],
                             "barrier_h_mm": 1e3 * st["barrier"][0],
                             "roll_deg": np.rad2deg(st["roll"]),
                             "tilt_deg": np.rad2deg(st["tilt"]),
                             "angle_to_plan_deg": np.rad2deg(st["angle_to_plan"]),
                             "master": self.master,
                             "speed_mm_s": 1e3 * self.keyboard.speed,
                             "rate_deg_s": np.rad2deg(self.keyboard.rate),
                             "paused": self.keyboard.paused}
            out["teleop"]["sliders"] = dict(self.sliders.last)  # any thread may ask
        out["card"] = self.card()
        out["recordings"] = [p.name for p in self.saved]
        return to_jsonable(out)

    def card(self) -> dict | None:
        """The selected site's surgeon's card (analyses.cards) as plan.json holds it (the
        planned layout, or the one last kept), in the report's words and units."""
        from implantplan.analyses import cards

        found = [c for c in self.sp.plan.get("cards") or []
                 if c["site"] == self.sp.names[self.site]]
        if not found:
            return None
        c = found[0]
        return {"title": cards.card_title(c), "verdict": c["verdict"],
                "next_step": c["next_step"], "lines": dict(cards.card_lines(c))}

    def run(self, *, lock=None, stop=None, idle: float = 0.02) -> None:
        """Poll until Quit or ``stop`` (a threading.Event) is set; each turn holds ``lock``
        (the status page reads under it). Ctrl-C raises KeyboardInterrupt to the caller."""
        lock = lock or threading.Lock()
        while stop is None or not stop.is_set():
            with lock:
                going = self.poll()
            if not going:
                return
            if self.mode == "setup":
                time.sleep(idle)


KEY_HELP = {
    "feed_in": "along the fixture into the mouth", "feed_out": "back out along it",
    "lateral_x-": "across the feed", "lateral_x+": "across the feed",
    "lateral_y+": "across the feed", "lateral_y-": "across the feed",
    "roll-": "turn about the feed axis (the rod)", "roll+": "turn about the feed axis (the rod)",
    "tilt_x+": "turn about lateral x", "tilt_x-": "turn about lateral x",
    "tilt_y-": "turn about lateral y", "tilt_y+": "turn about lateral y",
    "faster": "speed and turn rate x1.5", "slower": "speed and turn rate /1.5",
    "pause": "stop every motion (sliders: back to 0)",
}


def help_keys() -> list[str]:
    """The studio's keys and sliders, one line each (the status page, ``studio --help`` and the
    command's start-up lines show them)."""
    lines = [f"{label}: {KEY_HELP[action]}" for action, (label, _) in KEYS.items()]
    lines += [f"{TELEOP}: teleop mode on/off (off saves the run)", f"{SAVE}: save the run so far",
              f"{MASTER}: teleop from the keyboard or the sliders",
              f"{SLICES}: show/hide the FPSM slices"]
    lines += [f"slider {label}: -{half:g}..{half:g}, 0 = still (sliders master)"
              for label, half, *_ in SLIDERS.values()]
    lines.append("the fixture holds roll and tilt within beta (0.5 deg by default) of the plan")
    return lines


FORCE_SHOWN_N = 0.05  # N: the fixture's force arrow shows from this size on
FORCE_MM_PER_N = 10.0  # the arrow's length per newton


# -- the status page -------------------------------------------------------------------------------

PAGE = """<!doctype html><html><head><meta charset="utf-8"><title>implantplan studio</title>
<style>body{margin:0;display:flex;height:100vh;font:13px system-ui,sans-serif}
iframe{flex:1;border:0}#p{width:340px;overflow:auto;padding:8px;background:#f4f4f6}
td{padding:1px 4px;vertical-align:top}.bad{color:#c00;font-weight:bold}
#card{background:#fff;border:1px solid #ccc;padding:4px}.v-refused b{color:#c00}
.v-tight b{color:#a60}.v-ready b{color:#126b12}</style></head>
<body><iframe src="MESHCAT" id="m"></iframe><div id="p">loading...</div><script>
function fmt(v){if(v===null||v===undefined)return '-';
if(Array.isArray(v))return v.map(fmt).join(', ');
if(typeof v==='number')return (Math.abs(v)>=100?v.toFixed(0):v.toPrecision(4));
if(typeof v==='object')return Object.entries(v).map(([k,x])=>k+' '+fmt(x)).join('; ');
return String(v);}
function rows(o){return Object.entries(o).map(([k,v])=>'<tr><td>'+k+'</td><td'+
((k==='clear'||k==='confirmed'||k==='feasible')&&v===false||(k==='alarm'&&v)?' class=bad':'')+
'>'+fmt(v)+'</td></tr>').join('');}
function esc(t){return String(t).replace(/[&<>"']/g,c=>'&#'+c.charCodeAt(0)+';');}
function card(c){return '<div id="card" class="v-'+esc(c.verdict)+'"><b>'+esc(c.title)+': '+
esc(c.verdict)+'</b><br>'+esc(c.next_step)+'<table>'+Object.entries(c.lines).map(([k,v])=>
'<tr><td>'+esc(k)+'</td><td>'+esc(v)+'</td></tr>').join('')+'</table></div>';}
async function tick(){try{const s=await (await fetch('status.json')).json();
let h='<b>mode '+s.mode+'</b>, site '+s.site+', margin '+fmt(s.margin_mm)+' mm';
if(s.card)h+="<h4>surgeon's card (plan)</h4>"+card(s.card);
if(s.setup)h+='<h4>setup</h4><table>'+rows(s.setup)+'</table>';
if(s.teleop)h+='<h4>teleop</h4><table>'+rows(s.teleop)+'</table>';
h+='<h4>messages</h4>'+s.messages.join('<br>');
h+='<h4>keys (teleop)</h4><small>'+s.keys.join('<br>')+'</small>';
document.getElementById('p').innerHTML=h;
window.studioStatus=s;}catch(e){}setTimeout(tick,250);}tick();</script></body></html>"""


class StatusServer:
    """The status page on ``host`` (an ephemeral port unless ``port``): ``/`` the page (Meshcat
    embedded), ``/status.json`` the studio's :meth:`Studio.status`."""

    def __init__(self, studio: Studio, meshcat_url: str, *, host: str = "127.0.0.1",
                 port: int = 0):
        self.studio = studio
        self.lock = threading.Lock()
        page = PAGE.replace("MESHCAT", meshcat_url).encode()
        server = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 - http.server's name
                if self.path.startswith("/status.json"):
                    with server.lock:
                        body = json.dumps(server.studio.status()).encode()
                    kind = "application/json"
                elif self.path == "/favicon.ico":
                    self.send_response(204)
                    self.end_headers()
                    return
                elif self.path in ("/", "/index.html"):
                    body, kind = page, "text/html; charset=utf-8"
                else:
                    self.send_error(404)
                    return
                self.send_response(200)
                self.send_header("Content-Type", kind)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args):  # quiet
                pass

        self.httpd = ThreadingHTTPServer((host, port), Handler)
        self.url = f"http://{host}:{self.httpd.server_address[1]}/"
        # shutdown() waits for the serving loop's next poll: 50 ms, not the default 0.5 s
        self._thread = threading.Thread(target=self.httpd.serve_forever, args=(0.05,),
                                        daemon=True)
        self._thread.start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


# -- the command -----------------------------------------------------------------------------------


def register(subparsers) -> None:
    p = subparsers.add_parser("studio", help="the planning studio: live setup planning and "
                              "teleoperation in the browser (Meshcat)",
                              description=__doc__.split("\n\n")[0],
                              epilog="teleop keys and sliders:\n  " + "\n  ".join(help_keys()),
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("case", type=Path, nargs="?", help="case YAML to plan first")
    p.add_argument("--plan", type=Path, help="a plan folder (implantplan plan/demo) to open")
    p.add_argument("--out", type=Path, help="where a case is planned (default out/studio-NAME)")
    p.add_argument("--port", type=int, default=None,
                   help="Meshcat's port (default: a free one); the status page takes the next")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1)")
    p.add_argument("--master", choices=MASTERS, default="keyboard",
                   help="teleop master to start with (key M switches; default keyboard)")
    p.add_argument("--quiet", action="store_true", help="no planning progress lines")
    p.set_defaults(func=_cmd_studio)


def open_studio(plan_dir, *, host: str = "127.0.0.1", port: int | None = None,
                realtime_rate: float = 1.0, scan: bool = True, master: str = "keyboard"):
    """(studio, meshcat, status server) on a plan folder, serving on ``host``."""
    from pydrake.geometry import Meshcat, MeshcatParams

    sp = ls.load_plan(plan_dir)
    mesh = ls.opened_scan(sp) if scan else None
    params = MeshcatParams()
    params.host = host
    if port is not None:
        params.port = port
    meshcat = Meshcat(params)
    studio = Studio(sp, meshcat, scan=mesh, realtime_rate=realtime_rate, master=master)
    status = StatusServer(studio, meshcat.web_url(), host=host,
                          port=0 if port is None else port + 1)
    return studio, meshcat, status


def _cmd_studio(args) -> int:
    if (args.case is None) == (args.plan is None):
        raise InputError("studio", "expected a case YAML or --plan DIR (one of them)")
    if args.port is not None and not 0 < args.port < 65535:
        raise InputError("--port", f"expected a port 1..65534, got {args.port}")
    folder = args.plan
    if args.case is not None:
        from implantplan.analyses.case import load_case

        if args.out is not None:  # before any work, as plan does (stale staging folders go)
            out_folder.check_out(args.out, force=None)
        from implantplan.analyses.plan import plan_case

        case = load_case(args.case)
        folder = args.out or Path("out") / f"studio-{case.name}"
        plan_case(case, folder, quiet=args.quiet, html_scene=False)
        print(f"plan: {folder / 'plan.json'}")
    elif not (folder / "plan.json").is_file():
        raise InputError("--plan", f"expected a plan folder with plan.json, got {str(folder)!r}")
    studio, meshcat, status = open_studio(folder, host=args.host, port=args.port,
                                          master=args.master)
    print(f"studio: {status.url}  (3D view alone: {meshcat.web_url()})", flush=True)
    print("keys: " + ", ".join(f"{lab}" for lab, _ in KEYS.values())
          + "; T teleop on/off, V save recording, M keyboard/sliders, G FPSM slices; "
          "Quit button or Ctrl-C to stop", flush=True)
    stopped = None
    try:
        studio.run(lock=status.lock)
    except KeyboardInterrupt as exc:  # Ctrl-C is the studio's way to quit (exit 0)
        stopped = exc
    finally:
        status.close()
    print("studio: closed", flush=True)
    if stopped is not None and type(stopped) is not KeyboardInterrupt:
        raise stopped  # SIGTERM (the CLI's Terminated): exit 143 as every command
    return 0
