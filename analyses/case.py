"""The case file: one surgical case to plan (DESIGN.md section 1; YAML, schema_version 1).

A case names the oral scan (mesh, units, how to close/open it), the Center frame in the mesh, the
FPSM settings, the implant sites (position and axis in Center, implant length, tool radius), the
patient posture, the robot scenario and the settings of each later stage, and a seed.
``models/cases/default.yaml`` is the bundled example; every key is described there.

Lengths are mm in the file (people write them) and metres in :class:`Case` (code uses SI).
Unknown keys are errors, so a typo never falls back to a default silently.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from implantplan import models
from implantplan.systems import validate as v
from implantplan.systems.errors import InputError
from implantplan.systems.files import read_yaml

MM = 1e-3
DEFAULT_CASE = "cases/default.yaml"  # under models/


@dataclass(frozen=True)
class Site:
    """One implant site. position (m) and axis (unit, from the bone into the cavity) in Center."""

    name: str
    position: np.ndarray
    axis: np.ndarray
    implant_length: float
    rod_radius: float


@dataclass(frozen=True)
class Case:
    name: str
    source: Path
    seed: int
    mesh_path: Path
    units: str
    close_open_cuts: bool
    cap_radius: float | None
    mouth_opening_deg: float
    opening: dict  # keyword arguments of systems.oral_mesh.open_mouth (m), empty when 0 deg
    center_origin: np.ndarray
    center_z: np.ndarray
    center_x_hint: np.ndarray | None
    slices: int
    control_points: int
    samples: int
    fit_method: str
    margin: float
    z_range: tuple[float, float] | None
    sites: tuple[Site, ...]
    objective: str
    posture: str
    scenario: str
    pop: int
    gen: int
    voxel: float
    directions: int
    sim_runs: int
    sim_mode: str
    site_tolerance: float = 1e-3  # m: largest distance of a site from the scanned tissue
    extra: dict = field(default_factory=dict)


_TOP = ("schema_version", "name", "seed", "mesh", "center", "fpsm", "sites", "site_check",
        "placement", "patient", "robot", "capability", "simulation")


def resolve_path(value: str, base_dir: Path, field_name: str) -> Path:
    """``package://implantplan/REL`` -> models/REL; a relative path is relative to the case file."""
    if not isinstance(value, str) or not value:
        raise InputError(field_name, f"expected a file path, got {value!r}")
    prefix = "package://implantplan/"
    if value.startswith(prefix):
        path = models.MODELS_DIR / value[len(prefix):]
    else:
        path = Path(value).expanduser()
        if not path.is_absolute():
            path = base_dir / path
    if not path.is_file():
        raise InputError(field_name, f"file {str(path)!r} does not exist")
    return path


def default_case_path() -> Path:
    return models.model_path(DEFAULT_CASE)


def load_case(path) -> Case:
    """Read and validate a case file; every error names the offending field."""
    path = Path(path)
    data = read_yaml(path, field="case")
    return case_from_dict(data, source=path)


def case_from_dict(data: dict, *, source: Path) -> Case:
    v.unknown_keys(data, _TOP, "")
    version = data.get("schema_version")
    if version != 1:
        raise InputError("schema_version", f"expected 1, got {version!r}")
    base_dir = source.resolve().parent

    mesh = v.mapping(v.require(data, "mesh"), "mesh")
    v.unknown_keys(mesh, ("path", "units", "close_open_cuts", "cap_radius_mm",
                          "mouth_opening_deg", "hinge_point_mm", "hinge_axis",
                          "occlusal_point_mm", "occlusal_normal", "opening_blend_mm"), "mesh.")
    units = v.choice(mesh.get("units", "mm"), "mesh.units", ("mm", "m"))
    close = mesh.get("close_open_cuts", False)
    if not isinstance(close, bool):
        raise InputError("mesh.close_open_cuts", f"expected true or false, got {close!r}")
    cap = mesh.get("cap_radius_mm")
    opening = v.number(mesh.get("mouth_opening_deg", 0.0), "mesh.mouth_opening_deg",
                       low=0.0, high=45.0)
    opening_args = {}
    if opening > 0:
        opening_args = {
            "hinge_point": v.vector(v.require(mesh, "hinge_point_mm", "mesh."),
                                    "mesh.hinge_point_mm", 3) * MM,
            "hinge_axis": v.direction(v.require(mesh, "hinge_axis", "mesh."), "mesh.hinge_axis"),
            "occlusal_point": v.vector(v.require(mesh, "occlusal_point_mm", "mesh."),
                                       "mesh.occlusal_point_mm", 3) * MM,
            "occlusal_normal": v.direction(v.require(mesh, "occlusal_normal", "mesh."),
                                           "mesh.occlusal_normal"),
            "blend": v.number(mesh.get("opening_blend_mm", 20.0), "mesh.opening_blend_mm",
                              positive=True) * MM,
        }

    center = v.mapping(v.require(data, "center"), "center")
    v.unknown_keys(center, ("origin_mm", "z_axis", "x_hint"), "center.")
    x_hint = center.get("x_hint")

    fp = v.mapping(data.get("fpsm"), "fpsm")
    v.unknown_keys(fp, ("slices", "control_points", "samples", "method", "margin_mm",
                        "z_range_mm"), "fpsm.")
    z_range = fp.get("z_range_mm")
    if z_range is not None:
        z_range = tuple(v.interval(z_range, "fpsm.z_range_mm") * MM)

    raw_sites = data.get("sites")
    if not isinstance(raw_sites, list) or not raw_sites:
        raise InputError("sites", "expected a list of at least one implant site")
    sites, names = [], set()
    for k, s in enumerate(raw_sites):
        where = f"sites[{k}]."
        s = v.mapping(s, where[:-1])
        v.unknown_keys(s, ("name", "position_mm", "axis", "implant_length_mm", "rod_radius_mm"),
                       where)
        name = str(s.get("name", f"site{k + 1}"))
        if name in names:
            raise InputError(where + "name", f"site name {name!r} is used twice")
        names.add(name)
        sites.append(Site(
            name=name,
            position=v.vector(v.require(s, "position_mm", where), where + "position_mm", 3) * MM,
            axis=v.direction(v.require(s, "axis", where), where + "axis"),
            implant_length=v.number(s.get("implant_length_mm", 31.0), where + "implant_length_mm",
                                    positive=True) * MM,
            rod_radius=v.number(s.get("rod_radius_mm", 6.0), where + "rod_radius_mm",
                                nonneg=True) * MM,
        ))

    site_check = v.mapping(data.get("site_check"), "site_check")
    v.unknown_keys(site_check, ("tolerance_mm",), "site_check.")

    placement = v.mapping(data.get("placement"), "placement")
    v.unknown_keys(placement, ("objective",), "placement.")
    patient = v.mapping(data.get("patient"), "patient")
    v.unknown_keys(patient, ("posture",), "patient.")
    robot = v.mapping(data.get("robot"), "robot")
    v.unknown_keys(robot, ("scenario", "pop", "gen"), "robot.")
    cap_map = v.mapping(data.get("capability"), "capability")
    v.unknown_keys(cap_map, ("voxel_mm", "directions"), "capability.")
    sim = v.mapping(data.get("simulation"), "simulation")
    v.unknown_keys(sim, ("runs", "mode"), "simulation.")

    posture = v.choice(patient.get("posture", "lying"), "patient.posture", ("lying", "sitting"))
    scenario = robot.get("scenario", posture)
    if scenario not in ("lying", "sitting"):
        scenario = str(resolve_path(scenario, base_dir, "robot.scenario"))
    elif scenario != posture:
        raise InputError(
            "robot.scenario",
            f"the bundled scenario {scenario!r} contradicts patient.posture {posture!r}",
        )

    return Case(
        name=str(data.get("name", source.stem)),
        source=source,
        seed=v.integer(data.get("seed", 0), "seed", low=0),
        mesh_path=resolve_path(v.require(mesh, "path", "mesh."), base_dir, "mesh.path"),
        units=units,
        close_open_cuts=close,
        cap_radius=None if cap is None else v.number(cap, "mesh.cap_radius_mm", positive=True) * MM,
        mouth_opening_deg=opening,
        opening=opening_args,
        center_origin=v.vector(v.require(center, "origin_mm", "center."), "center.origin_mm", 3)
        * MM,
        center_z=v.direction(v.require(center, "z_axis", "center."), "center.z_axis"),
        center_x_hint=None if x_hint is None else v.direction(x_hint, "center.x_hint"),
        slices=v.integer(fp.get("slices", 15), "fpsm.slices", low=2),
        control_points=v.integer(fp.get("control_points", 15), "fpsm.control_points", low=3),
        samples=v.integer(fp.get("samples", 150), "fpsm.samples", low=8),
        fit_method=v.choice(fp.get("method", "exact"), "fpsm.method", ("exact", "paper")),
        margin=v.number(fp.get("margin_mm", 0.0), "fpsm.margin_mm", nonneg=True) * MM,
        z_range=z_range,
        sites=tuple(sites),
        site_tolerance=v.number(site_check.get("tolerance_mm", 1.0), "site_check.tolerance_mm",
                                positive=True) * MM,
        objective=v.choice(placement.get("objective", "eq14"), "placement.objective",
                           ("eq14", "eq21", "eq22")),
        posture=posture,
        scenario=scenario,
        pop=v.integer(robot.get("pop", 100), "robot.pop", low=4),
        gen=v.integer(robot.get("gen", 60), "robot.gen", low=1),
        voxel=v.number(cap_map.get("voxel_mm", 50.0), "capability.voxel_mm", low=10.0) * MM,
        directions=v.integer(cap_map.get("directions", 100), "capability.directions", low=4),
        sim_runs=v.integer(sim.get("runs", 1), "simulation.runs", low=0),
        sim_mode=v.choice(sim.get("mode", "kinematic"), "simulation.mode",
                          ("kinematic", "dynamic")),
    )
