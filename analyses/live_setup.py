"""The studio's live setup evaluation (DESIGN.md section 10): a plan folder's context, and what a
base position gives, fast enough to follow a slider.

A plan folder (``implantplan plan``/``demo``) holds everything the room needs: the scenario by
name, each site's feeding target in World, fixture and tool, the Pareto front of the base search.
:func:`load_plan` reads it once into a :class:`StudioPlan` (scenario, targets in Oral, the fast
collision model, the random feasible bases the percentiles rank against, recomputed with the
pipeline's own seed and function); then, per base position:

- :func:`evaluate_layout` (fast, one call per slider change): every site's surviving IK branch and
  its three MOPRP indices (systems.robot.moprp.evaluate_bases, the worst over the sites as in the
  plan),
  their percentiles, the fast model's arm clearance (a lower bound of SceneGraph's) at the pre-feed
  and target configurations, the cart's clearance; the tool's clearances in the mouth do not
  depend on the base and come from the plan (certified on the FPSM, exact with FCL).
- :func:`confirm_layout` (slow, ~0.1-0.3 s): SceneGraph's signed distance along every site's
  whole feed at that base (diagrams.arm_clearance.confirm_feed), the verdict the plan keeps.
- :class:`CapabilityView`: the capability map (seed 004) around every target from that base (the
  plan's verdict and index: certified and centre-sampled maps); the map lives in the base frame,
  so voxels built once are reused when the base comes back near.

Everything is in SI units; the studio shows mm and deg.
"""

from __future__ import annotations

import dataclasses
import functools
import pickle
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.math import RotationMatrix
from pydrake.systems.analysis import Simulator

from implantplan.analyses import pipeline
from implantplan.analyses.case import CapabilitySection
from implantplan.diagrams.arm_clearance import SceneGraphClearance, confirm_feed
from implantplan.diagrams.teleop import X_ET, FeedRun, TeleopCase, build_teleop, simulate
from implantplan.systems import actuator, seeds
from implantplan.systems.capability import maps as cm
from implantplan.systems.errors import InputError
from implantplan.systems.files import read_json
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.frames import frame_from_z, invert, rotation_angle
from implantplan.systems.instrument import Instrument
from implantplan.systems.placement.fixture import VirtualFixture
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.robot import moprp
from implantplan.systems.safety import SafetySpec
from implantplan.systems.teleop.master_device import IncrementalMapping, MasterMotion
from implantplan.systems.teleop.master_input import LiveMasterDevice, MasterInput


@dataclass
class StudioPlan:
    """A plan folder opened for the studio (SI units, frames as in plan.json)."""

    folder: Path
    plan: dict  # plan.json as read
    sc: moprp.Scenario
    fpsm: Fpsm
    names: list[str]
    X_OT: np.ndarray  # (S, 4, 4) feeding targets in Oral
    X_WCenter: np.ndarray
    model: object  # the fast collision model (systems.robot.arm_collision)
    F_reference: np.ndarray  # (n, 3) random feasible bases' indices (percentile reference)
    pareto_xyz: np.ndarray  # (P, 3)
    pareto_F: np.ndarray  # (P, 3)
    seed: int
    _scans: dict = field(default_factory=dict, repr=False)  # instrument -> ScanClearance

    @functools.cached_property
    def exact(self):
        """The plan's opened scan as FCL's exact reference in Center (read once from the case
        file the plan names; None when it is gone)."""
        from implantplan.analyses.case import load_case
        from implantplan.systems.placement.exact_clearance import ExactCavity

        source = Path(self.plan["case"]["source"])
        if not source.is_file():
            return None
        case = load_case(source)
        return ExactCavity.from_scan(pipeline.fit_stage(case).opened, self.fpsm,
                                     close_open_cuts=case.mesh.close_open_cuts)

    def scan_clearance(self, instrument: Instrument):
        """The scan bound of ``instrument`` against the plan's scan, built once per instrument
        (one distance grid for all), or None without the scan (then the FPSM's bound guards)."""
        from implantplan.systems.placement.scan_clearance import ScanClearance

        if self.exact is None:
            return None
        if instrument not in self._scans:
            grid = next(iter(self._scans.values())).grid if self._scans else None
            self._scans[instrument] = ScanClearance(self.exact, instrument, grid=grid)
        return self._scans[instrument]

    @property
    def base_xyz(self) -> np.ndarray:
        """The plan's selected base position in Oral (m)."""
        return np.asarray(self.plan["base"]["xyz_in_oral"], dtype=float)

    def site_index(self, name: str) -> int:
        if name not in self.names:
            raise InputError("site", f"expected one of {self.names}, got {name!r}")
        return self.names.index(name)

    def tool_clearances(self) -> list[dict]:
        """Per site the tool's clearance in the mouth from the plan (m): certified on the FPSM
        and exact against the scan over the feed and the fixture's region (base independent)."""
        out = []
        for s in self.plan["sites"]:
            ver = s["placement"].get("verification") or {}
            out.append({"certified": ver.get("clearance_certified"),
                        "exact": ver.get("clearance_exact_min"),
                        "margin": ver.get("clearance_margin")})
        return out

    def teleop_case(self, site: int, xyz=None, branch: int | None = None,
                    q_pre=None, *, scan: bool = True) -> TeleopCase:
        """Site ``site``'s feeding case in the room with the base at ``xyz`` (default: the
        plan's), starting at ``q_pre`` (default: the plan's pre-feed configuration); with
        ``scan`` (and the plan's scan there) the supervisor and the estimator bound the
        instrument against the scan, as the plan's simulation does."""
        s = self.plan["sites"][site]
        instrument = _planned_instrument(s)
        xyz = self.base_xyz if xyz is None else np.asarray(xyz, dtype=float)
        q0 = np.asarray(s["ik"]["q_pre"] if q_pre is None else q_pre, dtype=float)
        return TeleopCase(
            scenario=self.plan["frames"]["posture"],
            X_WBase=self.sc.X_WO @ moprp.base_pose(xyz),
            q_start=q0,
            X_WCenter=self.X_WCenter,
            fpsm=self.fpsm,
            vf=VirtualFixture.from_dict(s["vf"]),
            X_WTarget=self.sc.X_WO @ self.X_OT[site],
            rod_radius=float(s["rod_radius"]),
            implant_length=float(s["implant_length"]),
            limits=self.sc.limits,
            label=f"site {s['name']}",
            instrument=instrument,
            safety=self.safety,
            scan=self.scan_clearance(instrument or Instrument.paper(
                rod_radius=float(s["rod_radius"]), implant_length=float(s["implant_length"])))
            if scan else None,
        )

    @property
    def safety(self) -> SafetySpec:
        """The plan's safety spec (plan.json ``safety``; a plan written before it recorded the
        spec: the defaults)."""
        return SafetySpec.from_dict(self.plan["safety"]) if "safety" in self.plan else SafetySpec()


def _planned_instrument(site: dict):
    """The instrument the plan verified at a site (None for a plan that did not record it:
    the paper's tool of the site's rod radius and d12)."""
    tool = (site.get("placement", {}).get("verification") or {}).get("tool")
    return None if tool is None or "shapes" not in tool else Instrument.from_dict(tool)


def opened_scan(sp: StudioPlan):
    """The plan's case's opened scan (the case file it names), or None when it is gone."""
    from implantplan.analyses.case import load_case

    source = Path(sp.plan["case"]["source"])
    if not source.is_file():
        return None
    return pipeline.fit_stage(load_case(source)).opened


_REFERENCES: dict = {}  # (scenario, feeding targets) -> percentile reference, per process


def _percentile_reference(sc: moprp.Scenario, X_OT: np.ndarray, model) -> np.ndarray:
    """The plan's percentile reference (:func:`analyses.pipeline.percentile_reference`, seeded by
    the scenario), sampled once per process for a scenario and feeding targets: a plan opened
    again (the studio reopened, a replay) reads the same array instead of sampling 1 s again."""
    key = (pickle.dumps(sc), X_OT.tobytes())  # exact: every field and digit
    if key not in _REFERENCES:
        def evaluate(X, rng):
            return pipeline.combine_sites([moprp.evaluate_bases(X, sc, rng, model=model, X_OT=T)
                                           for T in X_OT])

        _REFERENCES[key] = pipeline.percentile_reference(sc, evaluate)
        _REFERENCES[key].setflags(write=False)
    return _REFERENCES[key]


def load_plan(folder, *, field: str = "--plan", reference: bool = True) -> StudioPlan:
    """Open a plan folder (its plan.json and fpsm.json) for the studio; without ``reference``
    no percentile reference is sampled (replays need none; percentiles are then NaN)."""
    folder = Path(folder)
    path = folder / "plan.json" if folder.is_dir() else folder
    plan = read_json(path, kind="plan", field=field)
    try:
        sc = moprp.load_scenario(plan["frames"]["scenario"], X_FT=actuator.X_FT())
    except InputError as exc:
        raise InputError(field, f"{path}: its scenario {plan['frames']['scenario']!r} cannot "
                         f"be loaded by name ({exc})") from None
    seed = int(plan["case"]["seed"])
    sc = dataclasses.replace(sc, seed=seeds.seed(seed, seeds.ROBOT))  # as the plan's robot stage
    fpsm = Fpsm.load(path.parent / plan["fpsm"]["file"], field=f"{field} fpsm")
    X_WO_inv = invert(sc.X_WO)
    X_OT = np.array([X_WO_inv @ np.asarray(s["feeding_target"]["X_WT"], dtype=float)
                     for s in plan["sites"]])
    model = moprp.collision_model(sc)

    F_ref = _percentile_reference(sc, X_OT, model) if reference else np.zeros((0, 3))
    pareto = plan["base"]["pareto"]
    return StudioPlan(
        folder=path.parent, plan=plan, sc=sc, fpsm=fpsm,
        names=[s["name"] for s in plan["sites"]], X_OT=X_OT,
        X_WCenter=np.asarray(plan["frames"]["X_WCenter"], dtype=float), model=model,
        F_reference=F_ref,
        pareto_xyz=np.array([p["base_xyz"] for p in pareto], dtype=float).reshape(-1, 3),
        pareto_F=np.array([[p["indices"][n] for n in moprp.INDEX_NAMES] for p in pareto],
                          dtype=float).reshape(-1, 3),
        seed=seed,
    )


@dataclass
class Layout:
    """What one base position gives (SI units; see :func:`evaluate_layout`)."""

    xyz: np.ndarray  # (3,) base in Oral
    feasible: bool  # every site has a surviving branch
    branch: np.ndarray  # (S,) -1 where none
    q: np.ndarray  # (S, 6) at the target (NaN where none)
    q_pre: np.ndarray  # (S, 6)
    site_indices: np.ndarray  # (S, 3) (inf where none)
    indices: np.ndarray  # (3,) worst over the sites
    percentiles: np.ndarray  # (3,)
    arm_clearance: np.ndarray  # (S,) fast model, min over pre-feed and target, all groups
    cart_clearance: float
    reasons: list[str]  # per site, why no branch survived ("ok" when one did)
    clear: bool  # fast verdict: every site's arm clearance >= the scenario's clearance
    confirmation: list[dict] | None = None  # SceneGraph along each feed (confirm_layout)
    capability: dict | None = None  # CapabilityView.at

    @property
    def confirmed(self) -> bool | None:
        """SceneGraph's verdict (None until confirmed)."""
        if self.confirmation is None:
            return None
        return all(c["ok"] for c in self.confirmation)


def evaluate_layout(sp: StudioPlan, xyz) -> Layout:
    """The fast evaluation of a base position (see the module docstring)."""
    xyz = np.asarray(xyz, dtype=float).reshape(3)
    if not np.all(np.isfinite(xyz)):
        raise InputError("base_xyz", f"expected finite coordinates (m), got {xyz}")
    sc = sp.sc
    rng = moprp.evaluation_rng(sc)
    evs = [moprp.evaluate_bases(xyz[None], sc, rng, model=sp.model, X_OT=T) for T in sp.X_OT]
    F, _ = pipeline.combine_sites(evs)
    branch = np.array([int(e.branch[0]) for e in evs])
    feasible = bool(np.all(branch >= 0))
    q = np.array([e.q[0] for e in evs])
    q_pre = np.array([e.q_pre[0] for e in evs])
    site_idx = np.array([e.objectives[0] for e in evs])
    indices = F[0] if feasible else np.full(3, np.inf)
    pct = moprp.percentiles(indices, sp.F_reference) if feasible else np.full(3, np.nan)
    arm = np.full(len(evs), -np.inf)
    ok = branch >= 0
    if np.any(ok):
        qs = np.concatenate([q_pre[ok], q[ok]])
        d = moprp.collision_clearance(qs, xyz, sc, sp.model)
        dmin = np.minimum(np.minimum(d["self"], d["environment"]), d["cabinet"])
        arm[ok] = np.minimum(dmin[: ok.sum()], dmin[ok.sum():])
    reasons = []
    for e in evs:
        codes = e.reason[0]
        if e.branch[0] >= 0:
            reasons.append("ok")
        else:
            common = codes[codes > 0]
            code = int(np.bincount(common).argmax()) if common.size else moprp.DROP_IK
            reasons.append(moprp.DROP_REASONS[code])
    return Layout(
        xyz=xyz, feasible=feasible, branch=branch, q=q, q_pre=q_pre, site_indices=site_idx,
        indices=indices, percentiles=pct, arm_clearance=arm,
        cart_clearance=float(moprp.cart_clearance(xyz[None], sc)[0]), reasons=reasons,
        clear=bool(feasible and np.all(moprp.is_clear(arm, sc.clearance))),
    )


def confirm_layout(sp: StudioPlan, layout: Layout) -> list[dict]:
    """SceneGraph along every site's whole feed at the layout's base (sets and returns
    ``layout.confirmation``; a site without a branch is reported not ok)."""
    checker = SceneGraphClearance(sp.sc, layout.xyz)
    out = []
    for k, T in enumerate(sp.X_OT):
        if layout.branch[k] < 0:
            out.append({"distance": float("-inf"), "pair": ["", ""], "samples": 0, "ok": False,
                        "limit": sp.sc.clearance, "distance_pre": float("nan"),
                        "distance_target": float("nan"), "headroom": np.full(6, -np.inf),
                        "headroom_limit": float(sp.sc.joint_headroom)})
        else:
            out.append(confirm_feed(checker, sp.sc, int(layout.branch[k]), X_OT=T))
    layout.confirmation = out
    return out


@dataclass
class CapabilityView:
    """The capability map around the feeding targets, grown as the base moves.

    The map is of the arm + actuator in its base frame (seed 004), so the voxels a base position
    needs are the 3x3x3 neighbourhoods of the targets expressed in that base; voxels already built
    for an earlier position are kept. As in the plan's capability stage (analyses.pipeline): the
    answer at a target is the certified cell's, or closed-form IK at the target where the cell
    is undecided (:meth:`CapabilityMap.answer`, it says which); the capability index and the
    voxel colours are the paper's centre-sampled index of the same map. Resolution and
    directions are the plan's case's defaults (``voxel``, ``directions``)."""

    sp: StudioPlan
    voxel: float = CapabilitySection().voxel  # m, the case's default
    directions: int = CapabilitySection().directions
    _built: dict = field(default_factory=dict)  # voxel id -> (reach, all-roll, yes rows)
    _tried: set = field(default_factory=set)  # voxel ids built (stored or unreachable)

    def __post_init__(self):
        X_FA = actuator.actuator_map_frame()
        self._X_FA = X_FA
        self.params = cm.make_params(self.voxel, self.directions, limits=self.sp.sc.limits,
                                     X_FT=X_FA, tool="actuator")
        self.grid = cm.make_grid(self.params)

    def _map(self, ids: np.ndarray) -> cm.CapabilityMap:
        """The map holding at least the voxels ``ids`` (building those not tried)."""
        todo = np.array([i for i in ids if int(i) not in self._tried], dtype=np.int64)
        if todo.size:
            block = cm.build_block(self.params, todo)
            for v, *rows in zip(*block, strict=True):
                self._built[int(v)] = rows
            self._tried.update(int(i) for i in todo)
        if not self._built:
            return cm.empty_map(self.params)
        keys = np.array(sorted(self._built), dtype=np.int64)
        rows = [np.array([self._built[int(k)][i] for k in keys], dtype=np.uint8)
                for i in range(3)]
        return cm.CapabilityMap(self.params, self.grid, keys, *rows)

    def at(self, layout: Layout) -> dict:
        """Capability at each target from the layout's base, and the voxels around them.

        Returns:
            dict(index (S,) of the target's voxel, neighbourhood_index (S,), map_reachable (S,)
            (the exact answer), map_source (S,) (what it rests on, maps.SOURCES), centres_W
            (V, 3) voxel centres in World, voxel_index (V,), voxel (m), ik_branches (S,));
            also set as ``layout.capability``.
        """
        X_BE = moprp.target_pose(layout.xyz, self.sp.X_OT)
        X_BA = X_BE @ invert(actuator.X_FT()) @ self._X_FA
        near = self.grid.neighbourhood(X_BA[:, :3, 3])
        ids = np.unique(near[near >= 0])
        cmap = self._map(ids)
        map_reach, source, index = cmap.answer(X_BA)
        neigh = cmap.neighbourhood_index(X_BA[:, :3, 3])
        centres_B = self.grid.centres(ids)
        X_WB = self.sp.sc.X_WO @ moprp.base_pose(layout.xyz)
        out = {
            "index": index, "neighbourhood_index": neigh, "map_reachable": map_reach,
            "map_source": source, "params": self.params,
            "centres_W": centres_B @ X_WB[:3, :3].T + X_WB[:3, 3],
            "voxel_index": cmap.voxel_index(centres_B),
            "voxel": self.voxel,
            "ik_branches": kin.ik(X_BE, limits=self.sp.sc.limits,
                                  X_FT=actuator.X_FT()).valid.sum(axis=-1),
        }
        layout.capability = out
        return out


# -- teleoperation by a person -------------------------------------------------------------------


def feed_mapping(case: TeleopCase) -> IncrementalMapping:
    """The master frame for a live feed: M's +x along the feed (from the start pose's tool
    position to the target), y and z across it, so "feed in" pushes the tool along the fixture
    and "roll" turns it about the feed axis."""
    u = case.X_WTarget[:3, 3] - case.X_WE(case.q_start)[:3, 3]
    n = float(np.linalg.norm(u))
    if n < 1e-9:
        raise InputError("q_start", "the start pose is already at the feeding target")
    return IncrementalMapping(R_WM=frame_from_z(np.zeros(3), u / n)[:3, [2, 0, 1]])


class LiveTeleop:
    """The teleop diagram (diagrams.teleop.build_teleop: fixture, supervisor, estimator, diff
    IK, arm) driven by a live master input, stepped by the caller (the studio's loop) at real
    time.

    Args:
        case: the feeding case (:meth:`StudioPlan.teleop_case`).
        source: the live master input (systems.teleop.master_input.MasterInput).
        meshcat: draw the plant there (None: headless).
        realtime_rate: the Simulator's target real-time rate (1.0 in the studio; 0 runs as fast
            as it can, for tests).
        options: more keyword arguments of diagrams.teleop.build_teleop (e.g. ``vf_enabled``).
    """

    def __init__(self, case: TeleopCase, source: MasterInput, *, meshcat=None,
                 realtime_rate: float = 1.0, **options):
        self.case = case
        self.mapping = feed_mapping(case)
        self.device = LiveMasterDevice(source, self.mapping)
        self.teleop = build_teleop(case, meshcat=meshcat, master=self.device, **options)
        self.simulator = Simulator(self.teleop.diagram)
        self.simulator.set_target_realtime_rate(realtime_rate)
        self.context = self.simulator.get_mutable_context()
        diffik_context = self.teleop.diffik.GetMyMutableContextFromRoot(self.context)
        self.teleop.diffik.GetInputPort("use_robot_state").FixValue(diffik_context, False)
        self.teleop.initialize(self.context)
        self.simulator.Initialize()
        self.start_W = case.X_WE(case.q_start)[:3, 3]
        self.start_R = case.X_WE(case.q_start)[:3, :3]

    @property
    def time(self) -> float:
        return float(self.context.get_time())

    def advance(self, seconds: float) -> None:
        """Run ``seconds`` more of simulated time (whole control periods)."""
        dt = self.device.dt
        n = max(int(round(seconds / dt)), 1)
        self.simulator.AdvanceTo((round(self.time / dt) + n) * dt)

    def state(self) -> dict:
        """Tool position, feed progress (m along the feed, target = its length), the fixture's
        force (N, World), the supervisor's barrier [h, scale, active], the estimator's alarm; the
        tool's turn since the start (rotation vector in World, rad), its roll about the feed axis
        and its tilt off it (rad), and its angle to the fixture's planned orientation (rad)."""
        t = self.teleop
        X_WE = t.tool_pose.GetOutputPort("X_WE").Eval(
            t.tool_pose.GetMyContextFromRoot(self.context)).GetAsMatrix4()
        p = X_WE[:3, 3]
        target = self.case.X_WTarget[:3, 3]
        u = (target - self.start_W) / np.linalg.norm(target - self.start_W)
        force = t.vf.GetOutputPort("F_W_fixture").Eval(t.vf.GetMyContextFromRoot(self.context))
        barrier = t.supervisor.GetOutputPort("barrier").Eval(
            t.supervisor.GetMyContextFromRoot(self.context))
        alarm = t.estimator.GetOutputPort("alarm").Eval(
            t.estimator.GetMyContextFromRoot(self.context))
        turn = RotationMatrix.ProjectToRotationMatrix(X_WE[:3, :3] @ self.start_R.T)
        aa = turn.ToAngleAxis()
        r_W = aa.angle() * aa.axis()
        R_CT = invert(self.case.X_WCenter)[:3, :3] @ X_WE[:3, :3] @ X_ET[:3, :3]
        R_ref = self.case.vf.R_ref
        to_plan = rotation_angle(R_CT @ R_ref.T) if R_ref is not None else float("nan")
        return {"t": self.time, "p_WE": p, "X_WE": X_WE,
                "turn_W": r_W, "roll": float(r_W @ u),
                "tilt": float(np.linalg.norm(r_W - (r_W @ u) * u)),
                "angle_to_plan": float(to_plan),
                "feed": float((p - self.start_W) @ u),
                "feed_length": float(np.linalg.norm(target - self.start_W)),
                "to_target": float(np.linalg.norm(target - p)),
                "F_W_fixture": np.array(force), "barrier": np.array(barrier),
                "alarm": bool(alarm[0] > 0.5)}

    def save(self, csv_path) -> Path:
        """Write the run's recording (MasterDevice CSV, atomically) and return its path."""
        from implantplan.systems.teleop.master_device import save_csv

        motion = self.device.recording(self.time)
        return save_csv(csv_path, motion)


def replay(case: TeleopCase, motion: MasterMotion) -> FeedRun:
    """A recorded live run on the same diagram with MasterDevice (no finishing by eye), for its
    duration: the run again."""
    teleop = build_teleop(case, motion, mapping=feed_mapping(case), finish=False)
    return simulate(teleop, motion.duration)


def recorded_case(csv_path) -> tuple[TeleopCase, MasterMotion, dict]:
    """A studio recording's case (from ``<csv>.json``: the plan folder, site, base, start) and
    motion, for a replay."""
    from implantplan.systems.teleop.master_device import load_csv

    csv_path = Path(csv_path)
    side = csv_path.with_suffix(".json")
    if not side.is_file():
        raise InputError("--csv", f"expected the recording's case beside it: {str(side)!r} "
                         "(the studio writes both)")
    info = read_json(side, kind="teleop_recording", field="--csv")
    sp = load_plan(side.parent / info["plan"], field="--csv plan", reference=False)
    case = sp.teleop_case(sp.site_index(str(info["site"])), info["base_xyz"],
                          q_pre=info["q_start"])
    return case, load_csv(csv_path, field="--csv"), info
