"""The plan's checks: one id, one bound and one pass/fail rule per requirement, shared by
``plan`` (every check of a plan), ``studio`` (the layout's checks again when a layout is kept)
and ``batch`` (which reads them from each plan).

A check is a dict: ``id`` (stable, what docs/formats.md's check table names), ``name``, ``site``
(None for the case), ``value``, ``limit``, ``bound`` ("max": passes when value <= limit; "min":
passes when value > limit, strictly, since a clearance of exactly 0 is contact), ``unit``,
``margin`` (>= 0 on the passing side) and ``pass``.
"""

from __future__ import annotations

import numpy as np

from implantplan.systems.capability import maps as cm
from implantplan.systems.frames import wrap_angle

MAX_PENETRATION_DEPTH = 0.5e-3  # m, dense check of the FPSM fit
GRID_TOL_D = 0.1e-3  # m, PSO vs exhaustive grid
GRID_TOL_THETA = np.deg2rad(0.1)
MIN_CAPABILITY = 0.5  # mean reachability index around a feeding target
MAX_VF_VIOLATION = 1e-3  # m

# The checks that depend on the robot's base: recomputed when the studio keeps another layout.
LAYOUT_CHECK_IDS = ("robot.arm_clearance_scene_graph", "robot.joint_headroom",
                    "robot.ik_branches",
                    "capability.neighbourhood_index")


def check(check_id: str, name: str, value: float, limit: float, *, unit: str, upper: bool,
          site=None) -> dict:
    """A check and its margin: a maximum (``upper``) passes when value <= limit (so "0 alarms
    <= 0" passes), a minimum when value > limit."""
    margin = (limit - value) if upper else (value - limit)
    passed = margin >= 0 if upper else margin > 0
    return {"id": check_id, "name": name, "site": site, "value": float(value),
            "limit": float(limit), "bound": "max" if upper else "min", "unit": unit,
            "margin": float(margin), "pass": bool(passed)}


def passed(checks: list[dict]) -> bool:
    """The plan's verdict: every check passes."""
    return all(c["pass"] for c in checks)


def scene_graph_fields(feed_clearance: list[dict], k: int) -> dict:
    """SceneGraph clearances of site k's reported configurations (empty before confirmation)."""
    if k >= len(feed_clearance):
        return {}
    f = feed_clearance[k]
    return {"scene_graph_clearance_m": f["distance_target"],
            "scene_graph_clearance_pre_m": f["distance_pre"],
            "feed_clearance": {"distance_m": f["distance"], "pair": f["pair"],
                               "samples": f["samples"], "limit_m": f["limit"],
                               "patient_distance_m": f.get("patient_distance"),
                               "patient_pair": f.get("patient_pair"),
                               "reported_within_m": f.get("max_distance")},
            "joint_headroom": {"min_rad": f["headroom"], "limit_rad": f["headroom_limit"],
                               "over": "every sample of the feed and of the feed under each "
                                       "head displacement the scenario allows"}}


def capability_fields(params, *, reachable: bool, source: int, index: float,
                      neighbourhood_index: float, ik_branches: int) -> dict:
    """A site's ``capability`` block (plan.json, the studio): the map's answer at the target and
    what it rests on (a certified cell, or closed-form IK at the target where the cell is
    undecided: systems.capability.maps.SOURCES), the paper's centre-sampled index of the
    target's voxel and around it, which map that index came from, and the IK branch count."""
    return {"map_reachable": bool(reachable),
            "map_answer": cm.SOURCES[int(source)],
            "voxel_index": float(index),
            "neighbourhood_index": float(neighbourhood_index),
            "index_map": f"centre-sampled index (seed 004) of the {params.describe()}",
            "ik_branches_within_limits": int(ik_branches)}


def fpsm_checks(diagnostics: dict) -> list[dict]:
    """The FPSM fit's dense check: no mesh point deeper than the bound outside the model."""
    return [check("fpsm.penetration_depth", "fpsm dense-check penetration depth",
                  diagnostics["dense_max_depth_m"], MAX_PENETRATION_DEPTH, unit="m", upper=True)]


def placement_checks(site: str, placement, *, distance_to_tissue: float, tolerance: float,
                     clearance_margin: float) -> list[dict]:
    """A site on the tissue, and its instrument placement: both lines' clearances, the whole
    tool's certified (FPSM) and exact (FCL) clearances over the feed and the fixture's region,
    and PSO against the exhaustive grid where the grid ran."""
    out = [check("site.on_tissue", "site on the scanned tissue", distance_to_tissue, tolerance,
                 unit="m", upper=True, site=site),
           check("placement.line1_clearance", "line1 (rod) clearance", placement.d_safe_min_line1,
                 clearance_margin, unit="m", upper=False, site=site),
           check("placement.line2_clearance", "line2 (implant path) clearance",
                 placement.d_safe_min_line2, clearance_margin, unit="m", upper=False, site=site)]
    ver = placement.verification
    if ver:
        against = "scan" if ver.get("certified_against") == "scan" else "FPSM"
        out.append(check("placement.tool_clearance_certified", "tool clearance over the feed and "
                         f"the fixture's region (certified, {against})", ver["clearance_certified"],
                         ver["clearance_margin"], unit="m", upper=False, site=site))
        if ver.get("clearance_exact_min") is not None:
            out.append(check("placement.tool_clearance_exact", "tool clearance over the feed and "
                             "the fixture's region (exact, FCL against the scan)",
                             ver["clearance_exact_min"], ver["clearance_margin"], unit="m",
                             upper=False, site=site))
    grid = placement.to_dict().get("grid_check") or {}
    if "x" in grid:
        # the PSO's optimum (of the FPSM objective) against the grid's; when the instrument
        # search replaced it (verification.instrument_search), the placement is not the PSO's
        d_d = grid.get("distance_d_T", abs(placement.d_T - float(grid["x"][0])))
        d_th = grid.get("distance_theta_T",
                        abs(wrap_angle(placement.theta_T - float(grid["x"][1]))))
        out.append(check("placement.grid_d_T", "PSO vs grid optimum, d_T", d_d, GRID_TOL_D,
                         unit="m", upper=True, site=site))
        out.append(check("placement.grid_theta_T", "PSO vs grid optimum, theta_T", d_th,
                         GRID_TOL_THETA, unit="rad", upper=True, site=site))
    return out


def layout_checks(site: str, feed: dict | None, *, ik_branches: int,
                  neighbourhood_index: float) -> list[dict]:
    """The base layout at a site (:data:`LAYOUT_CHECK_IDS`): the arm's SceneGraph clearance
    along the feed (once confirmed, ``feed``), IK branches at the target and the capability
    index around it."""
    out = []
    if feed is not None:
        out.append(check("robot.arm_clearance_scene_graph",
                         "arm clearance along the feed (SceneGraph)", feed["distance"],
                         feed["limit"], unit="m", upper=False, site=site)
                   | {"pair": " / ".join(feed["pair"])})
        room = np.asarray(feed["headroom"], dtype=float)
        j = int(np.argmin(room))
        out.append(check("robot.joint_headroom", "smallest joint headroom along the feed and "
                         "under the head motions", float(room[j]), feed["headroom_limit"],
                         unit="rad", upper=False, site=site) | {"joint": j + 1})
    out.append(check("robot.ik_branches", "IK branches at the feeding target", ik_branches, 0,
                     unit="branches", upper=False, site=site))
    out.append(check("capability.neighbourhood_index", "capability index around the target",
                     neighbourhood_index, MIN_CAPABILITY, unit="1", upper=False, site=site))
    return out


def feeding_checks(site: str, runs: list[dict]) -> list[dict]:
    """The simulated feeds at a site: every feed reaches the target, inside the fixture, with
    the rod clear and no FPSM alarm (none when no feed ran)."""
    if not runs:
        return []
    return [
        check("feeding.missed_target", "feeds missing the target",
              sum(not r["reached_target"] for r in runs), 0, unit="runs", upper=True, site=site),
        check("feeding.vf_violation", "max VF violation",
              max(r["max_vf_violation"] for r in runs), MAX_VF_VIOLATION, unit="m", upper=True,
              site=site),
        check("feeding.rod_d_safe", "min d_safe of the rod during feeds",
              min(r["min_d_safe"] for r in runs), 0.0, unit="m", upper=False, site=site),
        check("feeding.collision_alarms", "FPSM collision alarms",
              sum(r["collision_alarm"] for r in runs), 0, unit="runs", upper=True, site=site),
    ]


def anatomy_checks(anatomy: dict | None) -> list[dict]:
    """The clinical distances of each planned implant (analyses.pipeline.anatomy_stage), each
    against its bound (systems.anatomy.distances): canal >= 2 mm, adjacent tooth >= 1.5 mm,
    the nearest other implant >= 3 mm, the bone around the implant >= 1 mm (the CBCT's
    bone: the least lateral thickness from the crest to the apex, ``bone_margin_m``) and, at a
    site of the anterior maxilla, >= 1.5 mm on its facial side; a distance the case gives no
    anatomy for (no canal, no CBCT, one implant) is not checked."""
    from implantplan.systems.anatomy import distances as d

    if anatomy is None:
        return []
    out = []
    for rec in anatomy["sites"]:
        for key, check_id, name, limit in ANATOMY_RULES:
            if rec.get(key) is not None:
                out.append(check(check_id, name, rec[key], getattr(d, limit), unit="m",
                                 upper=False, site=rec["site"]))
    return out


# (anatomy record key, check id, name, bound in systems.anatomy.distances): the card's order
ANATOMY_RULES = (
    ("canal_clearance_m", "anatomy.canal_distance", "implant to the nerve canal", "MIN_CANAL"),
    ("tooth_clearance_m", "anatomy.adjacent_tooth_distance",
     "implant to an adjacent tooth (CBCT)", "MIN_TOOTH"),
    ("nearest_implant_m", "anatomy.inter_implant_distance",
     "implant to the nearest other implant", "MIN_INTER_IMPLANT"),
    ("bone_margin_m", "anatomy.bone_around_implant", "bone around the implant (CBCT)",
     "MIN_BONE"),
    ("facial_bone_margin_m", "anatomy.facial_bone_anterior_maxilla",
     "facial bone around the implant, anterior maxilla (CBCT)",
     "MIN_BONE_FACIAL_ANTERIOR_MAXILLA"),
)
