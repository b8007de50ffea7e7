"""Figures of stage 3 (MOPRP, seed 001): the Pareto set in design and objective space, the
selected layout before/after the feed (arm capsules, cart, patient, chair) and its Meshcat
static HTML.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from implantplan.analyses.figures import save
from implantplan.systems.robot import moprp


def plot_placement(sc: moprp.Scenario, out: dict, out_dir: Path, *, html: bool = True
                   ) -> list[Path]:
    """Pareto front in design and objective space, and the selected layout before/after feed
    (PNGs; and the Meshcat static HTML of the layout when ``html``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    P = np.array([e["base_xyz"] for e in out["pareto"]])
    F = np.array([[e["indices"][n] for n in moprp.INDEX_NAMES] for e in out["pareto"]])
    s = out["selected"]
    ps = np.asarray(s["base_xyz"])
    fs = np.array([s["indices"][n] for n in moprp.INDEX_NAMES])

    fig = plt.figure(figsize=(6.5, 5.5))
    ax = fig.add_subplot(projection="3d")
    sc_ = ax.scatter(*(1000 * P.T), c=F[:, 0], cmap="viridis", s=8)
    ax.scatter(*(1000 * ps), c="red", s=60, marker="*", label="selected")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.set_title(f"{sc.name}: Pareto set in design space (base in Oral)")
    fig.colorbar(sc_, ax=ax, shrink=0.6, label="dexterity I_d")
    ax.legend()
    paths.append(out_dir / "pareto_design.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fig = plt.figure(figsize=(6.5, 5.5))
    ax = fig.add_subplot(projection="3d")
    ax.scatter(F[:, 0], 1000 * F[:, 1], np.degrees(F[:, 2]), s=8, c="tab:blue")
    ax.scatter(fs[0], 1000 * fs[1], np.degrees(fs[2]), c="red", s=60, marker="*",
               label="selected")
    ax.set_xlabel("dexterity I_d")
    ax.set_ylabel("error range I_e (mm)")
    ax.set_zlabel("joint variation I_j (deg)")
    ax.set_title(f"{sc.name}: Pareto front in objective space")
    ax.legend()
    paths.append(out_dir / "pareto_objectives.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    for label, key in (("before", "q_pre"), ("after", "q")):
        paths.append(_plot_layout(sc, ps, np.asarray(s[key]), out_dir / f"layout_{label}.png",
                                  f"{sc.name}: selected layout {label} feeding"))
    if html:
        paths.append(write_layout_html(sc, ps, int(s["branch"]), out_dir / "layout.html"))
    return paths


def write_layout_html(sc: moprp.Scenario, xyz, branch: int, path: Path) -> Path:
    """Meshcat static HTML of the selected layout: the Drake plant of the scenario (arm +
    actuator at the base pose, the scenario's cart, patient and chair from
    diagrams.plant.add_scenario_geometry), and the feed animated from the pre-feed pose (t = 0)
    to the target (t = 1 s) on the selected branch. Headless Meshcat on an ephemeral port."""
    from pydrake.geometry import Meshcat, MeshcatParams

    from implantplan.diagrams.plant import build_plant
    from implantplan.systems.files import write_text_atomic
    from implantplan.systems.robot import kinematics as kin

    meshcat = Meshcat(MeshcatParams(port=0))
    X_WB = sc.X_WO @ moprp.base_pose(xyz)
    diagram, plant, _, handles = build_plant(scenario=sc, tool=True, X_WBase=X_WB,
                                             limits=sc.limits, meshcat=meshcat)
    feed = moprp.feed_poses(xyz, sc.feed_length, sc.feed_samples)
    record_feed(diagram, plant, handles, kin.ik(feed, limits=sc.limits, X_FT=sc.X_FT).q[:, branch])
    write_text_atomic(path, meshcat.StaticHtml())
    return Path(path)


def record_feed(diagram, plant, handles, q_path) -> None:
    """Record the arm through the configurations ``q_path`` (one per sample, t from 0 to 1 s) in
    the Meshcat of the plant's visualizer, and publish the recording (an animation)."""
    context = diagram.CreateDefaultContext()
    pc = plant.GetMyMutableContextFromRoot(context)
    vis = handles.visualizer
    vis.StartRecording(set_transforms_while_recording=False)
    for k, q in enumerate(q_path):
        context.SetTime(k / (len(q_path) - 1))
        plant.SetPositions(pc, handles.arm, q)
        diagram.ForcedPublish(context)
    vis.StopRecording()
    vis.PublishRecording()


def _plot_layout(sc, xyz, q, path, title) -> Path:
    import matplotlib.pyplot as plt

    from implantplan.systems.robot import arm_collision

    model = moprp.collision_model(sc)
    X_WB = sc.X_WO @ moprp.base_pose(xyz)
    arm = [(shape, X_WB @ X) for shape, X in model.posed_shapes(q)
           if shape.body not in (arm_collision.PATIENT_SCOPE, arm_collision.CART_SCOPE)]
    # the arm's capsules and cylinders as thick segments along their axes, its boxes as boxes
    seg = np.array([[X[:3, 3] - X[:3, 2] * sh.size[1] / 2, X[:3, 3] + X[:3, 2] * sh.size[1] / 2]
                    for sh, X in arm if sh.kind in ("capsule", "cylinder")])
    rad = np.array([sh.size[0] for sh, _ in arm if sh.kind in ("capsule", "cylinder")])
    corners = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    boxes = [(X_WB @ sc.X_BC, sc.cabinet_half, "tab:gray")]
    boxes += [(X, np.asarray(sh.size) / 2, "tab:blue") for sh, X in arm if sh.kind == "box"]
    boxes += [(o.X_WB, o.half_size, "tan") for o in sc.obstacles if o.kind == "box"]
    caps = [(np.array([o.p0, o.p1]), o.radius) for o in sc.obstacles if o.kind == "capsule"]
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8)
             if np.sum(corners[a] != corners[b]) == 1]
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.6))
    views = ((0, 1, "top (World x-y)"), (0, 2, "front (World x-z)"), (1, 2, "side (World y-z)"))
    for ax, (i, j, name) in zip(axes, views, strict=True):
        for X, half, color in boxes:
            pts = (corners * half) @ X[:3, :3].T + X[:3, 3]
            pts[:, 2] = np.maximum(pts[:, 2], 0.0)  # drawn down to the floor only
            for a, b in edges:
                ax.plot(pts[[a, b], i], pts[[a, b], j], color=color, lw=1)
        # capsules at their real size: the projection of a capsule is the segment's projection
        # grown by its radius (a stadium; a disc when seen end-on)
        for c, r in caps:
            _fill_capsule(ax, c[:, [i, j]], r, "peachpuff", 0.8)
        for k in range(seg.shape[0]):
            _fill_capsule(ax, seg[k][:, [i, j]], rad[k], "tab:blue", 0.45)
        o = sc.X_WO[:3, 3]
        ax.plot(o[i], o[j], "r+", ms=12, mew=2)
        ax.set_aspect("equal")
        ax.autoscale_view()
        ax.set_title(name)
        ax.set_xlabel("xyz"[i] + " (m)")
        ax.set_ylabel("xyz"[j] + " (m)")
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [Patch(color="tab:blue", alpha=0.45, label="arm (collision model)"),
               Patch(color="peachpuff", label="patient"),
               Line2D([], [], color="tan", label="chair"),
               Line2D([], [], color="tab:gray", label="cart"),
               Line2D([], [], color="r", marker="+", linestyle="none", ms=10, mew=2,
                      label="feeding target (Oral)")]
    fig.legend(handles=handles, loc="lower center", ncol=5, fontsize=8)
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    path = save(fig, path, dpi=100, tight=False)
    return Path(path)


def _fill_capsule(ax, ends_2d: np.ndarray, radius: float, color, alpha: float) -> None:
    """Fill the projection of a capsule (its 2D segment grown by the radius)."""
    from shapely.geometry import LineString, Point

    a, b = np.asarray(ends_2d, dtype=float)
    shape = Point(a) if np.allclose(a, b) else LineString([a, b])
    outline = np.asarray(shape.buffer(float(radius), quad_segs=16).exterior.coords)
    ax.fill(outline[:, 0], outline[:, 1], color=color, alpha=alpha, lw=0)
