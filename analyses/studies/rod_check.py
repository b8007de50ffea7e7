"""Acceptance of the sound rod clearance against the exact mesh: random rods on the
real cavity and on transformed copies, the fast verdict against FCL.

Run: ``python -m implantplan.analyses.studies.rod_check [--rods 100000] [--seed 0] [--variants
all]``.
For each variant of the default case's opened cavity (``real``; ``rigid`` = a random rotation
and translation, saved and reloaded as STL; ``mirror`` = reflected in the mesh's y = 0 plane,
PLY; ``scale0.85`` STL and ``scale1.15`` PLY, the Center frame and the slice range moved with the
mesh) the FPSM is fitted as the case fits it, and ``--rods`` random capsules are drawn:

- radius uniform in 2-8 mm, direction uniform on the cap within 60 deg of the opening axis
  (Center +z), length uniform in 20-150 mm;
- start anywhere the FPSM calls free (uniform in the model's bounding cylinder, kept where
  d_safe > 0), half of them near the walls (0 < d_safe < 3 mm).

Each rod gets the sound clearance (:func:`systems.placement.tool_clearance.rod_clearance`, "safe" =
> 0),
Eq. 12 (``method="paper"``) and the exact clearance against the mesh with FCL
(:class:`systems.placement.exact_clearance.ExactCavity`). Printed per variant: rods called safe
whose exact
clearance is below -0.1 mm and below 0 (the false-safe counts, both must be 0), the worst exact
clearance among rods called safe, the share of exactly-free rods called unsafe, and the same for
Eq. 12; and the machine load. Same seed, same rods.

**Where the rejections come from** (``--no-breakdown`` skips it). The FPSM is a conservative
inner model of the cavity: a rod free in the mesh but crossing the FPSM's boundary is unsafe
for the FPSM by definition. Each rod also gets its exact clearance to the FPSM boundary (FCL
against :func:`systems.placement.tool_clearance.boundary_mesh`, the walls, throat disc and top
annulus
densely triangulated), and each exactly-free rod the bound calls unsafe is put in one class:
``throat`` (the capsule reaches below the bottom slice: the throat rule), ``fpsm`` (it crosses
the FPSM boundary elsewhere: the surrogate's coverage), ``slack`` (its FPSM clearance is > 0 but
the bound's is not: the clearance model's own share). Printed: the three counts and the share of
the rods free in both the mesh and the FPSM that the bound calls unsafe; the same reference
checks the bound itself (no rod certified above its exact FPSM clearance, 1 um of
triangulation allowed).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from implantplan.systems.fpsm.fit import fit_fpsm
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.fpsm.oral_mesh import load_oral_mesh
from implantplan.systems.placement.exact_clearance import ExactCavity
from implantplan.systems.placement.tool_clearance import boundary_mesh, rod_clearance

VARIANTS = ("real", "rigid", "mirror", "scale0.85", "scale1.15")
MM = 1e-3


@dataclass
class Variant:
    name: str
    mesh: trimesh.Trimesh  # mesh frame (m)
    fpsm: Fpsm
    exact: ExactCavity


def _fit(case, mesh: trimesh.Trimesh, X_WC: np.ndarray, scale: float) -> Fpsm:
    fp = case.fpsm
    z_range = None if fp.z_range is None else tuple(scale * z for z in fp.z_range)
    return fit_fpsm(
        mesh, X_WC, slices=fp.slices, control_points=fp.control_points, samples=fp.samples,
        z_range=z_range, method=fp.method, margin=fp.margin * scale,
        cap_radius=case.mesh.cap_radius, close_open_cuts=case.mesh.close_open_cuts,
    )


def _roundtrip(mesh: trimesh.Trimesh, suffix: str, folder: Path) -> trimesh.Trimesh:
    path = folder / f"cavity{suffix}"
    mesh.export(path)
    loaded = load_oral_mesh(path, units="m")
    # STL stores a triangle soup: weld the corners again, or every edge looks like an open cut
    loaded.merge_vertices()
    return loaded


def make_variants(names=VARIANTS, *, seed: int = 0) -> list[Variant]:
    """The default case's cavity and its transformed copies, each with its FPSM and FCL model."""
    from implantplan.analyses.case import default_case_path, load_case
    from implantplan.analyses.pipeline import fit_stage

    case = load_case(default_case_path())
    fit = fit_stage(case)
    base, X_WC = fit.opened, fit.fpsm.X_WC
    rng = np.random.default_rng(seed)
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for name in names:
            if name == "real":
                mesh, X, fpsm = base, X_WC, fit.fpsm
            elif name == "rigid":
                T = trimesh.transformations.random_rotation_matrix(rng.random(3))
                T[:3, 3] = rng.uniform(-0.2, 0.2, 3)
                mesh = _roundtrip(base.copy().apply_transform(T), ".stl", folder)
                X = T @ X_WC
                fpsm = _fit(case, mesh, X, 1.0)
            elif name == "mirror":
                M = np.diag([1.0, -1.0, 1.0, 1.0])
                mesh = _roundtrip(base.copy().apply_transform(M), ".ply", folder)
                X = M @ X_WC @ np.diag([-1.0, 1.0, 1.0, 1.0])  # keep Center right-handed
                fpsm = _fit(case, mesh, X, 1.0)
            elif name.startswith("scale"):
                s = float(name[5:])
                S = np.diag([s, s, s, 1.0])
                mesh = _roundtrip(base.copy().apply_transform(S), ".stl" if s < 1 else ".ply",
                                  folder)
                X = X_WC.copy()
                X[:3, 3] *= s
                fpsm = _fit(case, mesh, X, s)
            else:
                raise ValueError(f"unknown variant {name!r}; expected one of {VARIANTS}")
            out.append(Variant(name, mesh, fpsm, ExactCavity.from_scan(mesh, fpsm)))
    return out


def random_rods(fpsm: Fpsm, n: int, *, seed: int = 0, near_wall: float = 0.5):
    """``n`` random capsules (p0, p1, radius) as in the module notes; same seed, same rods."""
    rng = np.random.default_rng(seed)
    z_lo, z_hi = fpsm.z_range
    R = float(np.max(fpsm.rho))
    starts = []
    n_near = int(round(near_wall * n))
    have_near, have_any = 0, 0
    while have_near < n_near or have_any < n - n_near:
        m = 4 * n
        p = np.column_stack([rng.uniform(-R, R, m), rng.uniform(-R, R, m),
                             rng.uniform(z_lo, z_hi, m)])
        d = fpsm.d_safe(p)
        near = (d > 0) & (d < 3 * MM)
        anyf = d > 0
        take_near = p[near][: max(n_near - have_near, 0)]
        take_any = p[anyf & ~near][: max(n - n_near - have_any, 0)]
        have_near += len(take_near)
        have_any += len(take_any)
        starts += [take_near, take_any]
    p0 = np.concatenate(starts)[:n]
    p0 = p0[rng.permutation(n)]
    cos_max = np.cos(np.radians(60.0))
    cz = rng.uniform(cos_max, 1.0, n)  # uniform on the spherical cap
    phi = rng.uniform(0, 2 * np.pi, n)
    sz = np.sqrt(1 - cz * cz)
    u = np.column_stack([sz * np.cos(phi), sz * np.sin(phi), cz])
    length = rng.uniform(20 * MM, 150 * MM, n)
    radius = rng.uniform(2 * MM, 8 * MM, n)
    return p0, p0 + length[:, None] * u, radius


TRIANGULATION = 1e-6  # m: allowed between the bound and the triangulated FPSM boundary


def compare(variant: Variant, n: int, *, seed: int = 0, breakdown: bool = False) -> dict:
    """The fast verdicts against FCL on ``n`` rods of ``variant``; ``breakdown``: the classes
    of the module notes (against the FPSM boundary)."""
    p0, p1, r = random_rods(variant.fpsm, n, seed=seed)
    t = time.perf_counter()
    sound = rod_clearance(variant.fpsm, p0, p1, r)
    t_sound = time.perf_counter() - t
    paper = rod_clearance(variant.fpsm, p0, p1, r, method="paper")
    t = time.perf_counter()
    exact = variant.exact.capsule_clearance(p0, p1, r)
    t_exact = time.perf_counter() - t
    free = exact > 0
    # the FPSM's throat rule: a capsule reaching below the bottom slice is a collision there,
    # whatever the scan says beyond it (DESIGN.md section 4)
    throat = np.minimum(p0[:, 2], p1[:, 2]) - r < variant.fpsm.z_range[0]
    out = {"variant": variant.name, "rods": n, "exactly_free": int(free.sum()),
           "exactly_free_above_throat": int((free & ~throat).sum())}
    for name, c in (("sound", sound), ("paper", paper)):
        safe = c > 0
        out[name] = {
            "called_safe": int(safe.sum()),
            "false_safe_below_0.1mm": int(np.sum(safe & (exact < -0.1 * MM))),
            "false_safe_below_0": int(np.sum(safe & (exact < 0))),
            "worst_exact_of_safe_mm": float(exact[safe].min() / MM) if safe.any() else None,
            "free_called_unsafe_share": float(np.mean(~safe[free])) if free.any() else 0.0,
            "free_above_throat_called_unsafe_share": (
                float(np.mean(~safe[free & ~throat])) if (free & ~throat).any() else 0.0
            ),
        }
    out["seconds"] = {"sound": t_sound, "exact_fcl": t_exact}
    if breakdown:
        fp = ExactCavity(boundary_mesh(variant.fpsm)).capsule_clearance(p0, p1, r)
        rejected = free & ~(sound > 0)
        both = free & (fp > 0)
        out["breakdown"] = {
            "rejected": int(rejected.sum()),
            "throat": int(np.sum(rejected & throat)),
            "fpsm": int(np.sum(rejected & ~throat & (fp <= 0))),
            "slack": int(np.sum(rejected & ~throat & (fp > 0))),
            "free_in_both": int(both.sum()),
            "free_in_both_called_unsafe_share": (
                float(np.mean(sound[both] <= 0)) if both.any() else 0.0
            ),
            "bound_above_fpsm_exact": int(np.sum((sound > 0) & (sound > fp + TRIANGULATION))),
        }
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="rod_check", description=__doc__.split("\n")[0])
    parser.add_argument("--rods", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--variants", default="all", help="comma-separated, or 'all'")
    parser.add_argument("--no-breakdown", action="store_true",
                        help="skip the classes of the rejected rods (FCL against the FPSM)")
    args = parser.parse_args(argv)
    names = VARIANTS if args.variants == "all" else tuple(args.variants.split(","))
    print(f"load average {os.getloadavg()}")
    for v in make_variants(names, seed=args.seed):
        res = compare(v, args.rods, seed=args.seed, breakdown=not args.no_breakdown)
        s, p = res["sound"], res["paper"]
        print(
            f"{res['variant']:>10}: {res['rods']} rods, {res['exactly_free']} exactly free | "
            f"sound: safe {s['called_safe']}, false-safe <-0.1 mm {s['false_safe_below_0.1mm']}"
            f", <0 {s['false_safe_below_0']}, worst {s['worst_exact_of_safe_mm']} mm, "
            f"free called unsafe {100 * s['free_called_unsafe_share']:.1f} % "
            f"({100 * s['free_above_throat_called_unsafe_share']:.1f} % of those not reaching "
            f"below the bottom slice) | "
            f"Eq. 12: false-safe <-0.1 mm {p['false_safe_below_0.1mm']}, <0 "
            f"{p['false_safe_below_0']}, worst {p['worst_exact_of_safe_mm']} mm, free called "
            f"unsafe {100 * p['free_called_unsafe_share']:.1f} % | "
            f"sound {res['seconds']['sound']:.2f}"
            f" s, FCL {res['seconds']['exact_fcl']:.2f} s"
        )
        if "breakdown" in res:
            b = res["breakdown"]
            print(
                f"{'':>10}  free called unsafe: {b['rejected']} = throat {b['throat']} + crosses "
                f"the FPSM {b['fpsm']} + bound slack {b['slack']}; of the {b['free_in_both']} "
                f"rods free in the mesh and the FPSM, "
                f"{100 * b['free_in_both_called_unsafe_share']:.1f} % called unsafe; bound above "
                f"its exact FPSM clearance: {b['bound_above_fpsm_exact']}"
            )
    print(f"load average {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
