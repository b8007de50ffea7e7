"""Figures of a surgical case: the mouth opening and the instrument placements at its sites.

``python -m implantplan.analyses.case_figures [--case models/cases/default.yaml] [--out DIR]``
opens the case's mesh (:func:`systems.fpsm.oral_mesh.open_mouth`), fits the FPSM, places the
paper's tool
at each site (:func:`systems.placement.planner.place_instrument`) and writes

* ``opening.png``: side views (mesh x-z, mm) of the scanned and the opened mesh in the
  mid-sagittal plane and in the sites' sagittal planes, with the hinge and the occlusal plane;
* ``placements.png``: per site, a side view (Center Z-Y) in the plane X = the site's X and a top
  view (Center Z-X) at the Tool origin's height: mesh section, the FPSM's wall and its wall
  shrunk by the rod radius (Eq. 12), the implant axis, the Tool origin, line1 (rod) and line2
  (implant tip path), projected (the lines are not in these planes, so only the third panel
  shows their clearance: d_safe along each line up to the mouth opening);

and prints each placement's figures. The case is read and fitted as ``implantplan plan`` does
(analyses.case, analyses.pipeline).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from implantplan.analyses.case import default_case_path
from implantplan.analyses.figures.fpsm import plot_mouth_opening
from implantplan.analyses.figures.placement import plot_placements

MM = 1e-3


def build_case(case_path):
    """Load a case (analyses.case), open its mesh and fit the FPSM (analyses.pipeline.fit_stage),
    and place the tool at every site (valid or not: the figures show both).

    Returns:
        dict with ``case`` (:class:`analyses.case.Case`), ``scanned`` and ``opened`` meshes (m),
        ``X_WC``, ``fpsm``, ``placements`` (list of :class:`systems.placement.planner.Placement`),
        ``seconds`` (dict: fit, place = all sites with their grid checks).
    """
    import time

    from implantplan.analyses.case import load_case
    from implantplan.analyses.pipeline import fit_stage, placement_stage

    case = load_case(case_path)
    fit = fit_stage(case)
    t = time.perf_counter()
    placements = placement_stage(case, fit, require_valid=False)
    place_s = time.perf_counter() - t
    return {
        "case": case,
        "scanned": fit.scanned,
        "opened": fit.opened,
        "X_WC": fit.fpsm.X_WC,
        "fpsm": fit.fpsm,
        "placements": placements,
        "seconds": {"fit": fit.seconds, "place": place_s},
    }


def scan_sites(
    fpsm,
    *,
    rod_radius: float,
    implant_length: float,
    slices=None,
    angles_deg=tuple(range(-170, -9, 10)),
    lingual_tilts_deg=(0.0, 15.0, 30.0),
    mesial_tilts_deg=(0.0, 10.0, 20.0),
    grid=(41, 73),
    objective: str = "eq14",
    mesh=None,
    X_WC=None,
) -> list[dict]:
    """Rank candidate implant sites on the lower half of a fitted FPSM by their best placement.

    Candidates: the model's wall point at each slice in ``slices`` (default all but the end
    slices) and polar angle in ``angles_deg`` (Center, -90 = straight down), with the axis
    Center +Y tilted towards the mid-sagittal plane by each lingual tilt and then towards +Z
    (out of the mouth) by each mesial tilt. Each is scored by the exhaustive placement grid
    (:func:`systems.placement.planner.grid_search`, ``grid`` points over the default bounds), which
    is
    how the default case's sites were chosen. With the scan (``mesh`` and the Center pose
    ``X_WC`` in it) each candidate is then moved along -axis onto the tissue
    (:func:`systems.fpsm.sites.project_to_tissue`), where a site must lie; candidates whose axis
    meets no tissue are left out.

    Returns:
        dicts sorted by F (best first): slice, angle_deg, lingual/mesial tilt (deg), site (m),
        axis, F, f_safe_line1/2 (m), d_T (m), theta_T (rad), valid (both f_safe > 0).
    """
    from implantplan.systems.fpsm.sites import project_to_tissue
    from implantplan.systems.placement.planner import (
        PlacementProblem,
        default_bounds,
        grid_search,
        hole_frame,
    )

    js = range(1, fpsm.slices - 1) if slices is None else slices
    bounds = default_bounds(fpsm, implant_length)
    out = []
    for j in js:
        z = float(fpsm.slice_z[j])
        for phi_deg in angles_deg:
            phi = np.deg2rad(phi_deg)
            r = float(fpsm.radius_at(phi, z))
            site = np.array([r * np.cos(phi), r * np.sin(phi), z])
            lingual = np.array([-np.sign(site[0]), 0.0, 0.0])
            for t_in in lingual_tilts_deg:
                for t_z in mesial_tilts_deg:
                    a = np.cos(np.deg2rad(t_in)) * np.array([0.0, 1.0, 0.0])
                    a = a + np.sin(np.deg2rad(t_in)) * lingual
                    a = np.cos(np.deg2rad(t_z)) * a + np.sin(np.deg2rad(t_z)) * np.array(
                        [0.0, 0.0, 1.0]
                    )
                    if mesh is not None:
                        site = project_to_tissue(mesh, X_WC, site, a)[0]
                        if not np.all(np.isfinite(site)):
                            continue
                    problem = PlacementProblem(
                        fpsm, hole_frame(site, a), rod_radius, implant_length, objective
                    )
                    g = grid_search(problem, bounds[0], bounds[1], grid)
                    ev = problem.evaluate(g.x[None])
                    f1, f2 = float(ev.f_safe_line1[0]), float(ev.f_safe_line2[0])
                    out.append(
                        {
                            "slice": int(j),
                            "angle_deg": float(phi_deg),
                            "lingual_tilt_deg": float(t_in),
                            "mesial_tilt_deg": float(t_z),
                            "site": site,
                            "axis": a,
                            "F": g.best_F,
                            "f_safe_line1": f1,
                            "f_safe_line2": f2,
                            "d_T": float(g.x[0]),
                            "theta_T": float(g.x[1]),
                            "valid": f1 > 0 and f2 > 0,
                        }
                    )
    out.sort(key=lambda c: c["F"])
    return out


def case_figures(case_path, out_dir) -> dict:
    """Build the case (:func:`build_case`) and write ``opening.png`` and ``placements.png``."""
    out_dir = Path(out_dir)
    built = build_case(case_path)
    case = built["case"]
    sites_y = [float((built["X_WC"] @ np.r_[s.position, 1.0])[1]) for s in case.sites]
    opening = plot_mouth_opening(
        built["scanned"],
        built["opened"],
        out_dir / "opening.png",
        planes_y=(0.0, *sites_y),
        hinge_point=case.mesh.opening.get("hinge_point"),
        occlusal_point=case.mesh.opening.get("occlusal_point"),
        occlusal_normal=case.mesh.opening.get("occlusal_normal"),
    )
    placements = plot_placements(
        built["opened"],
        built["X_WC"],
        built["fpsm"],
        built["placements"],
        [s.name for s in case.sites],
        out_dir / "placements.png",
    )
    return {**built, "figures": [opening, placements]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", type=Path, default=default_case_path())
    parser.add_argument("--out", type=Path, default=Path("case_figures"))
    parser.add_argument(
        "--scan",
        action="store_true",
        help="also rank candidate sites on the lower-lateral wall (how the sites were chosen)",
    )
    args = parser.parse_args(argv)
    out = case_figures(args.case, args.out)
    info = out["opened"].metadata["implantplan"]["open_mouth"]
    print(
        f"opening {info['angle_deg']} deg: {info['moved_vertices']} vertices moved, "
        f"{info['inverted_faces']} inverted, {info['degenerate_faces']} degenerate faces"
    )
    s = out["seconds"]
    print(f"open + fit {s['fit']:.3f} s, placements with grid checks {s['place']:.3f} s")
    for site, pl in zip(out["case"].sites, out["placements"], strict=True):
        g = pl.grid
        print(
            f"site {site.name}: valid={pl.valid} d_T={pl.d_T / MM:.2f} mm "
            f"theta_T={np.rad2deg(pl.theta_T):.2f} deg f_safe1={pl.f_safe_line1 / MM:.3f} mm "
            f"f_safe2={pl.f_safe_line2 / MM:.3f} mm F_safe={pl.F_safe:.5f} sqrt(m) "
            f"PSO {pl.iterations} it {pl.seconds:.3f} s | grid "
            f"d_T={g['d_T'] / MM:.2f} mm theta_T={np.rad2deg(g['theta_T']):.2f} deg "
            f"F_pso-F_grid={g['F_pso_minus_grid']:.2e}"
        )
    for f in out["figures"]:
        print(f"wrote {f}")
    if args.scan:
        tool0 = out["case"].instrument_at(out["case"].sites[0])
        ranked = scan_sites(
            out["fpsm"], rod_radius=tool0.rod_radius, implant_length=tool0.implant_length,
            mesh=out["opened"], X_WC=out["X_WC"],
        )
        print(f"scan: {sum(c['valid'] for c in ranked)} of {len(ranked)} candidates valid")
        # the sides of the arch: lower-lateral quadrants, away from the throat and the lips
        for side, (lo, hi) in (("X < 0", (-165, -115)), ("X > 0", (-65, -15))):
            sel = [
                c
                for c in ranked
                if lo <= c["angle_deg"] <= hi and 6 <= c["slice"] <= 11 and c["valid"]
            ]
            print(f"best lateral candidates, {side} (slices 6-11): {len(sel)} valid")
            for c in sel[:5]:
                print(
                    f"  slice {c['slice']} angle {c['angle_deg']:.0f} deg lingual "
                    f"{c['lingual_tilt_deg']:.0f} mesial {c['mesial_tilt_deg']:.0f} site_mm "
                    f"{np.round(c['site'] / MM, 1).tolist()} F={c['F']:.4f} "
                    f"f1={c['f_safe_line1'] / MM:.2f} f2={c['f_safe_line2'] / MM:.2f} mm "
                    f"d_T={c['d_T'] / MM:.1f} mm"
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
