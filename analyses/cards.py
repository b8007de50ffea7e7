"""The surgeon's card: one per implant, what the plan means for that implant on one screen
(DESIGN.md section 9). ``plan.json`` carries the cards (``cards``, SI units), ``report.html``
opens with them (mm, deg) and the studio's status panel shows the selected site's.

A card is built from the plan itself (:func:`surgeon_cards` reads only the plan's dict), so the
three places show the same numbers:

- tooth (FDI, when the site's name is a tooth number), the entry point (the site, on the jaw
  surface) and the apex (``placed_implant_length`` into the bone along the axis) in the scan's
  frame (the mesh file's coordinates, after the mouth opening the plan modelled), the axis there,
  its angles (tilt from the Center frame's +Y, the mouth's up, and the tilt's two components
  towards Center +X and +Z, out of the mouth), the depth (entry to apex);
- the instrument-to-tissue clearance (exact: FCL against the scan over the feed and the
  fixture's region, ``placement.tool_clearance_exact``) with the instrument named; the arm-to-
  patient clearance (SceneGraph along the feed, the closest pair named); P(the clearance stays
  above 0) under registration error (the plan's registration Monte Carlo); the feed's
  duration (the simulated feeds, the longest); the smallest joint headroom per joint; the
  capability check's answer as it reports it;
- with anatomy (canals, a CBCT), each clinical distance of the implant (analyses.checks.
  ANATOMY_RULES: canal, adjacent tooth, nearest other implant, bone around it, facial bone in
  the anterior maxilla) with its bound and pass/fail, from the plan's anatomy checks;
- a verdict in words: ``refused`` (a check of the site failed: which), ``tight`` (every check
  passes but a margin is below :data:`TIGHT`: what to check) or ``ready``, with the next step.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np

# A passing plan is "tight" at a site when a margin is below these (SI): the tissue clearance
# over the clinical margin, P(clear) under registration error, the arm's clearance over the
# scenario's, the joint headroom over the scenario's.
TIGHT = {"tissue_margin": 0.5e-3, "p_clear": 0.99, "arm_margin": 5e-3,
         "headroom_margin": np.deg2rad(5.0)}
FDI = re.compile(r"^(?:[1-4][1-8]|[5-8][1-5])$")  # permanent and deciduous teeth
READY_STEP = ("register the patient to the plan, then feed from the pre-feed pose under the "
              "virtual fixture")


def tooth_fdi(name: str) -> int | None:
    """The FDI tooth number a site's name is (``"36"`` -> 36), None for other names."""
    return int(name) if FDI.match(str(name)) else None


def axis_angles(axis_C) -> dict:
    """The implant axis (unit, Center) as angles (rad): ``tilt`` from Center +Y (the mouth's
    up, the occlusal normal of a lower jaw), ``towards_x`` and ``towards_z`` its components in
    the XY and ZY planes (atan2 of the X / Z component over the Y component)."""
    a = np.asarray(axis_C, dtype=float)
    a = a / np.linalg.norm(a)
    return {"tilt": float(np.arccos(np.clip(a[1], -1.0, 1.0))),
            "towards_x": float(np.arctan2(a[0], a[1])),
            "towards_z": float(np.arctan2(a[2], a[1]))}


def _site_checks(plan: dict, name: str) -> list[dict]:
    return [c for c in plan["checks"] if c["site"] == name]


def _check(checks: list[dict], check_id: str) -> dict | None:
    found = [c for c in checks if c["id"] == check_id]
    return min(found, key=lambda c: c["margin"]) if found else None


def surgeon_card(plan: dict, k: int) -> dict:
    """Site ``k``'s card from the plan dict (SI; see the module docstring)."""
    s = plan["sites"][k]
    name = s["name"]
    X_MC = np.asarray(plan["fpsm"]["X_mesh_Center"], dtype=float)
    p_C = np.asarray(s["hole"]["position"], dtype=float)
    a_C = np.asarray(s["hole"]["axis"], dtype=float)
    a_C = a_C / np.linalg.norm(a_C)
    depth = float(s["placed_implant_length"])
    entry = X_MC[:3, :3] @ p_C + X_MC[:3, 3]
    axis = X_MC[:3, :3] @ a_C
    apex = entry - depth * axis  # the axis points from the bone into the cavity
    checks = _site_checks(plan, name)
    case_checks = [c for c in plan["checks"] if c["site"] is None]

    tissue = _check(checks, "placement.tool_clearance_exact")
    arm = _check(checks, "robot.arm_clearance_scene_graph")
    room = _check(checks, "robot.joint_headroom")
    reg = s.get("registration") or {}
    runs = (s.get("simulation") or {}).get("runs") or []
    inst = plan["case"]["instrument"]
    head = s["ik"].get("joint_headroom") or {}
    card = {
        "site": name,
        "tooth_fdi": tooth_fdi(name),
        "frame": "scan: the mesh file's coordinates, the mouth opened as planned "
                 f"({plan['fpsm']['mouth_opening_deg']:g} deg)",
        "entry": entry, "apex": apex, "axis": axis,
        "axis_angles": axis_angles(a_C),
        "depth": depth,
        "instrument": inst["kind"] + (f" ({inst['urdf']})" if inst.get("urdf") else ""),
        "instrument_to_tissue": None if tissue is None else {
            "value": tissue["value"], "limit": tissue["limit"], "margin": tissue["margin"],
            "reference": "exact: FCL against the scan, the whole instrument over the feed and "
                         "the fixture's region"},
        "arm_to_patient": _arm_to_patient(s["ik"].get("feed_clearance")),
        "p_clear_under_registration": reg.get("probability_clear"),
        "registration": None if not reg else {
            "sigma_translation": reg["sigma_translation"],
            "sigma_rotation": reg["sigma_rotation"], "samples": reg["samples"]},
        "expected_accuracy": None if not reg else registration_accuracy(
            reg, X_MC[:3, :3].T @ (entry - X_MC[:3, 3]), p_C - depth * a_C),
        "feed_duration": max((r["sim_seconds"] for r in runs), default=None),
        "joint_headroom": head.get("min_rad"),
        "joint_headroom_limit": head.get("limit_rad"),
        "reach": {key: val for key, val in (s.get("capability") or {}).items()
                  if isinstance(val, (bool, int, float, str))},
        "anatomy": _anatomy(checks),
        "units": "m, rad, s",
    }
    card.update(_verdict(checks + case_checks, tissue, card["arm_to_patient"], arm, room, card))
    return card


def registration_accuracy(reg: dict, entry_C, apex_C) -> dict:
    """The implant's expected deviation from the plan under registration error alone (the
    dominant source of analyses.studies.accuracy's budget): the plan's own registration Monte
    Carlo samples (its seed, sigmas and count: the same draws of E^-1), applied to the planned
    entry and apex in Center (m) and to the axis; mean and 95th percentile of the entry and
    apex deviation (m) and of the angle (rad)."""
    from implantplan.systems.frames import frame_from_z
    from implantplan.systems.placement.exact_clearance import registration_errors
    from implantplan.systems.safety import SafetySpec
    from implantplan.systems.teleop.insertion import PlannedImplant, implant_deviation

    spec = dataclasses.replace(SafetySpec(),
                               registration_sigma_translation=reg["sigma_translation"],
                               registration_sigma_rotation=reg["sigma_rotation"])
    E = registration_errors(spec, np.random.default_rng(reg["seed"]), int(reg["samples"]))
    entry, apex = np.asarray(entry_C, float), np.asarray(apex_C, float)
    # the implant as placed at a frame on its axis (origin the entry): E^-1 moves that frame
    length = float(np.linalg.norm(entry - apex))
    F = frame_from_z(entry, entry - apex)
    dev = implant_deviation(E @ F, PlannedImplant(X_CT_target=F, depth=0.0,
                                                  platform_T=np.zeros(3),
                                                  apex_T=np.array([0.0, 0.0, -length])))
    out = {"source": "registration error alone (the plan's registration Monte Carlo draws; "
                     "the full budget: implantplan analyze accuracy)"}
    for key in ("entry", "apex", "angle"):
        out[key] = {"mean": float(dev[key].mean()), "p95": float(np.percentile(dev[key], 95))}
    return out


ANATOMY_LABELS = {"anatomy.canal_distance": "implant to canal",
                  "anatomy.adjacent_tooth_distance": "implant to adjacent tooth",
                  "anatomy.inter_implant_distance": "implant to nearest implant",
                  "anatomy.bone_around_implant": "bone around implant",
                  "anatomy.facial_bone_anterior_maxilla": "facial bone (anterior maxilla)"}


def _anatomy(checks: list[dict]) -> list[dict] | None:
    """The site's anatomical distances (its ``anatomy.*`` checks, in analyses.checks.
    ANATOMY_RULES' order): id, label, value (m; None where not finite), bound (m, a minimum)
    and pass; None when the plan checked no anatomy at the site."""
    from implantplan.analyses.checks import ANATOMY_RULES

    out = []
    for _, check_id, _, _ in ANATOMY_RULES:
        c = _check(checks, check_id)
        if c is not None:
            out.append({"id": check_id, "label": ANATOMY_LABELS[check_id], "value": c["value"],
                        "limit": c["limit"], "pass": c["pass"]})
    return out or None


def _arm_to_patient(feed: dict | None) -> dict | None:
    """The arm's SceneGraph clearance to the patient and chair along the feed (None before
    confirmation; ``value`` None when nothing is within the distance SceneGraph reported)."""
    if not feed or "patient_distance_m" not in feed:
        return None
    d, limit = feed["patient_distance_m"], feed["limit_m"]
    return {"value": d, "limit": limit, "margin": None if d is None else d - limit,
            "pair": " / ".join(feed["patient_pair"]) if d is not None else "",
            "reported_within": feed["reported_within_m"],
            "reference": "Drake SceneGraph along the feed, pairs with the patient or chair"}


def _verdict(checks, tissue, arm, arm_all, room, card) -> dict:
    failed = [c for c in checks if not c["pass"]]
    if failed:
        why = [c["name"] + (f" ({c['pair']})" if c.get("pair") else "") for c in failed]
        return {"verdict": "refused", "reasons": why,
                "next_step": "refused: " + "; ".join(why) + ". Re-plan (move the site, the "
                             "instrument or the robot's bounds) before surgery"}
    tight = []
    if tissue is not None and tissue["margin"] < TIGHT["tissue_margin"]:
        tight.append(f"the instrument's clearance to the tissue "
                     f"({1e3 * tissue['value']:.2f} mm, {1e3 * tissue['margin']:.2f} mm over "
                     "the margin): check the site and the mouth opening")
    p = card["p_clear_under_registration"]
    if p is not None and p < TIGHT["p_clear"]:
        tight.append(f"the registration (the clearance holds in {100 * p:.1f} % of "
                     "registration errors): check the registration accuracy")
    if arm is not None and arm["margin"] is not None and arm["margin"] < TIGHT["arm_margin"]:
        tight.append(f"the arm near the patient ({arm['pair']}, {1e3 * arm['value']:.1f} mm): "
                     "check the cart's position")
    if arm_all is not None and arm_all["margin"] < TIGHT["arm_margin"]:
        tight.append(f"the arm's clearance ({arm_all.get('pair', '')}, "
                     f"{1e3 * arm_all['value']:.1f} mm): check the cart's position")
    if room is not None and room["margin"] < TIGHT["headroom_margin"]:
        tight.append(f"joint {room.get('joint', '?')}'s headroom "
                     f"({np.rad2deg(room['value']):.1f} deg): check the cart's position")
    if tight:
        return {"verdict": "tight", "reasons": tight, "next_step": "tight: " +
                "; ".join(tight)}
    return {"verdict": "ready", "reasons": [], "next_step": "ready: " + READY_STEP}


def surgeon_cards(plan: dict) -> list[dict]:
    """Every site's card, in the plan's site order."""
    return [surgeon_card(plan, k) for k in range(len(plan["sites"]))]


def card_lines(card: dict) -> list[tuple[str, str]]:
    """A card as (label, value) lines in mm and deg: what the report and the studio show."""
    def mm3(v):
        return "(" + ", ".join(f"{1e3 * x:.1f}" for x in v) + ") mm"

    ang = card["axis_angles"]
    tc, ac = card["instrument_to_tissue"], card["arm_to_patient"]
    reg = card["registration"]
    p = card["p_clear_under_registration"]
    acc = card.get("expected_accuracy")
    room = card["joint_headroom"]
    reach = card["reach"]
    lines = [
        ("entry point (scan)", mm3(card["entry"])),
        ("apex (scan)", mm3(card["apex"])),
        ("axis", f"tilt {np.rad2deg(ang['tilt']):.1f} deg from Center +Y "
                 f"(towards +X {np.rad2deg(ang['towards_x']):.1f}, towards +Z "
                 f"{np.rad2deg(ang['towards_z']):.1f} deg)"),
        ("depth (entry to apex)", f"{1e3 * card['depth']:.1f} mm"),
        ("instrument to tissue", "not checked" if tc is None else
         f"{1e3 * tc['value']:.2f} mm exact (FCL), margin {1e3 * tc['limit']:.1f} mm; "
         f"instrument: {card['instrument']}"),
        ("arm to patient", "not confirmed" if ac is None else
         (f"> {1e3 * ac['reported_within']:.0f} mm" if ac["value"] is None else
          f"{1e3 * ac['value']:.1f} mm ({ac['pair']})")
         + f" (SceneGraph along the feed), limit {1e3 * ac['limit']:.1f} mm"),
        ("P(margin holds)", "not run" if p is None else
         f"{100 * p:.1f} % (clearance > 0 under registration error, sigma "
         f"{1e3 * reg['sigma_translation']:.2g} mm / {np.rad2deg(reg['sigma_rotation']):.2g} "
         f"deg, {reg['samples']} samples)"),
        ("expected accuracy", "not run" if acc is None else
         f"entry {1e3 * acc['entry']['mean']:.2f} / apex {1e3 * acc['apex']['mean']:.2f} mm / "
         f"angle {np.rad2deg(acc['angle']['mean']):.2f} deg mean (p95 "
         f"{1e3 * acc['entry']['p95']:.2f} / {1e3 * acc['apex']['p95']:.2f} mm / "
         f"{np.rad2deg(acc['angle']['p95']):.2f} deg) under registration error alone"),
        ("feed duration", "not simulated" if card["feed_duration"] is None else
         f"{card['feed_duration']:.1f} s (simulated feed)"),
        ("joint headroom", "not confirmed" if room is None else
         " ".join(f"J{j + 1} {np.rad2deg(r):.0f}" for j, r in enumerate(room))
         + f" deg (limit {np.rad2deg(card['joint_headroom_limit']):.0f})"),
        ("reach", ", ".join(f"{k.replace('_', ' ')}: {_word(v)}" for k, v in reach.items())),
    ]
    for a in card.get("anatomy") or ():
        value = "not measured" if a["value"] is None or not np.isfinite(a["value"]) else \
            f"{1e3 * a['value']:.2f} mm"
        lines.append((a["label"], f"{value} (>= {1e3 * a['limit']:.1f} mm): "
                      + ("pass" if a["pass"] else "FAIL")))
    return lines


def _word(value) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.2f}"
    return str(value)


def card_title(card: dict) -> str:
    """``tooth 36`` (FDI) or ``site NAME``."""
    return (f"tooth {card['tooth_fdi']} (FDI)" if card["tooth_fdi"] is not None
            else f"site {card['site']}")
