"""The case pipeline's stages as plain functions (DESIGN.md section 1), shared by ``plan``,
``demo`` and the figure scripts.

    case -> mesh (opened) -> FPSM fit -> placement + VF per site -> robot base (all sites)
         -> capability check of every feeding target -> teleop feeding per site

Each stage takes what the previous one made and returns plain results; the ``plan`` command
(analyses.plan) writes them out and builds the report. Stages call cores only (systems, diagrams,
analyses.case), never a command module (tests/test_layers.py).
"""

from __future__ import annotations

import dataclasses
import re
import time
from dataclasses import dataclass, field

import numpy as np
import trimesh

from implantplan.analyses.case import Case
from implantplan.diagrams.arm_clearance import SceneGraphClearance, confirm_feed
from implantplan.diagrams.feeding import run_feeding
from implantplan.diagrams.teleop import TeleopCase
from implantplan.systems import actuator, seeds
from implantplan.systems.anatomy import distances as anatomy
from implantplan.systems.anatomy.cbct import CbctScan, is_volume_path, load_cbct_scan
from implantplan.systems.capability import maps as cm
from implantplan.systems.errors import InputError, PlanningFailure, fields_renamed
from implantplan.systems.fpsm.fit import fit_fpsm
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.fpsm.oral_mesh import (
    center_frame,
    load_oral_mesh,
    open_mouth,
    opening_map,
    rotate_about_axis,
)
from implantplan.systems.fpsm.sites import SiteCheck, check_sites, site_problems
from implantplan.systems.frames import apply, invert, transform
from implantplan.systems.placement.planner import Placement, place_instrument
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.robot import moprp


@dataclass
class FitResult:
    scanned: trimesh.Trimesh  # m, mesh frame
    opened: trimesh.Trimesh  # after the jaw-opening model (the scanned mesh when 0 deg)
    fpsm: Fpsm  # its X_WC is the Center frame in the mesh frame
    seconds: float
    cbct: CbctScan | None = None  # the CBCT the scan was extracted from (mesh.path a volume)
    _exact: dict = field(default_factory=dict, repr=False)

    def exact(self, close_open_cuts: bool):
        """The opened scan as FCL's exact reference in Center, cut at the mouth opening
        (:meth:`ExactCavity.from_scan`), built once per fit."""
        from implantplan.systems.placement.exact_clearance import ExactCavity

        key = bool(close_open_cuts)
        if key not in self._exact:
            self._exact[key] = ExactCavity.from_scan(self.opened, self.fpsm,
                                                     close_open_cuts=key)
        return self._exact[key]


# The FPSM core's field names and the `fpsm fit` command's flags in its messages -> the case's
# keys: a case file's user is told what to change in the case.
CASE_FIELDS = {
    "mesh": "mesh.path", "center_origin": "center.origin_mm", "z_range": "fpsm.z_range_mm",
    "margin": "fpsm.margin_mm", "cap_radius": "mesh.cap_radius_mm", "samples": "fpsm.samples",
    "slices": "fpsm.slices", "control_points": "fpsm.control_points",
}
CASE_TEXTS = {"Pass --cap-radius-mm": "Set mesh.cap_radius_mm",
              "--close-open-cuts": "mesh.close_open_cuts: true",
              "--z-range-mm": "fpsm.z_range_mm"}


MAX_OPEN_EDGE_SHARE = 0.03  # a scan's open boundary edges, share of its edges, closed unasked


def check_repairs(mesh: trimesh.Trimesh, *, accept: bool = False) -> dict:
    """The share of the scan's edges on open boundary loops (what ``close_open_cuts`` closes).
    The bundled scan, cut open along its floor, has one loop of 330 edges (0.9 % of its 37,062);
    a scan with 2 % of its triangles missing has 454 loops (about 5 %). Over
    :data:`MAX_OPEN_EDGE_SHARE` it is an InputError naming ``mesh.close_open_cuts`` unless
    ``accept`` (--accept-repairs): so much missing surface is a bad scan, not a cut."""
    from implantplan.systems.fpsm.oral_mesh import boundary_loops

    loops = boundary_loops(mesh)
    open_edges = int(sum(len(loop) for loop in loops))
    share = open_edges / max(len(mesh.edges_unique), 1)
    if share > MAX_OPEN_EDGE_SHARE and not accept:
        raise InputError("mesh.close_open_cuts", f"the scan has {len(loops)} open boundary "
                         f"loops ({open_edges} edges, {share:.1%} of its edges; expected at most "
                         f"{MAX_OPEN_EDGE_SHARE:.0%}): parts of the scan are missing; rescan, "
                         "or --accept-repairs to plan with the holes closed")
    return {"loops": len(loops), "open_edges": open_edges, "share": share}


def fit_stage(case: Case, *, progress=None, accept_repairs: bool = False,
              notes: list | None = None) -> FitResult:
    """Load the scan, open the mouth if the case asks, fit the FPSM (stage 1). With
    ``mesh.close_open_cuts`` the scan's open boundary is checked first (:func:`check_repairs`);
    an accepted excess is appended to ``notes``."""
    t0 = time.perf_counter()
    mesh, center, fp = case.mesh, case.center, case.fpsm
    cbct = None
    if is_volume_path(mesh.path):
        cbct = load_cbct_scan(mesh.path, air_threshold_hu=mesh.air_threshold_hu,
                              bone_threshold_hu=mesh.bone_threshold_hu, field="mesh.path")
        scanned = cbct.mesh
        if progress is not None:
            progress.say(f"CBCT {cbct.info['shape_kji']} voxels of "
                         f"{np.round(cbct.info['spacing_mm'], 3).tolist()} mm: air surface "
                         f"{cbct.info['air']['faces']} triangles at {mesh.air_threshold_hu:g} HU")
    else:
        scanned = load_oral_mesh(mesh.path, units=mesh.units, field="mesh.path")
    opened = scanned
    if mesh.mouth_opening_deg > 0:
        opened = open_mouth(scanned, mesh.mouth_opening_deg, **mesh.opening)
        if progress is not None:
            info = opened.metadata.get("implantplan", {}).get("open_mouth", {})
            progress.say(f"mouth opened by {mesh.mouth_opening_deg:g} deg "
                         f"({info.get('moved_vertices', '?')} vertices moved)")
    lo, hi = opened.bounds
    if np.any(center.origin < lo) or np.any(center.origin > hi):
        raise InputError(
            "center.origin_mm",
            f"{np.round(center.origin * 1e3, 1).tolist()} mm lies outside the mesh's "
            f"bounding box {np.round(lo * 1e3, 1).tolist()} .. {np.round(hi * 1e3, 1).tolist()} "
            f"mm (mesh read in {mesh.units}); check mesh.units and the Center origin",
        )
    if mesh.close_open_cuts:
        repairs = check_repairs(opened, accept=accept_repairs)
        if repairs["share"] > MAX_OPEN_EDGE_SHARE and notes is not None:
            notes.append({"flag": "--accept-repairs",
                          "what": f"{repairs['loops']} open boundary loops closed "
                                  f"({repairs['share']:.1%} of the scan's edges)"})
    X_WC = center_frame(center.origin, center.z_axis, x_hint=center.x_hint)
    with fields_renamed(CASE_FIELDS, CASE_TEXTS):
        fpsm = fit_fpsm(
            opened,
            X_WC,
            slices=fp.slices,
            control_points=fp.control_points,
            samples=fp.samples,
            z_range=fp.z_range,
            method=fp.method,
            margin=fp.margin,
            cap_radius=mesh.cap_radius,
            close_open_cuts=mesh.close_open_cuts,
            progress=progress,
        )
    fpsm.settings["mesh_units"] = mesh.units
    return FitResult(scanned, opened, fpsm, time.perf_counter() - t0, cbct)


def site_stage(case: Case, fit: FitResult) -> SiteCheck:
    """Every site on the scanned tissue with its axis into the cavity (systems.fpsm.sites); the
    first
    site that is not is an input error naming it (exit 2), with the likely slip when one fits."""
    positions = np.array([s.position for s in case.sites])
    axes = np.array([s.axis for s in case.sites])
    check = check_sites(fit.opened, fit.fpsm.X_WC, positions, axes,
                        tolerance=case.site_check.tolerance)
    for k, problem in enumerate(site_problems(check, fit.opened, fit.fpsm.X_WC, positions)):
        if problem is not None:
            raise InputError(f"sites[{k}] ({case.sites[k].name})", problem)
    return check


def placement_stage(case: Case, fit: FitResult, *, progress=None,
                    require_valid: bool = True) -> list[Placement]:
    """Stage 2 for every site; with ``require_valid`` a site without a collision-free placement
    is a planning failure that names the site and the reason.

    Every placement is verified over the fixture's admissible region against the clinical
    margin (``case.safety``, passed whole): certified on the FPSM and exactly with FCL against
    the fit's opened scan (one exact cavity per fit, :meth:`FitResult.exact`, shared with the
    feeding stage); then the registration Monte Carlo of the exact clearance along the feed
    (``placement.verification["registration"]``). The fit is passed whole so that no caller
    plans without the scan's verification."""
    from implantplan.systems.placement.scan_clearance import registration_monte_carlo

    fpsm = fit.fpsm
    exact = fit.exact(case.mesh.close_open_cuts)
    safety = case.safety
    out = []
    for k, site in enumerate(case.sites):
        tool = case.instrument_at(site)
        try:
            p = _place_site(case, fpsm, exact, site, k, progress=progress)
        except InputError as exc:  # name the case's field, not the placement's argument
            message = str(exc)
            if exc.field == "hole" and "outside the model" in exc.message:
                # the site passed the scan check (site_stage): what is wrong is the surrogate
                core = re.sub(r"\(tolerance ([\d.]+) mm\)", r"(the placement allows \1 mm)",
                              exc.message.replace("the model", "the FPSM").replace(
                                  "; expected a site on the cavity wall", ""))
                message = (f"{core} although it lies on "
                           f"the scanned tissue (within site_check.tolerance_mm "
                           f"{case.site_check.tolerance * 1e3:g} mm): the fitted cavity does "
                           "not reach the site (a wall between the mouth opening and the site, "
                           "a large fpsm.margin_mm, or fpsm.z_range_mm / center.origin_mm "
                           "missing it)")
            raise InputError(f"sites[{k}] (site {site.name})", message) from None
        if progress is not None:
            progress.step(k, len(case.sites), f"site {site.name}: d_T {p.d_T * 1e3:.1f} mm, "
                          f"theta_T {np.rad2deg(p.theta_T):.1f} deg, F_safe {p.F_safe:.4f}, "
                          f"{'valid' if p.valid else 'INVALID'}")
        if exact is not None and p.valid and safety.registration_samples > 0:
            p.verification["registration"] = registration_monte_carlo(
                exact, p.X_CT, tool,
                depth=p.verification["feed_depth"], safety=safety,
                seed=seeds.seed(case.seed, seeds.PLACEMENT, k, 1))
        if require_valid and not p.valid:
            result = {"site": site.name, **p.to_dict()}
            reason = p.reason
            if refused_by_geometry(p, safety):  # not the bound's slack: a larger opening?
                probe = opening_needed(case, k, progress=progress)
                result["opening_probe"] = probe
                reason += f"; {probe['text']}"
            raise PlanningFailure(f"site {site.name}: no collision-free instrument placement "
                                  f"({reason})", result=result)
        out.append(p)
    return out


def _place_site(case: Case, fpsm, exact, site, k: int, *, progress=None) -> Placement:
    """Stage 2 at one site (``k`` its index in the case: its random stream; ``progress`` gets
    the lines of a long verification)."""
    tool = case.instrument_at(site)
    return place_instrument(
        fpsm,
        site.position,
        site.axis,
        rod_radius=tool.rod_radius,
        implant_length=tool.implant_length,
        objective=case.placement.objective,
        seed=seeds.seed(case.seed, seeds.PLACEMENT, k),
        tool=tool,
        safety=case.safety,
        exact=exact,
        progress=progress,
    )


def refused_by_geometry(p: Placement, safety) -> bool:
    """True where the scan's instrument search refused the site and not for the certified
    bound's slack: the exact reference of the refusal (the planner's ``exact_best``: FCL at
    sampled poses of every candidate's feed and region) keeps less than the margin, or no
    candidate had collision-free FPSM lines for it to check (the cavity is too narrow for the
    rod's line itself)."""
    search = (p.verification or {}).get("instrument_search")
    if not search:
        return False
    best = search.get("exact_best")
    return not best or best["value"] < safety.clearance_margin


OPENING_STEP_DEG = 5.0  # a geometry refusal tries larger mouth openings in these steps
OPENING_MAX_DEG = 45.0  # up to the jaw-opening model's largest (mesh.mouth_opening_deg)


def site_at_opening(case: Case, site, angle_deg: float):
    """``site`` carried with the jaw to another mouth opening: its position taken back to the
    scan as scanned (:func:`systems.anatomy.distances.as_scanned` inverts the opening map) and
    opened by ``angle_deg`` (:func:`opening_map`); its axis, an axis in the bone, turned as a
    rigid body about the hinge by the change of the map's rotation at the site (inside the
    occlusal band, where a molar's crown may lie, the map stretches the tissue; the bone turns
    with the jaw)."""
    mesh, params = case.mesh, case.mesh.jaw
    X_WC = center_frame(case.center.origin, case.center.z_axis, x_hint=case.center.x_hint)
    R, t = X_WC[:3, :3], X_WC[:3, 3]
    p_W = R @ site.position + t
    scanned = anatomy.as_scanned(p_W[None], mesh.mouth_opening_deg, params)
    _, a_old = opening_map(scanned, mesh.mouth_opening_deg, **params)
    moved, a_new = opening_map(scanned, angle_deg, **params)
    hinge = np.asarray(mesh.hinge_axis, dtype=float)
    axis_W = rotate_about_axis((R @ site.axis)[None], np.zeros(3), hinge / np.linalg.norm(hinge),
                               a_new - a_old)[0]
    return dataclasses.replace(site, position=R.T @ (moved[0] - t), axis=R.T @ axis_W)


def opening_needed(case: Case, k: int, *, progress=None) -> dict:
    """For site ``k``, refused by its geometry at the case's mouth opening: the smallest larger
    opening (steps of :data:`OPENING_STEP_DEG` up to :data:`OPENING_MAX_DEG`) at which stage 2
    places the whole instrument (refit, the site carried with the jaw, :func:`site_at_opening`,
    the same verification). The widest opening is tried first: where even it does not place
    the site (a handle too thick for this mouth) one trial answers instead of eight. Returns
    ``opening_deg`` (None if none does), what each opening gave (``tried``, in the order
    tried) and the sentence the refusal adds (``text``)."""
    mesh = case.mesh
    if (mesh.mouth_opening_deg <= 0 or mesh.hinge_point is None
            or mesh.mouth_opening_deg >= OPENING_MAX_DEG):
        return {"opening_deg": None, "tried": [],
                "text": "the case has no jaw-opening model to try a larger opening with"
                if mesh.mouth_opening_deg < OPENING_MAX_DEG
                else f"the mouth is open by the model's largest {OPENING_MAX_DEG:g} deg"}
    site = case.sites[k]
    tried = []

    def trial(deg: float) -> dict:
        if progress is not None:
            progress.say(f"site {site.name}: refused by its geometry; trying a mouth opening "
                         f"of {deg:g} deg")
        moved = site_at_opening(case, site, deg)
        opened = dataclasses.replace(case, mesh=dataclasses.replace(mesh, mouth_opening_deg=deg),
                                     sites=(moved,))
        fit = fit_stage(opened)
        try:
            site_stage(opened, fit)
            p = _place_site(opened, fit.fpsm, fit.exact(mesh.close_open_cuts), moved, k,
                            progress=progress)
        except InputError as exc:
            tried.append({"opening_deg": deg, "valid": False, "reason": str(exc)})
        else:
            tried.append({"opening_deg": deg, "valid": p.valid,
                          "clearance_certified": p.verification.get("clearance_certified"),
                          "reason": p.reason})
        return tried[-1]

    widest = trial(OPENING_MAX_DEG)
    if not widest["valid"]:
        return {"opening_deg": None, "tried": tried,
                "text": f"not even the jaw model's widest opening ({OPENING_MAX_DEG:g} deg) "
                        "places it"}
    found = widest
    for deg in np.arange(mesh.mouth_opening_deg + OPENING_STEP_DEG, OPENING_MAX_DEG - 1e-9,
                         OPENING_STEP_DEG):
        if trial(float(deg))["valid"]:
            found = tried[-1]
            break
    deg, cert = found["opening_deg"], found["clearance_certified"]
    return {"opening_deg": deg, "tried": tried,
            "text": f"it plans at a mouth opening of {deg:g} deg (mesh.mouth_opening_deg;"
                    f" certified {cert * 1e3:.2f} mm there)"}


# -- robot base for all sites -----------------------------------------------------------------

# Center axes in the scenario's Oral frame, by posture. The bundled scenarios keep Oral Y up in
# the room (so the cart stands on the floor, Base Z || Oral Y). Lying supine: the mouth opens up
# (Center Z = Oral Y) and the head lies towards World +Y = -Oral Z (Center Y, cranial); sitting:
# the mouth faces Oral Z and the head is up (Center Y = Oral Y).
R_OC_BY_POSTURE = {
    "lying": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
    "sitting": np.eye(3),
}


def center_in_oral(posture: str, placements: list[Placement]) -> np.ndarray:
    """X_OC: the patient's Center frame in the scenario's Oral frame. Oral's origin is where the
    scenario puts the mouth; we put the mean feeding target there."""
    R = R_OC_BY_POSTURE[posture]
    p_CT = np.mean([p.X_CT[:3, 3] for p in placements], axis=0)
    return transform(R, -R @ p_CT)


@dataclass
class RobotResult:
    scenario: object  # systems.robot.moprp.Scenario (with the plant's TCP)
    X_OC: np.ndarray
    X_OT: np.ndarray  # (S, 4, 4) feeding targets in Oral
    base_xyz: np.ndarray  # (3,) selected base position in Oral
    X_WBase: np.ndarray
    branch: np.ndarray  # (S,) IK branch per site
    q: np.ndarray  # (S, 6) at the feeding target
    q_pre: np.ndarray  # (S, 6) pre-feed configuration
    indices: np.ndarray  # (3,) worst over sites of [dexterity, error_range, joint_variation]
    site_indices: np.ndarray  # (S, 3)
    pareto_xyz: np.ndarray
    pareto_F: np.ndarray
    percentiles: np.ndarray  # (3,) of the selection against random feasible bases
    percentile_samples: int
    evaluations: int
    generations: int
    seconds: float
    # SceneGraph along each site's feed (diagrams.arm_clearance.confirm_feed): distance (m),
    # pair, samples, ok, limit (= the scenario's clearance); front bases dropped before it
    feed_clearance: list = field(default_factory=list)
    selection_dropped: int = 0


def _site_evaluations(X, sc, rng, targets, model):
    return [moprp.evaluate_bases(X, sc, rng, model=model, X_OT=T) for T in targets]


def combine_sites(evs):
    """Several sites from one base: feasible when every site is; each index is its worst value
    over the sites (the base must serve all of them); violations add up."""
    F = np.max([np.where(np.isfinite(e.objectives), e.objectives, 1e12) for e in evs], axis=0)
    cv = np.sum([e.violation for e in evs], axis=0)
    return F, cv


def percentile_reference(sc, evaluate) -> np.ndarray:
    """Indices (n, 3) of up to ``sc.percentile_samples`` uniformly random bases in the bounds that
    serve every site (``evaluate(X, rng) -> (F, violation)``), seeded by the scenario: what the
    selection's percentile ranks are taken against (the plan and the studio)."""
    rng_pct = seeds.rng(sc.seed, moprp.STREAM_PERCENTILES)
    F_rand = []
    for _ in range(20):
        Xr = sc.lower + rng_pct.random((2000, 3)) * (sc.upper - sc.lower)
        Fr, cvr = evaluate(Xr, rng_pct)
        F_rand.append(Fr[cvr <= 0])
        if sum(len(f) for f in F_rand) >= sc.percentile_samples:
            break
    return np.concatenate(F_rand)[: sc.percentile_samples]


def robot_stage(case: Case, placements: list[Placement], *, progress=None) -> RobotResult:
    """MOPRP over the base position with every site's feeding target (NSGA-II, systems.robot.nsga2).

    Departure from seed 001 for several sites: the objectives are the worst index over the sites
    and a base is feasible only if every site has a surviving branch."""
    t0 = time.perf_counter()
    sc = moprp.load_scenario(case.robot.scenario, X_FT=actuator.X_FT())
    sc = dataclasses.replace(sc, pop=case.robot.pop, gen=case.robot.gen,
                             seed=seeds.seed(case.seed, seeds.ROBOT))
    if case.robot.joint_headroom is not None:
        sc = dataclasses.replace(sc, joint_headroom=case.robot.joint_headroom)
    X_OC = center_in_oral(case.patient.posture, placements)
    targets = np.array([X_OC @ p.X_CT for p in placements])
    model = moprp.collision_model(sc)

    def evaluate(X, rng):
        return combine_sites(_site_evaluations(X, sc, rng, targets, model))

    def explain(Xs, rng) -> str:
        evs = _site_evaluations(Xs, sc, rng, targets, model)
        why = []
        for site, ev in zip(case.sites, evs, strict=True):
            codes = ev.reason[ev.reason > 0]
            common = int(np.bincount(codes).argmax()) if codes.size else moprp.DROP_IK
            why.append(f"site {site.name}: {int(ev.feasible.sum())} feasible, mostly "
                       f"'{moprp.DROP_REASONS[common]}'")
        return (f"no base position in the bounds serves every site ({Xs.shape[0]} sampled); "
                + "; ".join(why))

    def on_start(n_ok, n0):
        if progress is not None:
            progress.say(f"{n_ok} of {n0} sampled bases serve all {len(placements)} sites; "
                         f"NSGA-II pop {sc.pop}, gen <= {sc.gen}")

    def on_gen(g, n_front, hv):
        if progress is not None:
            progress.step(g - 1, sc.gen, f"generations, front {n_front}, hypervolume {hv:.4g}")

    res = moprp.search(sc, evaluate, explain=explain, on_start=on_start, on_generation=on_gen)
    Xf, F = res.X, res.F
    # SceneGraph confirms the selection along every site's whole feed; a base that fails is
    # dropped and the next-ranked one taken
    dropped = 0
    for k in moprp.selection_order(F):
        evs = _site_evaluations(Xf[k : k + 1], sc, moprp.evaluation_rng(sc), targets,
                                model)
        checker = SceneGraphClearance(sc, Xf[k])
        feeds = [confirm_feed(checker, sc, int(e.branch[0]), X_OT=T)
                 for e, T in zip(evs, targets, strict=True)]
        if all(f["ok"] for f in feeds):
            break
        dropped += 1
    else:
        raise PlanningFailure(
            f"none of the {Xf.shape[0]} front bases keeps every site's feed clear in SceneGraph "
            f"by the clearance {1000 * sc.clearance:.1f} mm with every joint "
            f"{np.rad2deg(sc.joint_headroom):g} deg from its limits")
    if progress is not None and dropped:
        progress.say(f"SceneGraph: {dropped} front bases dropped before the selection")

    # percentile ranks of the selection against random bases that serve every site
    F_rand = percentile_reference(sc, evaluate)
    pct = moprp.percentiles(F[k], F_rand) if len(F_rand) else np.full(3, np.nan)

    return RobotResult(
        scenario=sc,
        X_OC=X_OC,
        X_OT=targets,
        base_xyz=Xf[k],
        X_WBase=sc.X_WO @ moprp.base_pose(Xf[k]),
        branch=np.array([int(e.branch[0]) for e in evs]),
        q=np.array([e.q[0] for e in evs]),
        q_pre=np.array([e.q_pre[0] for e in evs]),
        indices=F[k],
        site_indices=np.array([e.objectives[0] for e in evs]),
        pareto_xyz=Xf,
        pareto_F=F,
        percentiles=pct,
        percentile_samples=int(len(F_rand)),
        evaluations=int(res.evaluations),
        generations=int(res.generations),
        seconds=time.perf_counter() - t0,
        feed_clearance=feeds,
        selection_dropped=dropped,
    )


# -- capability check of every feeding target ---------------------------------------------------


@dataclass
class CapabilityResult:
    cmap: object  # systems.capability.maps.CapabilityMap over the sites' neighbourhoods
    X_BA: np.ndarray  # (S, 4, 4) the mapped frame (implant tip, z = drilling) at each target
    map_reachable: np.ndarray  # (S,) the map's answer at the target (exact: undecided -> IK)
    map_source: np.ndarray  # (S,) int8 what it rests on (maps.SOURCES: certified / by IK)
    index: np.ndarray  # (S,) reachability index of the target's voxel (centre-sampled, seed 004)
    neighbourhood_index: np.ndarray  # (S,) mean index over the 3x3x3 voxels around the target
    ik_branches: np.ndarray  # (S,) closed-form branches within limits at the exact target
    seconds: float


def capability_stage(case: Case, robot: RobotResult, *, progress=None) -> CapabilityResult:
    """Capability map (seed 004) of the arm + actuator around each feeding target, from the chosen
    base: the voxels of the 3x3x3 neighbourhood of every target, all approach directions and
    sampled rolls (the contra-angle's roll is not free). Only these voxels are built: the check
    needs the map where the tasks are, not the whole workspace (a full 5 cm map takes minutes).
    The answer at each target is the certified cell's or, where the cell is undecided,
    closed-form IK at the target (:meth:`CapabilityMap.answer`): never "not reachable" where IK
    reaches; the index is the paper's (centre-sampled) of the same map."""
    t0 = time.perf_counter()
    sc = robot.scenario
    X_FA = actuator.actuator_map_frame()
    X_BE = moprp.target_pose(robot.base_xyz, robot.X_OT)
    X_BA = X_BE @ invert(actuator.X_FT()) @ X_FA
    params = cm.make_params(case.capability.voxel, case.capability.directions,
                            limits=sc.limits, X_FT=X_FA, tool="actuator")
    grid = cm.make_grid(params)
    near = grid.neighbourhood(X_BA[:, :3, 3])
    cmap = cm.CapabilityMap(params, grid, *cm.build_block(params, np.unique(near[near >= 0])))
    map_reach, source, index = cmap.answer(X_BA)
    neigh = cmap.neighbourhood_index(X_BA[:, :3, 3])
    branches = kin.ik(X_BE, limits=sc.limits, X_FT=actuator.X_FT()).valid.sum(axis=-1)
    if progress is not None:
        for site, r, src, i, b in zip(case.sites, map_reach, source, index, branches,
                                      strict=True):
            progress.say(f"site {site.name}: {'reachable' if r else 'NOT reachable'} "
                         f"({cm.SOURCES[int(src)]}), voxel index {i:.2f}, "
                         f"{int(b)} IK branches within limits")
    return CapabilityResult(cmap, X_BA, map_reach, source, index, neigh, branches,
                            time.perf_counter() - t0)


# -- teleoperated feeding per site ---------------------------------------------------------------


def teleop_cases(case: Case, fit: FitResult, placements: list[Placement],
                 robot: RobotResult) -> list[TeleopCase]:
    """Each site's feeding case in the room: layout, start pose, FPSM, fixture, target, and the
    scan bound of the site's instrument (what the supervisor and the estimator bound)."""
    from implantplan.systems.placement.scan_clearance import ScanClearance

    exact = fit.exact(case.mesh.close_open_cuts)
    scans, grid = [], None
    for site in case.sites:  # one distance grid of the scan for every site's instrument
        scans.append(ScanClearance(exact, case.instrument_at(site), grid=grid))
        grid = scans[-1].grid
    sc = robot.scenario
    X_WC = sc.X_WO @ robot.X_OC
    return [
        TeleopCase(
            scenario=case.patient.posture,
            X_WBase=robot.X_WBase,
            q_start=robot.q_pre[k],
            X_WCenter=X_WC,
            fpsm=fit.fpsm,
            vf=p.vf,
            X_WTarget=sc.X_WO @ robot.X_OT[k],
            rod_radius=p.rod_radius,
            implant_length=p.implant_length,
            limits=sc.limits,
            label=f"site {site.name}",
            instrument=case.instrument_at(site),
            safety=case.safety,
            scan=scans[k],
        )
        for k, (site, p) in enumerate(zip(case.sites, placements, strict=True))
    ]


def simulation_stage(case: Case, fit: FitResult, placements: list[Placement],
                     robot: RobotResult, *, runs: int | None = None, progress=None) -> list[dict]:
    """A short teleop feeding simulation per site (seed 001's feeding test on the Drake diagram):
    scripted operator feeds from the pre-feed configuration to the feeding target, VF active,
    FPSM estimator watching."""
    runs = case.simulation.runs if runs is None else runs
    if runs == 0:
        if progress is not None:
            progress.say("no feeding runs asked for (simulation.runs = 0 / --runs 0)")
        return []
    out = []
    for k, (site, tc) in enumerate(zip(case.sites, teleop_cases(case, fit, placements, robot),
                                       strict=True)):
        res = run_feeding(tc, runs=runs, seed=seeds.seed(case.seed, seeds.FEEDING, k),
                          mode=case.simulation.mode)
        res["site"] = site.name
        out.append(res)
        if progress is not None:
            worst = max(r["max_vf_violation"] for r in res["runs"])
            progress.step(k, len(case.sites), f"site {site.name}: {runs} feeds, max VF "
                          f"violation {worst * 1e3:.2f} mm, realtime x{res['realtime_factor']:.1f}")
    return out


def planned_implants(case: Case, X_WC: np.ndarray, *, scanned: bool = False):
    """Each site's planned implant as (entries, apexes) (n, 3), m: the entry at the site, the
    apex ``placed_length`` deeper along the axis; in the opened mesh frame, or with
    ``scanned`` back in the scan's frame as scanned (systems.anatomy.distances.as_scanned)."""
    entry = apply(X_WC, np.array([s.position for s in case.sites]))
    axis = np.array([X_WC[:3, :3] @ s.axis for s in case.sites])
    apex = entry - np.array([s.placed_length for s in case.sites])[:, None] * axis
    if not scanned:
        return entry, apex
    both = anatomy.as_scanned(np.vstack([entry, apex]), case.mesh.mouth_opening_deg,
                              case.mesh.opening)
    return both[:len(entry)], both[len(entry):]


def anatomy_stage(case: Case, fit: FitResult) -> dict | None:
    """The clinical distances of every planned implant (systems.anatomy.distances), when the
    case has anatomy (``anatomy:`` canals) or a CBCT (teeth and bone): each implant (its entry
    at the site, its apex ``placed_length`` deeper, ``implant_diameter`` wide) is taken back
    to the scan's frame as scanned (the inverse of the jaw-opening map), where the CBCT and the
    canals are; distances in m. With a CBCT, the bone around each implant (and, at a site of
    the anterior maxilla, on its facial side). None without anatomy."""
    if case.anatomy is None and fit.cbct is None:
        return None
    entry_s, apex_s = planned_implants(case, fit.fpsm.X_WC, scanned=True)
    length = np.array([s.placed_length for s in case.sites])
    radius = np.array([s.implant_diameter / 2 for s in case.sites])
    canals = case.anatomy.canals if case.anatomy is not None else ()
    teeth_hu = case.anatomy.teeth_threshold_hu if case.anatomy is not None else 1800.0
    inter = anatomy.inter_implant_clearances(entry_s, apex_s, radius)
    sites = []
    for k, s in enumerate(case.sites):
        rec = {"site": s.name, "entry": entry_s[k], "apex": apex_s[k],
               "diameter": float(2 * radius[k]), "length": float(length[k]),
               "nearest_implant_m": float(np.min(inter[k])) if len(case.sites) > 1 else None}
        if canals:
            d = [anatomy.canal_clearance(entry_s[k], apex_s[k], radius[k], c.polyline, c.radius)
                 for c in canals]
            rec["canal_clearance_m"], rec["canal"] = float(min(d)), int(np.argmin(d))
        if fit.cbct is not None:
            vol = fit.cbct.volume
            rec["tooth_clearance_m"] = anatomy.tooth_clearance(vol, entry_s[k], apex_s[k],
                                                               radius[k], teeth_hu)
            rec["bone_margin_m"], rec["bone_crest_depth_m"] = anatomy.bone_margin(
                vol, entry_s[k], apex_s[k], radius[k], case.mesh.bone_threshold_hu)
            if anatomy.anterior_maxilla(s.name):  # facial: out of the mouth, Center +Z (the
                # upper jaw does not move with the jaw-opening model)
                rec["facial_bone_margin_m"] = anatomy.bone_margin(
                    vol, entry_s[k], apex_s[k], radius[k], case.mesh.bone_threshold_hu,
                    facial=fit.fpsm.X_WC[:3, 2])[0]
        sites.append(rec)
    return {"frame": "the scan's frame as scanned (a CBCT's patient frame, LPS), m",
            "teeth_threshold_hu": teeth_hu, "bone_threshold_hu": case.mesh.bone_threshold_hu,
            "canals": len(canals), "sites": sites}
