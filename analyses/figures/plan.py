"""Every figure of a case plan (``implantplan plan``/``demo``), by report section.
"""

from __future__ import annotations

from pathlib import Path

from implantplan.analyses.figures.capability import plot_target_neighbourhoods
from implantplan.analyses.figures.fpsm import plot_fit, plot_mouth_opening
from implantplan.analyses.figures.placement import plot_placement
from implantplan.analyses.figures.robot import plot_placement as plot_robot
from implantplan.analyses.figures.robot import write_layout_html
from implantplan.analyses.figures.scene import write_site_scene
from implantplan.analyses.figures.simulation import plot_feeding
from implantplan.systems.robot import moprp


def make_figures(case, fit, placements, robot, cap, sims, fig_dir: Path, *, html_scene: bool,
                 out: Path) -> dict:
    """Every figure of the report, by section; paths relative to the output folder."""

    def rel(paths):
        return [str(Path(p).relative_to(out)) for p in paths]

    figs = {}
    fpsm_dir = fig_dir / "fpsm"
    figs["fpsm"] = rel(plot_fit(fit.fpsm, fit.opened, fpsm_dir))
    if case.mesh.mouth_opening_deg > 0:
        o = case.mesh.opening
        figs["fpsm"] = rel([plot_mouth_opening(
            fit.scanned, fit.opened, fpsm_dir / "mouth_opening.png",
            planes_y=(0.0,), hinge_point=o["hinge_point"], occlusal_point=o["occlusal_point"],
            occlusal_normal=o["occlusal_normal"])]) + figs["fpsm"]
    figs["sites"] = {}
    for site, p in zip(case.sites, placements, strict=True):
        figs["sites"][site.name] = rel(plot_placement(fit.fpsm, p, fig_dir / f"site_{site.name}",
                                                      placed_length=site.placed_length))
    sel = {"base_xyz": robot.base_xyz, "branch": int(robot.branch[0]), "q": robot.q[0],
           "q_pre": robot.q_pre[0],
           "indices": dict(zip(moprp.INDEX_NAMES, robot.indices.tolist(), strict=True))}
    out_robot = {"pareto": [{"base_xyz": x, "indices": dict(zip(moprp.INDEX_NAMES, f.tolist(),
                                                                strict=True))}
                            for x, f in zip(robot.pareto_xyz, robot.pareto_F, strict=True)],
                 "selected": sel}
    figs["robot"] = rel(plot_robot(robot.scenario, out_robot, fig_dir / "robot", html=False))
    if html_scene:
        scene = write_layout_html(robot.scenario, robot.base_xyz, int(robot.branch[0]),
                                  out / "layout.html")
        figs["scene"] = str(Path(scene).relative_to(out))
        figs["site_scenes"] = {
            site.name: str(write_site_scene(out / f"scene_{site.name}.html", fit=fit,
                                            placement=p, robot=robot, site_index=k
                                            ).relative_to(out))
            for k, (site, p) in enumerate(zip(case.sites, placements, strict=True))}
    cap_png = fig_dir / "capability" / "target_neighbourhoods.png"
    cap_png.parent.mkdir(parents=True, exist_ok=True)
    plot_target_neighbourhoods(cap.cmap, cap.X_BA, [s.name for s in case.sites], cap_png)
    figs["capability"] = rel([cap_png])
    figs["simulation"] = {}
    for s in sims:
        d = fig_dir / f"sim_{s['site']}"
        d.mkdir(parents=True, exist_ok=True)
        figs["simulation"][s["site"]] = rel([plot_feeding(s, d)])
    return figs
