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
from functools import partial
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
    opening: dict  # keyword arguments of systems.fpsm.oral_mesh.open_mouth (m), empty when 0 deg
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
    # safety (issue 12): clinical margin, the fixture's admissible region, registration error
    clearance_margin: float = 0.001
    lateral_tolerance: float = 0.0005
    angle_tolerance: float = float(np.radians(1.0))
    registration: dict = field(default_factory=lambda: {
        "sigma_translation": 0.0005, "sigma_rotation": float(np.radians(0.5)), "samples": 1000})


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


# -- the file's schema (systems.validate typed sections; lengths in mm in the file) --------------


@dataclass(frozen=True)
class MeshSection:
    path: str = v.spec(v.text)
    units: str = v.spec(v.one_of("mm", "m"), "mm")
    close_open_cuts: bool = v.spec(v.boolean, False)
    cap_radius: float | None = v.spec(v.positive, None, key="cap_radius_mm", scale=MM)
    mouth_opening_deg: float = v.spec(partial(v.number, low=0.0, high=45.0), 0.0)
    hinge_point: np.ndarray | None = v.spec(v.vec3, None, key="hinge_point_mm", scale=MM)
    hinge_axis: np.ndarray | None = v.spec(v.direction, None)
    occlusal_point: np.ndarray | None = v.spec(v.vec3, None, key="occlusal_point_mm", scale=MM)
    occlusal_normal: np.ndarray | None = v.spec(v.direction, None)
    blend: float = v.spec(v.positive, 20.0, key="opening_blend_mm", scale=MM)


@dataclass(frozen=True)
class CenterSection:
    origin: np.ndarray = v.spec(v.vec3, key="origin_mm", scale=MM)
    z_axis: np.ndarray = v.spec(v.direction)
    x_hint: np.ndarray | None = v.spec(v.direction, None)


@dataclass(frozen=True)
class FpsmSection:
    slices: int = v.spec(partial(v.integer, low=2), 15)
    control_points: int = v.spec(partial(v.integer, low=3), 15)
    samples: int = v.spec(partial(v.integer, low=8), 150)
    method: str = v.spec(v.one_of("exact", "paper"), "exact")
    margin: float = v.spec(v.nonneg, 0.0, key="margin_mm", scale=MM)
    z_range: np.ndarray | None = v.spec(v.interval, None, key="z_range_mm", scale=MM)


@dataclass(frozen=True, kw_only=True)
class SiteSection:
    name: str | None = v.spec(v.label, None)
    position: np.ndarray = v.spec(v.vec3, key="position_mm", scale=MM)
    axis: np.ndarray = v.spec(v.direction)
    implant_length: float = v.spec(v.positive, 31.0, key="implant_length_mm", scale=MM)
    rod_radius: float = v.spec(v.nonneg, 6.0, key="rod_radius_mm", scale=MM)


@dataclass(frozen=True)
class SiteCheckSection:
    tolerance: float = v.spec(v.positive, 1.0, key="tolerance_mm", scale=MM)


@dataclass(frozen=True)
class PlacementSection:
    objective: str = v.spec(v.one_of("eq14", "eq21", "eq22"), "eq14")


@dataclass(frozen=True)
class PatientSection:
    posture: str = v.spec(v.one_of("lying", "sitting"), "lying")


@dataclass(frozen=True)
class RobotSection:
    scenario: str | None = v.spec(v.text, None)
    pop: int = v.spec(partial(v.integer, low=4), 100)
    gen: int = v.spec(partial(v.integer, low=1), 60)


@dataclass(frozen=True)
class CapabilitySection:
    voxel: float = v.spec(partial(v.number, low=10.0), 50.0, key="voxel_mm", scale=MM)
    directions: int = v.spec(partial(v.integer, low=4), 100)


@dataclass(frozen=True)
class SafetySection:
    clearance: float = v.spec(v.nonneg, 1.0, key="clearance_mm", scale=MM)
    lateral_tolerance: float = v.spec(v.nonneg, 0.5, key="lateral_tolerance_mm", scale=MM)
    angle_tolerance_deg: float = v.spec(partial(v.number, low=0.0, high=10.0), 1.0)
    registration_sigma: float = v.spec(v.nonneg, 0.5, key="registration_sigma_mm", scale=MM)
    registration_sigma_deg: float = v.spec(partial(v.number, low=0.0, high=10.0), 0.5)
    registration_samples: int = v.spec(partial(v.integer, low=0), 1000)


@dataclass(frozen=True)
class SimulationSection:
    runs: int = v.spec(partial(v.integer, low=0), 1)
    mode: str = v.spec(v.one_of("kinematic", "dynamic"), "kinematic")


def _sites(value, where: str) -> tuple:
    if not isinstance(value, list) or not value:
        raise InputError(where, "expected a list of at least one implant site")
    return v.sections(SiteSection)(value, where)


@dataclass(frozen=True, kw_only=True)
class CaseFile:
    """The case file as written (mm), section by section; :func:`case_from_dict` turns it into
    a :class:`Case` (SI, paths resolved, cross-field rules checked)."""

    schema_version: int = v.spec(v.version(1))
    name: str | None = v.spec(v.label, None)
    seed: int = v.spec(partial(v.integer, low=0), 0)
    mesh: MeshSection = v.spec(v.section(MeshSection))
    center: CenterSection = v.spec(v.section(CenterSection))
    fpsm: FpsmSection = v.spec(v.section(FpsmSection), {})
    sites: tuple = v.spec(_sites)
    site_check: SiteCheckSection = v.spec(v.section(SiteCheckSection), {})
    placement: PlacementSection = v.spec(v.section(PlacementSection), {})
    patient: PatientSection = v.spec(v.section(PatientSection), {})
    robot: RobotSection = v.spec(v.section(RobotSection), {})
    capability: CapabilitySection = v.spec(v.section(CapabilitySection), {})
    simulation: SimulationSection = v.spec(v.section(SimulationSection), {})
    safety: SafetySection = v.spec(v.section(SafetySection), {})


def case_from_dict(data: dict, *, source: Path) -> Case:
    """Validate a case mapping (:class:`CaseFile`) and resolve it into a :class:`Case`."""
    f = v.parse(CaseFile, data, "")
    base_dir = source.resolve().parent
    mesh = f.mesh
    opening_args = {}
    if mesh.mouth_opening_deg > 0:
        for key, value in (("hinge_point_mm", mesh.hinge_point), ("hinge_axis", mesh.hinge_axis),
                           ("occlusal_point_mm", mesh.occlusal_point),
                           ("occlusal_normal", mesh.occlusal_normal)):
            if value is None:
                raise InputError(f"mesh.{key}", "missing (required)")
        opening_args = {"hinge_point": mesh.hinge_point, "hinge_axis": mesh.hinge_axis,
                        "occlusal_point": mesh.occlusal_point,
                        "occlusal_normal": mesh.occlusal_normal, "blend": mesh.blend}

    sites, names = [], set()
    for k, s in enumerate(f.sites):
        name = f"site{k + 1}" if s.name is None else s.name
        if name in names:
            raise InputError(f"sites[{k}].name", f"site name {name!r} is used twice")
        names.add(name)
        sites.append(Site(name=name, position=s.position, axis=s.axis,
                          implant_length=s.implant_length, rod_radius=s.rod_radius))

    posture = f.patient.posture
    scenario = f.robot.scenario or posture
    if scenario not in ("lying", "sitting"):
        scenario = str(resolve_path(scenario, base_dir, "robot.scenario"))
    elif scenario != posture:
        raise InputError(
            "robot.scenario",
            f"the bundled scenario {scenario!r} contradicts patient.posture {posture!r}",
        )
    fp = f.fpsm
    return Case(
        name=source.stem if f.name is None else f.name,
        source=source,
        seed=f.seed,
        mesh_path=resolve_path(mesh.path, base_dir, "mesh.path"),
        units=mesh.units,
        close_open_cuts=mesh.close_open_cuts,
        cap_radius=mesh.cap_radius,
        mouth_opening_deg=mesh.mouth_opening_deg,
        opening=opening_args,
        center_origin=f.center.origin,
        center_z=f.center.z_axis,
        center_x_hint=f.center.x_hint,
        slices=fp.slices,
        control_points=fp.control_points,
        samples=fp.samples,
        fit_method=fp.method,
        margin=fp.margin,
        z_range=None if fp.z_range is None else tuple(fp.z_range),
        sites=tuple(sites),
        objective=f.placement.objective,
        posture=posture,
        scenario=scenario,
        pop=f.robot.pop,
        gen=f.robot.gen,
        voxel=f.capability.voxel,
        directions=f.capability.directions,
        sim_runs=f.simulation.runs,
        sim_mode=f.simulation.mode,
        site_tolerance=f.site_check.tolerance,
        clearance_margin=f.safety.clearance,
        lateral_tolerance=f.safety.lateral_tolerance,
        angle_tolerance=float(np.radians(f.safety.angle_tolerance_deg)),
        registration={"sigma_translation": f.safety.registration_sigma,
                      "sigma_rotation": float(np.radians(f.safety.registration_sigma_deg)),
                      "samples": f.safety.registration_samples},
    )
