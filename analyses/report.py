"""``report.html``: one self-contained page per plan (the figures are files beside it).

It opens with the surgeon's cards (analyses.cards: one per implant, the plan in words). Sections
then follow the pipeline: checks first (pass/fail with margins), then the FPSM, each site's
placement and virtual fixture, the robot base, the capability check, the feeding simulations and
the 3D scene (the Meshcat static HTML of the layout in an iframe). Tables show mm and degrees;
the plan itself stays in SI units.
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from implantplan.systems.files import write_text_atomic

_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
h1 { margin-bottom: 0.2em; } h2 { border-bottom: 1px solid #ccc; padding-bottom: 0.2em; }
table { border-collapse: collapse; margin: 0.6em 0 1.2em; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: right; }
th { background: #f3f3f3; } td.l, th.l { text-align: left; }
.pass { color: #126b12; font-weight: 600; } .fail { color: #b00020; font-weight: 600; }
.figs img { max-width: 100%; border: 1px solid #ddd; margin: 4px 0; }
iframe { width: 100%; height: 560px; border: 1px solid #ccc; }
.muted { color: #666; font-size: 0.9em; }
.cards { display: flex; flex-wrap: wrap; gap: 12px; }
.card { flex: 1 1 480px; border: 1px solid #bbb; border-radius: 6px; padding: 6px 10px;
        font-size: 0.86em; }
.card h2 { margin: 0.1em 0; font-size: 1.25em; border: 0; }
.card table { margin: 0.3em 0; width: 100%; font-size: 1em; }
.card th { width: 9.5em; } .card td, .card th { padding: 2px 5px; }
.card .next { margin: 0.2em 0; font-weight: 600; }
.v-ready .verdict { color: #126b12; } .v-tight .verdict { color: #a65f00; }
.v-refused .verdict { color: #b00020; }
.print-only { display: none; }
@media print {
  body { margin: 0; max-width: none; font-size: 10pt; }
  iframe, select, .screen-only { display: none; }
  .print-only { display: block; }
  h2, h3 { break-after: avoid; } tr, .figs img { break-inside: avoid; }
  .figs img { max-height: 24cm; }
}
"""


def _fmt(value, unit: str) -> str:
    """A value in the unit people read: m -> mm, rad -> deg."""
    if unit == "m":
        return f"{value * 1e3:.3f} mm"
    if unit == "rad":
        return f"{np.degrees(value):.3f} deg"
    if unit in ("runs", "branches"):
        return f"{value:g}"
    return f"{value:.3f}"


class Markup(str):
    """Markup this module wrote itself (a pass/fail badge): the one cell kind not escaped."""


def table_cell(value) -> str:
    """A table cell's HTML: every value is escaped (html.escape) unless it is :class:`Markup`,
    so a site or case name from the user's YAML cannot inject markup into the page."""
    return value if isinstance(value, Markup) else html.escape(str(value))


def _badge(passed: bool) -> Markup:
    return Markup(f"<span class='{'pass' if passed else 'fail'}'>"
                  f"{'pass' if passed else 'FAIL'}</span>")


def _table(header: list[str], rows: list[list], left: int = 1) -> str:
    th = "".join(f"<th class='{'l' if i < left else ''}'>{html.escape(h)}</th>"
                 for i, h in enumerate(header))
    body = []
    for r in rows:
        cells = "".join(f"<td class='{'l' if i < left else ''}'>{table_cell(c)}</td>"
                        for i, c in enumerate(r))
        body.append(f"<tr>{cells}</tr>")
    return f"<table><tr>{th}</tr>{''.join(body)}</table>"


def _figs(paths) -> str:
    return "<div class='figs'>" + "".join(
        f"<img src='{html.escape(p)}' alt='{html.escape(Path(p).stem)}'>" for p in paths
    ) + "</div>"


def render(plan: dict, figs: dict) -> str:
    ok = plan["passed"]
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
        "<link rel='icon' href='data:,'>",
        f"<title>implantplan: {html.escape(plan['case']['name'])}</title>",
        f"<style>{_CSS}</style></head><body>",
        f"<h1>Implant plan: {html.escape(plan['case']['name'])}</h1>",
        f"<p class='muted'>case {html.escape(plan['case']['source'])}, seed "
        f"{html.escape(str(plan['case']['seed']))}; all checks: "
        f"<span class='{'pass' if ok else 'fail'}'>{'PASS' if ok else 'FAIL'}</span></p>",
        *[f"<p class='fail'>Accepted by the user ({html.escape(a['flag'])}): "
          f"{html.escape(a['what'])}</p>" for a in plan.get("acknowledged", [])],
        *_cards(plan.get("cards") or []),
        "<h2>Checks</h2>",
        _table(["check", "id", "site", "value", "limit", "bound", "margin", "result"], [
            [c["name"] + (f" ({c['pair']})" if c.get("pair") else ""), c.get("id", ""),
             c["site"] or "", _fmt(c["value"], c["unit"]), _fmt(c["limit"], c["unit"]),
             {"max": "max (value <= limit)", "min": "min (value > limit)"}.get(
                 c.get("bound"), ""),
             _fmt(c["margin"], c["unit"]), _badge(c["pass"])]
            for c in plan["checks"]], left=3),
    ]

    parts += _safety_spec(plan.get("safety"))

    f = plan["fpsm"]
    parts += [
        "<h2>1. Surrogate of the oral cavity (FPSM)</h2>",
        _table(["slices", "control points", "z range (mm)", "method", "mean coverage",
                "dense-check penetration", "max depth", "mouth opening"], [[
                    f["slices"], f["control_points"],
                    f"{f['z_range'][0] * 1e3:.1f} .. {f['z_range'][1] * 1e3:.1f}", f["method"],
                    f"{100 * f['coverage_mean']:.1f} %",
                    "" if f["dense_penetration_rate"] is None
                    else f"{100 * f['dense_penetration_rate']:.3f} %",
                    f"{f['dense_max_depth'] * 1e3:.3f} mm", f"{f['mouth_opening_deg']:g} deg"]],
               left=0),
        _figs(figs.get("fpsm", [])),
    ]

    parts.append("<h2>2. Instrument placement and virtual fixture per site</h2>")
    rows = []
    for s in plan["sites"]:
        p = s["placement"]
        grid = p.get("grid_check") or {}
        gx = grid.get("x")
        rows.append([
            s["name"], f"{p['d_T'] * 1e3:.2f}", f"{np.degrees(p['theta_T']):.2f}",
            f"{p['f_safe_line1'] * 1e3:.2f}", f"{p['f_safe_line2'] * 1e3:.2f}",
            f"{p['d_safe_min_line1'] * 1e3:.2f}", f"{p['d_safe_min_line2'] * 1e3:.2f}",
            f"{p['F_safe']:.5f}",
            "" if gx is None else f"{gx[0] * 1e3:.2f} / {np.degrees(gx[1]):.2f}",
            p["iterations"], "valid" if p["valid"] else "INVALID"])
    parts.append(_table(["site", "d_T (mm)", "theta_T (deg)", "f_safe line1 (mm)",
                         "f_safe line2 (mm)", "min d_safe line1 (mm)", "min d_safe line2 (mm)",
                         "F_safe", "grid optimum d_T/theta_T", "PSO iterations", ""], rows))
    rows = []
    for s in plan["sites"]:
        ver = s["placement"].get("verification") or {}
        reg = s.get("registration") or {}
        if not ver:
            continue
        exact = ver.get("clearance_exact_min")
        rows.append([
            s["name"], f"{ver['clearance_certified'] * 1e3:.3f}",
            "" if exact is None else f"{exact * 1e3:.3f}",
            f"{ver['clearance_margin'] * 1e3:.2f}",
            f"{ver['lateral_tolerance'] * 1e3:.2f} / {np.degrees(ver['angle_tolerance']):.2f}",
            "" if not reg else f"{reg['samples']}",
            "" if not reg else (f"{reg['sigma_translation'] * 1e3:.2f} / "
                                f"{np.degrees(reg['sigma_rotation']):.2f}"),
            "" if not reg else f"{100 * reg['probability_clear']:.1f} %",
            "" if not reg else f"{reg['clearance_p01'] * 1e3:.3f}"])
    if rows:
        parts.append("<h3>Tool clearance: verified region and registration error</h3>")
        parts.append("<p class='muted'>Certified: a lower bound on the FPSM over the whole feed "
                     "and the fixture's admissible region (lateral offset and angle); exact: FCL "
                     "against the scan at sampled poses of that region; the Monte Carlo moves "
                     "the Center frame by the registration error and takes the exact clearance "
                     "along the feed.</p>")
        parts.append(_table(["site", "certified (mm)", "exact (mm)", "margin (mm)",
                             "lateral (mm) / angle (deg)", "MC samples",
                             "sigma (mm / deg)", "P(clearance > 0)", "1st percentile (mm)"],
                            rows))
    for s in plan["sites"]:
        parts.append(f"<h3>Site {html.escape(s['name'])}</h3>")
        parts.append(_figs(figs.get("sites", {}).get(s["name"], [])))

    b = plan["base"]
    parts += [
        "<h2>3. Robot base (MOPRP, all sites from one base)</h2>",
        _table(["base in Oral (mm)", "dexterity", "error range (mm)", "joint variation (deg)",
                "percentiles (dex / err / joint)", "Pareto size", "generations",
                "evaluations"], [[
                    " ".join(f"{v * 1e3:.0f}" for v in b["xyz_in_oral"]),
                    f"{b['indices_worst_over_sites']['dexterity']:.3f}",
                    f"{b['indices_worst_over_sites']['error_range'] * 1e3:.3f}",
                    f"{np.degrees(b['indices_worst_over_sites']['joint_variation']):.2f}",
                    " / ".join(f"{v:.1f} %" for v in b["percentiles"].values()),
                    len(b["pareto"]), b["generations"], b["evaluations"]]], left=0),
        _table(["site", "IK branch", "q at target (deg)", "q pre-feed (deg)"], [
            [s["name"], s["ik"]["branch"], " ".join(f"{np.degrees(v):.1f}" for v in s["ik"]["q"]),
             " ".join(f"{np.degrees(v):.1f}" for v in s["ik"]["q_pre"])]
            for s in plan["sites"]]),
        _figs(figs.get("robot", [])),
    ]

    parts += [
        "<h2>4. Capability check from the chosen base</h2>",
        _table(["site", "reachable (how it is known)", "voxel index (seed 004)",
                "mean index around the target", "IK branches within limits"], [
            [s["name"], ("yes" if s["capability"]["map_reachable"] else "no")
             + (f" ({s['capability']['map_answer']})" if "map_answer" in s["capability"] else ""),
             f"{s['capability']['voxel_index']:.2f}",
             f"{s['capability']['neighbourhood_index']:.2f}",
             s["capability"]["ik_branches_within_limits"]] for s in plan["sites"]]),
        _figs(figs.get("capability", [])),
    ]

    parts.append("<h2>5. Teleoperated feeding (Drake diagram)</h2>")
    rows = []
    for s in plan["sites"]:
        sim = s["simulation"]
        for i, r in enumerate((sim or {}).get("runs", [])):
            rows.append([s["name"], i, f"{r['joint_travel']:.3f}",
                         f"{r['min_d_safe'] * 1e3:.2f}", f"{r['max_vf_violation'] * 1e3:.3f}",
                         "yes" if r["collision_alarm"] else "no",
                         f"{r['final_error'] * 1e3:.3f}", f"{r['sim_seconds']:.2f}",
                         f"{r['wall_seconds']:.2f}"])
    parts.append(_table(["site", "run", "joint travel (rad)", "min d_safe (mm)",
                         "max VF violation (mm)", "alarm", "final error (mm)", "sim (s)",
                         "wall (s)"], rows, left=1) if rows else "<p>No feeding runs.</p>")
    for site, paths in figs.get("simulation", {}).items():
        parts.append(f"<h3>Site {html.escape(site)}</h3>" + _figs(paths))

    scenes = figs.get("site_scenes") or {}
    if scenes:
        first = next(iter(scenes.values()))
        options = "".join(f"<option value='{html.escape(src)}'>site {html.escape(name)}</option>"
                          for name, src in scenes.items())
        parts += ["<h2>3D scene of each site</h2>",
                  "<p class='muted'>The opened scan (pink, see-through), the FPSM slices (blue),"
                  " the site and the implant path (red), the feeding target's axes, the virtual "
                  "fixture (green), the rod (grey) and the arm with its actuator, fed from the "
                  "pre-feed pose (t = 0) to the target (t = 1 s; play it from the Controls' "
                  "Animation folder). <label>Site: <select id='site-scene' onchange="
                  "\"document.getElementById('site-frame').src = this.value\">"
                  f"{options}</select></label> <a href='{html.escape(first)}'>Open full page</a>"
                  ".</p>",
                  f"<iframe id='site-frame' src='{html.escape(first)}' title='site scene'>"
                  "</iframe>",
                  "<p class='print-only'>The 3D scenes are interactive: open "
                  + ", ".join(html.escape(src) for src in scenes.values())
                  + " beside this report.</p>"]
    if figs.get("scene"):
        parts += ["<h2>3D scene of the layout</h2>",
                  "<p class='muted'>Meshcat recording of the selected layout: the feed of the "
                  "first site from the pre-feed pose (t = 0) to the target (t = 1 s). "
                  f"<a href='{html.escape(figs['scene'])}'>Open full page</a>.</p>",
                  f"<iframe id='layout-frame' src='{html.escape(figs['scene'])}' "
                  "title='3D scene'></iframe>"]
    parts += _provenance(plan.get("provenance"))
    parts.append("</body></html>")
    return "\n".join(parts)


def _cards(cards: list[dict]) -> list[str]:
    """The surgeon's cards (analyses.cards), one per implant, side by side on the first screen."""
    from implantplan.analyses.cards import card_lines, card_title

    if not cards:
        return []
    out = ["<div class='cards'>"]
    for c in cards:
        rows = "".join(f"<tr><th class='l'>{html.escape(k)}</th><td class='l'>{html.escape(v)}"
                       "</td></tr>" for k, v in card_lines(c))
        out.append(
            f"<section class='card v-{html.escape(c['verdict'])}' "
            f"data-site='{html.escape(c['site'])}'>"
            f"<h2>{html.escape(card_title(c))}: <span class='verdict'>"
            f"{html.escape(c['verdict'])}</span></h2>"
            f"<p class='next'>{html.escape(c['next_step'])}</p><table>{rows}</table></section>")
    out.append("</div>")
    return out


def _safety_spec(spec: dict | None) -> list[str]:
    """The safety spec the plan verified and the feeding diagram executes (plan.json
    ``safety``), in the case file's units."""
    if not spec:
        return []
    cl = spec["command_limits"]
    rows = [
        ["clearance margin (every clearance check)", f"{spec['clearance_margin'] * 1e3:g} mm"],
        ["fixture: lateral / angle tolerance (verified whole)",
         f"{spec['lateral_tolerance'] * 1e3:g} mm / {np.rad2deg(spec['angle_tolerance']):.3g} deg"],
        ["registration Monte Carlo: sigma, samples",
         f"{spec['registration_sigma_translation'] * 1e3:g} mm, "
         f"{np.rad2deg(spec['registration_sigma_rotation']):.3g} deg, "
         f"{spec['registration_samples']}"],
        ["estimator alarm margin", f"{spec['alarm_margin'] * 1e3:g} mm"],
        ["supervisor barrier rate", f"{spec['barrier_rate']:g} /s"],
        ["command limits: speed, turn rate",
         f"{cl['linear_speed'] * 1e3:g} mm/s, {np.rad2deg(cl['angular_speed']):.3g} deg/s"],
        ["command faults: jump, turn per period; clears after",
         f"{cl['fault_jump'] * 1e3:g} mm, {np.rad2deg(cl['fault_turn']):.3g} deg; "
         f"{cl['clear_after']:g} s"],
    ]
    return ["<h2>Safety spec (verified by the plan, executed by the feeding diagram)</h2>",
            _table(["setting", "value"], rows)]


def _provenance(block: dict | None) -> list[str]:
    """The provenance table: software, inputs with their sha256, command, time, seed."""
    if not block:
        return []
    git = block.get("git") or {}
    rows = [["implantplan", block["software"].get("implantplan", "")]]
    if git:
        rows.append(["git commit", git["commit"] + (" (uncommitted changes)" if git["dirty"]
                                                     else "")])
    rows += [[name, v] for name, v in block["software"].items() if name != "implantplan"]
    rows += [["command", " ".join(block["command"])], ["UTC time", block["utc"]],
             ["platform", block.get("platform", "")], ["seed", block["seed"]]]
    inputs = block["inputs"]
    files = ([["case", inputs["case"]["path"], inputs["case"]["sha256"]]] if "case" in inputs
             else []) + [["mesh", m["path"], m["sha256"]] for m in inputs["meshes"]]
    return ["<h2>Provenance</h2>", _table(["what", "value"], rows),
            _table(["input", "file", "sha256"], files, left=3)]


def write_report(path: Path, plan: dict, figs: dict) -> Path:
    from implantplan.systems.files import to_jsonable

    return write_text_atomic(path, render(to_jsonable(plan), figs))


def render_head_motion(study: dict, figs: dict) -> str:
    """``report.html`` of the awake-patient study (analyses.studies.head_motion): per site, the
    summary
    per profile (path deviation and time-indexed error following vs ignoring the head, exact
    clearance, completion, the startle's stop and back-out), lost tracking, and the figures
    (``figs``: {site: [PNG paths relative to the page]})."""
    sites = study["sites"] if "sites" in study else {"cylinder": study}
    trk = study.get("tracker", {})
    verdict = study.get("passed")
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
        "<link rel='icon' href='data:,'><title>implantplan: the awake patient</title>"
        f"<style>{_CSS}</style></head><body>",
        "<h1>The awake patient: head motion, tracking and following</h1>",
        f"<p class='muted'>case {html.escape(str(study.get('case', '')))}; runs per profile "
        f"{html.escape(str(next(iter(sites.values()))['runs']))}; seed "
        f"{html.escape(str(next(iter(sites.values()))['seed']))}; tracker "
        f"{html.escape(str(trk.get('rate', '')))} Hz, latency "
        f"{html.escape(str(1000 * trk.get('latency', float('nan'))))} ms, prediction over "
        f"{html.escape(str(trk.get('predict_samples', '')))} samples"
        + ("" if verdict is None else "; exact clearance never below 0: "
           + str(_badge(bool(verdict))))
        + "</p>",
    ]
    mm = 1000.0
    for name, res in sites.items():
        rows = []
        for prof, entry in res["profiles"].items():
            s = entry["summary"]
            stop = s.get("stop_after_onset_max_s")
            back = s.get("backed_out_after_onset_max_s")
            rows.append([
                prof, s["runs"],
                f"{mm * s['path_deviation_mean_following']:.2f} / "
                f"{mm * s['path_deviation_max_following']:.2f}",
                f"{mm * s['path_deviation_mean_ignoring']:.2f} / "
                f"{mm * s['path_deviation_max_ignoring']:.2f}",
                f"{mm * s['path_error_mean_following']:.2f} / "
                f"{mm * s['path_error_max_following']:.2f}",
                f"{mm * s['path_error_mean_ignoring']:.2f} / "
                f"{mm * s['path_error_max_ignoring']:.2f}",
                f"{mm * s['exact_clearance_min_following']:.2f}",
                s["runs_below_zero_following"], s["runs_below_margin_minus_0p2mm_following"],
                f"{s['reached_target_following']}/{s['runs']}",
                "" if stop is None else f"{stop:.3f}", "" if back is None else f"{back:.3f}"])
        title = str(name) if str(name).startswith("site") else f"Site {name}"
        parts += [f"<h2>{html.escape(title)}</h2>", _table(
            ["profile", "runs", "deviation following (mm, mean / max)",
             "deviation ignoring (mm)", "time-indexed error following (mm)",
             "time-indexed error ignoring (mm)", "min exact clearance following (mm)",
             "runs < 0", "runs < margin - 0.2 mm outside the event", "feeds completed",
             "stop after onset, max (s)", "backed out after onset, max (s)"], rows, left=1)]
        lt = res.get("lost_tracking")
        if lt:
            stop = lt.get("stop_after_dropout_s")
            parts.append(_table(
                ["lost tracking (1 s dropout mid-feed)", "stop after the dropout (s)",
                 "backed out (mm)", "min exact clearance (mm)"],
                [["breathing, run 0", "" if stop is None else f"{stop:.3f}",
                  f"{mm * lt.get('backed_out_m', 0.0):.1f}",
                  f"{mm * lt['exact_clearance_min']:.2f}"]], left=1))
        parts.append(_figs(figs.get(name, [])))
    parts.append("</body></html>")
    return "\n".join(parts)


def render_head_turn(study: dict, figs: list) -> str:
    """``report.html`` of the head-turn sweep (``analyze head-motion --turn-sweep``,
    analyses.studies.head_turn): the table per site x peak speed x direction, the pass rule,
    and the worst run's figure (``figs``: PNG paths relative to the page)."""
    res = study["turn_sweep"]
    s = res["summary"]
    mm = 1000.0
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
        "<link rel='icon' href='data:,'><title>implantplan: head turns</title>"
        f"<style>{_CSS}</style></head><body>",
        "<h1>The awake patient: head turns about the neck</h1>",
        f"<p class='muted'>{html.escape(str(s['runs']))} runs, seed "
        f"{html.escape(str(res['seed']))}; pass: exact clearance at the poses and over the swept "
        f"motion &ge; {mm * (res['margin'] - res['margin_slack']):.1f} mm (margin "
        f"{mm * res['margin']:.1f} mm - 0.2 mm), fixture violation &le; "
        f"{mm * res['max_violation']:.1f} mm and no TCP step above "
        f"{mm * res['step_limit']:.3f} mm per control step in the tracked head's frame (the "
        f"frame the command lives in; the true head's adds the camera's error): "
        f"{_badge(bool(study['passed']))}; differential IK reports {s['diffik_reports']} "
        f"({s['diffik_stuck']} stuck)</p>",
        _table(["site", "peak speed (deg/s)", "direction", "runs", "min exact at poses (mm)",
                "min exact between poses, certified (mm)",
                "max fixture violation, tracked head (mm)", "same, true head (mm)",
                "max TCP step, tracked head (mm)", "same, true head (mm)", "arm jumps",
                "DiffIK stuck", "guard stops", "backed out", "failed"],
               [[r["site"], f"{r['peak_speed_deg_s']:.0f}", f"{r['direction']:+.0f}",
                 r["runs"], f"{r['exact_mm']:.3f}", f"{r['between_mm']:.3f}",
                 f"{r['violation_mm']:.3f}", f"{r['violation_true_mm']:.3f}",
                 f"{r['step_mm']:.3f}", f"{r['step_true_mm']:.3f}", r["jumps"], r["stuck"],
                 r["stopped"], r["backed_out"], r["failed"]] for r in res["table"]], left=1),
        _figs(figs), "</body></html>"]
    return "\n".join(parts)
