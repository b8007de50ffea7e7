"""Cohorts of cases (DESIGN.md section 11): the cohort file, and a synthetic cohort made from one
case for studies and tests.

A **cohort file** (YAML, schema_version 1) lists case files::

    schema_version: 1
    name: molars
    cases: [case-00.yaml, case-01.yaml, ...]   # relative to the cohort file
    generated: {...}                             # optional: how make_cohort made them

A listed case that is missing or invalid is that case's failure (recorded by ``implantplan
batch``), not the cohort's: the others are still planned.

**Synthetic cohort** (:func:`make_cohort`): case i perturbs the anatomy of the source case by a
seeded similarity about the Center origin o (mesh frame, mm),

    x' = o + s R (x - o) + t,   s = 1 + scale_sd N(0, 1),  R = exp(angle [axis]_x),
    angle = rotation_deg N(0, 1), axis uniform,  t = shift_mm N(0, I3),

applied to the scan's vertices and to its landmarks (jaw hinge point and axis, occlusal point and
normal; the opening blend band scales by s). The Center frame itself (the planner's frame) stays
where the source case puts it, so the patient's anatomy sits slightly differently in it, as scans
of different patients do. Each site moves with the anatomy (position and axis, in Center) plus a
seeded jitter of ``site_jitter_mm`` N(0, I3) of its position, and then along its axis back onto
the (opened) scan's tissue, where the plan's site check wants it. Draws are truncated at 3 sigma, so
a cohort never holds a wild outlier. Same source, seed and settings: byte-identical files.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
import yaml

from implantplan.analyses.case import load_case
from implantplan.systems import validate as v
from implantplan.systems.errors import InputError
from implantplan.systems.files import SCHEMA_VERSION, read_yaml, write_atomic, write_text_atomic
from implantplan.systems.fpsm.oral_mesh import center_frame, load_oral_mesh, open_mouth
from implantplan.systems.fpsm.sites import project_to_tissue


def _case_files(value, where: str) -> tuple[str, ...]:
    if not isinstance(value, list) or not value or not all(isinstance(c, str) and c
                                                           for c in value):
        raise InputError(where, "expected a list of at least one case file path")
    return tuple(value)


@dataclass(frozen=True, kw_only=True)
class CohortFile:
    """The cohort file (systems.validate typed section): ``generated`` is a record, kept as
    written."""

    schema_version: int = v.spec(v.version(SCHEMA_VERSION))
    name: str | None = v.spec(v.label, None)
    cases: tuple[str, ...] = v.spec(_case_files)
    generated: dict | None = v.spec(v.mapping, None)


def load_cohort(path) -> tuple[str, list[Path]]:
    """(name, case files) of a cohort file; paths are resolved against the cohort's folder."""
    path = Path(path)
    f = v.parse(CohortFile, read_yaml(path, field="--cohort"), "")
    base = path.resolve().parent
    return (path.stem if f.name is None else f.name), [
        (Path(c).expanduser() if Path(c).expanduser().is_absolute() else base / c)
        for c in f.cases
    ]


def _truncated_normal(rng: np.random.Generator, size=None) -> np.ndarray:
    return np.clip(rng.standard_normal(size), -3.0, 3.0)


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


def make_cohort(
    case_path,
    out_dir,
    n: int,
    *,
    seed: int = 0,
    scale_sd: float = 0.03,
    rotation_deg: float = 2.0,
    shift_mm: float = 1.0,
    site_jitter_mm: float = 0.5,
) -> Path:
    """Write ``n`` perturbed copies of a case (YAML + OBJ mesh each) and ``cohort.yaml`` into
    ``out_dir``; returns the cohort file. See the module docstring for the perturbation."""
    n = v.integer(n, "--cases", low=1)
    seed = v.integer(seed, "--seed", low=0)
    for name, value in (
        ("--scale-sd", scale_sd),
        ("--rotation-deg", rotation_deg),
        ("--shift-mm", shift_mm),
        ("--site-jitter-mm", site_jitter_mm),
    ):
        v.number(value, name, nonneg=True)
    if scale_sd >= 1.0 / 3.0:
        raise InputError("--scale-sd", f"expected < 1/3 (a scale that stays > 0), got {scale_sd}")
    case_path = Path(case_path)
    case = load_case(case_path)  # validates the source case (every error names its field)
    raw = read_yaml(case_path, field="case")
    mesh = load_oral_mesh(case.mesh.path, units=case.mesh.units, field="mesh.path")
    V0 = np.asarray(mesh.vertices) * 1e3  # mm, mesh frame
    center = case.center
    X_WC = center_frame(center.origin, center.z_axis, x_hint=center.x_hint)
    o = center.origin * 1e3
    R_C = X_WC[:3, :3]
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = case.name
    files, record = [], []
    for i in range(n):
        rng = np.random.default_rng([seed, i])
        s = 1.0 + scale_sd * float(_truncated_normal(rng))
        axis = rng.standard_normal(3)
        angle = np.deg2rad(rotation_deg) * float(_truncated_normal(rng))
        R = _rotation(axis, angle)
        t = shift_mm * _truncated_normal(rng, 3)
        jitter = site_jitter_mm * _truncated_normal(rng, (len(case.sites), 3))

        def point(p, s=s, R=R, t=t):
            return o + s * R @ (np.asarray(p, float) - o) + t

        name = f"{stem}-{i:02d}"
        data = copy.deepcopy(raw)
        data["name"] = name
        data["seed"] = int(case.seed)
        m = data["mesh"]
        m.update(path=f"{name}.obj", units="mm")
        if case.mesh.mouth_opening_deg > 0:
            op = case.mesh.opening
            m["hinge_point_mm"] = _r(point(op["hinge_point"] * 1e3))
            m["hinge_axis"] = _r(R @ op["hinge_axis"])
            m["occlusal_point_mm"] = _r(point(op["occlusal_point"] * 1e3))
            m["occlusal_normal"] = _r(R @ op["occlusal_normal"])
            m["opening_blend_mm"] = _r(s * op["blend"] * 1e3)
        if case.mesh.cap_radius is not None:
            m["cap_radius_mm"] = _r(s * case.mesh.cap_radius * 1e3)
        R_in_C = R_C.T @ R @ R_C  # the anatomy's rotation seen in Center
        V = o + s * (V0 - o) @ R.T + t
        mesh_out = mesh.copy()
        mesh_out.vertices = V
        # the scan as the case plans it (opened, metres): jittered sites go back onto its tissue
        planned = trimesh.Trimesh(V * 1e-3, mesh.faces, process=False)
        if case.mesh.mouth_opening_deg > 0:
            planned = open_mouth(planned, case.mesh.mouth_opening_deg, **{
                "hinge_point": np.asarray(m["hinge_point_mm"]) * 1e-3,
                "hinge_axis": np.asarray(m["hinge_axis"]),
                "occlusal_point": np.asarray(m["occlusal_point_mm"]) * 1e-3,
                "occlusal_normal": np.asarray(m["occlusal_normal"]),
                "blend": m["opening_blend_mm"] * 1e-3})
        for k, (site, raw_site) in enumerate(zip(case.sites, data["sites"], strict=True)):
            axis = R_in_C @ site.axis
            p_C = R_C.T @ (s * R @ R_C @ (site.position * 1e3) + t) + jitter[k]
            # the site moves with the anatomy and the jitter, then along its axis onto the tissue
            # (the site check of the plan: within 1 mm of the scan, axis into the cavity)
            on_tissue = project_to_tissue(planned, X_WC, p_C * 1e-3 + 2e-3 * axis, axis)[0]
            if np.all(np.isfinite(on_tissue)):
                p_C = on_tissue * 1e3
            raw_site["position_mm"] = _r(p_C)
            raw_site["axis"] = _r(axis)
        write_atomic(out_dir / f"{name}.obj",
                     lambda tmp, mo=mesh_out: mo.export(tmp, file_type="obj"))  # fmt: skip
        write_text_atomic(out_dir / f"{name}.yaml", yaml.safe_dump(data, sort_keys=False))
        files.append(f"{name}.yaml")
        record.append({
            "case": name, "scale": _r(s), "rotation_axis": _r(axis / np.linalg.norm(axis)),
            "rotation_deg": _r(np.rad2deg(angle)), "shift_mm": _r(t), "site_jitter_mm": _r(jitter),
        })  # fmt: skip
    cohort = {
        "schema_version": SCHEMA_VERSION,
        "name": f"{stem}-cohort",
        "cases": files,
        "generated": {
            "source": str(case_path.resolve()),
            "seed": seed,
            "scale_sd": float(scale_sd),
            "rotation_deg": float(rotation_deg),
            "shift_mm": float(shift_mm),
            "site_jitter_mm": float(site_jitter_mm),
            "rule": "x' = o + s R (x - o) + t about the Center origin; sites move with the "
            "anatomy plus jitter; Center frame fixed; draws truncated at 3 sigma",
            "cases": record,
        },
    }
    path = out_dir / "cohort.yaml"
    write_text_atomic(path, yaml.safe_dump(cohort, sort_keys=False))
    return path


def _r(x):
    """Plain floats rounded to 1e-9 (mm or unitless) for the YAML files."""
    a = np.round(np.asarray(x, dtype=float), 9)
    return a.tolist() if a.ndim else float(a)
