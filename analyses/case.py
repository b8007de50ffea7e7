"""The case file: one surgical case to plan (DESIGN.md section 1; YAML, schema_version 1).

A case names the oral scan (mesh, units, how to close/open it), the Center frame in the mesh, the
FPSM settings, the implant sites (position and axis in Center, the tool's d12 and radius, the
placed implant's length), the patient posture, the robot scenario and the settings of each later
stage, and a seed.
``models/cases/default.yaml`` is the bundled example; every key is described there.

Lengths are mm in the file (people write them) and metres in :class:`Case` (code uses SI). A
:class:`Case` is the file's sections as typed frozen objects (``case.mesh``, ``case.fpsm``,
``case.safety``, ...), each default written once in its section's spec; a stage takes the section
it uses whole. Unknown and duplicate keys are errors, so a typo never falls back to a default
silently.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np

from implantplan import models
from implantplan.systems import validate as v
from implantplan.systems.errors import InputError
from implantplan.systems.files import read_yaml
from implantplan.systems.robot.scenario import load_scenario
from implantplan.systems.safety import SafetySpec

MM = 1e-3
DEFAULT_CASE = "cases/default.yaml"  # under models/


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


# -- the case's sections (systems.validate typed sections; lengths in mm in the file) -------------


@dataclass(frozen=True)
class MeshSection:
    """``mesh:`` the oral scan and the jaw-opening model (systems.fpsm.oral_mesh.open_mouth).
    ``path`` is the text of the file; in a loaded :class:`Case`, the file it names."""

    path: str | Path = v.spec(v.text)
    units: str = v.spec(v.one_of("mm", "m"), "mm")
    close_open_cuts: bool = v.spec(v.boolean, False)
    cap_radius: float | None = v.spec(v.positive, None, key="cap_radius_mm", scale=MM)
    mouth_opening_deg: float = v.spec(partial(v.number, low=0.0, high=45.0), 0.0)
    hinge_point: np.ndarray | None = v.spec(v.vec3, None, key="hinge_point_mm", scale=MM)
    hinge_axis: np.ndarray | None = v.spec(v.direction, None)
    occlusal_point: np.ndarray | None = v.spec(v.vec3, None, key="occlusal_point_mm", scale=MM)
    occlusal_normal: np.ndarray | None = v.spec(v.direction, None)
    blend: float = v.spec(v.positive, 20.0, key="opening_blend_mm", scale=MM)

    @property
    def opening(self) -> dict:
        """Keyword arguments of systems.fpsm.oral_mesh.open_mouth (m); empty when 0 deg."""
        if self.mouth_opening_deg <= 0:
            return {}
        return {"hinge_point": self.hinge_point, "hinge_axis": self.hinge_axis,
                "occlusal_point": self.occlusal_point, "occlusal_normal": self.occlusal_normal,
                "blend": self.blend}


@dataclass(frozen=True)
class CenterSection:
    """``center:`` the Center frame in the (opened) mesh frame."""

    origin: np.ndarray = v.spec(v.vec3, key="origin_mm", scale=MM)
    z_axis: np.ndarray = v.spec(v.direction)
    x_hint: np.ndarray | None = v.spec(v.direction, None)


@dataclass(frozen=True)
class FpsmSection:
    """``fpsm:`` the FPSM fit (systems.fpsm.fit.fit_fpsm). ``margin`` is the fit's offset from
    the wall, not the clinical margin (that is ``safety.clearance_margin``)."""

    slices: int = v.spec(partial(v.integer, low=2), 15)
    control_points: int = v.spec(partial(v.integer, low=3), 15)
    samples: int = v.spec(partial(v.integer, low=8), 150)
    method: str = v.spec(v.one_of("exact", "paper"), "exact")
    margin: float = v.spec(v.nonneg, 0.0, key="margin_mm", scale=MM)
    z_range: np.ndarray | None = v.spec(v.interval, None, key="z_range_mm", scale=MM)


@dataclass(frozen=True, kw_only=True)
class Site:
    """One implant site. position (m) and axis (unit, from the bone into the cavity) in Center;
    ``name`` is ``site<k>`` in a loaded :class:`Case` when the file gives none."""

    name: str | None = v.spec(v.label, None)
    position: np.ndarray = v.spec(v.vec3, key="position_mm", scale=MM)
    axis: np.ndarray = v.spec(v.direction)
    # seed 000's d12: the actuator head's centre to the implant tip (not the implant's length;
    # the key was ``implant_length_mm``, still read with a note)
    implant_length: float = v.spec(partial(v.number, low=1.0, high=100.0), 31.0,
                                   key="head_to_tip_mm", scale=MM)
    rod_radius: float = v.spec(v.nonneg, 6.0, key="rod_radius_mm", scale=MM)
    # the implant placed in the bone, from the entry point (the site) to its apex (the card)
    placed_length: float = v.spec(partial(v.number, low=4.0, high=25.0), 10.0,
                                  key="placed_implant_length_mm", scale=MM)


@dataclass(frozen=True)
class SiteCheckSection:
    """``site_check:`` how far a site may lie from the scanned tissue (systems.fpsm.sites)."""

    tolerance: float = v.spec(v.positive, 1.0, key="tolerance_mm", scale=MM)


@dataclass(frozen=True)
class PlacementSection:
    """``placement:`` the instrument placement's objective (Eq. 14, 21 or 22)."""

    objective: str = v.spec(v.one_of("eq14", "eq21", "eq22"), "eq14")


@dataclass(frozen=True)
class PatientSection:
    posture: str = v.spec(v.one_of("lying", "sitting"), "lying")


@dataclass(frozen=True)
class RobotSection:
    """``robot:`` the MOPRP scenario and the NSGA-II size. ``scenario`` is as written (None:
    the patient's posture); in a loaded :class:`Case`, a bundled name or the file's path,
    validated when the case is loaded."""

    scenario: str | None = v.spec(v.text, None)
    pop: int = v.spec(partial(v.integer, low=4), 100)
    gen: int = v.spec(partial(v.integer, low=1), 60)
    # the joint-limit headroom (rad) along every feed and under the head motions; None: the
    # scenario's ``joint_headroom_deg`` (10 deg in the bundled ones)
    joint_headroom: float | None = v.spec(partial(v.number, low=0.0, high=90.0), None,
                                          key="joint_headroom_deg", scale=np.pi / 180.0)


@dataclass(frozen=True)
class CapabilitySection:
    """``capability:`` the capability map around the feeding targets (seed 004)."""

    voxel: float = v.spec(partial(v.number, low=10.0), 50.0, key="voxel_mm", scale=MM)
    directions: int = v.spec(partial(v.integer, low=4), 100)


@dataclass(frozen=True)
class SimulationSection:
    """``simulation:`` the teleoperated feeding runs per site."""

    runs: int = v.spec(partial(v.integer, low=0), 1)
    mode: str = v.spec(v.one_of("kinematic", "dynamic"), "kinematic")


@dataclass(frozen=True)
class InstrumentSection:
    """``instrument:`` the instrument every safety layer checks (systems.instrument): ``paper``
    (seed 000's thin tool, with each site's ``rod_radius_mm`` and ``head_to_tip_mm``),
    ``actuator`` (the shipped actuator URDF's solids: its head is a cylinder r 8 mm x 14 mm), or
    ``{urdf: PATH}`` (an actuator URDF of the case's own, relative to the case file). Written as
    a word or as a mapping ``{kind: ..., urdf: ...}``."""

    kind: str = v.spec(v.one_of("paper", "actuator", "urdf"), "paper")
    urdf: str | None = v.spec(v.text, None)

    def instrument(self, site: Site):
        """The :class:`systems.instrument.Instrument` at a site (the paper's tool takes the
        site's rod radius and d12; an actuator's are its own)."""
        from implantplan.systems.instrument import Instrument

        if self.kind == "paper":
            return Instrument.paper(rod_radius=site.rod_radius, implant_length=site.implant_length)
        if self.kind == "actuator":
            return Instrument.actuator()
        return Instrument.from_urdf(self.urdf)


def _instrument(value, where: str) -> InstrumentSection:
    """``instrument:`` as a word (the kind), ``{urdf: PATH}`` or ``{kind: ..., urdf: ...}``."""
    if isinstance(value, str):
        value = {"kind": value}
    elif isinstance(value, dict) and "urdf" in value and "kind" not in value:
        value = {"kind": "urdf", **value}
    section = v.parse(InstrumentSection, value, where)
    if (section.kind == "urdf") != (section.urdf is not None):
        raise InputError(f"{where}.urdf", "expected a URDF path exactly when kind is 'urdf' "
                         "(or write instrument: {urdf: PATH})")
    return section


OLD_D12_KEY = "implant_length_mm"
notes_printed: set[str] = set()  # the notes printed in this process (once each)


def _sites(value, where: str) -> tuple:
    if not isinstance(value, list) or not value:
        raise InputError(where, "expected a list of at least one implant site")
    value = [_renamed_d12(s, f"{where}[{k}]") for k, s in enumerate(value)]
    return v.sections(Site)(value, where)


def _renamed_d12(site, where: str):
    """A site written with the old key for d12 (``implant_length_mm``) reads as
    ``head_to_tip_mm``, with a note printed once per run; both keys at once is an error."""
    if not isinstance(site, dict) or OLD_D12_KEY not in site:
        return site
    if "head_to_tip_mm" in site:
        raise InputError(f"{where}.{OLD_D12_KEY}", "expected one of implant_length_mm (the old "
                         "name) and head_to_tip_mm, not both")
    if OLD_D12_KEY not in notes_printed:
        notes_printed.add(OLD_D12_KEY)
        print(f"note: {where}.{OLD_D12_KEY} is read as head_to_tip_mm (seed 000's d12, the "
              "head centre to the implant tip, not the implant's length); rename the key",
              file=sys.stderr)
    site = dict(site)
    site["head_to_tip_mm"] = site.pop(OLD_D12_KEY)
    return site


@dataclass(frozen=True, kw_only=True)
class Case:
    """One case: the file's sections as typed objects (SI), each passed whole to the stage that
    uses it (analyses.pipeline). :func:`load_case` fills in what the file may leave out (the
    name, the site names, the scenario) and resolves the paths; ``source`` is the case file."""

    schema_version: int = v.spec(v.version(1))
    name: str | None = v.spec(v.label, None)
    seed: int = v.spec(partial(v.integer, low=0), 0)
    mesh: MeshSection = v.spec(v.section(MeshSection))
    center: CenterSection = v.spec(v.section(CenterSection))
    fpsm: FpsmSection = v.spec(v.section(FpsmSection), {})
    sites: tuple[Site, ...] = v.spec(_sites)
    site_check: SiteCheckSection = v.spec(v.section(SiteCheckSection), {})
    placement: PlacementSection = v.spec(v.section(PlacementSection), {})
    patient: PatientSection = v.spec(v.section(PatientSection), {})
    robot: RobotSection = v.spec(v.section(RobotSection), {})
    capability: CapabilitySection = v.spec(v.section(CapabilitySection), {})
    simulation: SimulationSection = v.spec(v.section(SimulationSection), {})
    safety: SafetySpec = v.spec(v.section(SafetySpec), {})
    instrument: InstrumentSection = v.spec(_instrument, "paper")
    source: Path | None = None

    def instrument_at(self, site: Site):
        """The instrument the plan checks at ``site`` (:meth:`InstrumentSection.instrument`)."""
        return self.instrument.instrument(site)


def case_from_dict(data: dict, *, source: Path) -> Case:
    """Validate a case mapping (:class:`Case`'s sections) and resolve it: paths against the case
    file's folder, default names, the scenario (read and validated now, so a bad scenario file
    stops the plan before any stage runs), the cross-field rules."""
    case = v.parse(Case, data, "")
    base_dir = source.resolve().parent
    mesh = case.mesh
    if mesh.mouth_opening_deg > 0:
        for key, value in (("hinge_point_mm", mesh.hinge_point), ("hinge_axis", mesh.hinge_axis),
                           ("occlusal_point_mm", mesh.occlusal_point),
                           ("occlusal_normal", mesh.occlusal_normal)):
            if value is None:
                raise InputError(f"mesh.{key}", "missing (required)")

    sites, names = [], set()
    for k, s in enumerate(case.sites):
        name = f"site{k + 1}" if s.name is None else s.name
        if name in names:
            raise InputError(f"sites[{k}].name", f"site name {name!r} is used twice")
        names.add(name)
        sites.append(replace(s, name=name))

    posture = case.patient.posture
    scenario = case.robot.scenario or posture
    if scenario not in ("lying", "sitting"):
        scenario = str(resolve_path(scenario, base_dir, "robot.scenario"))
        load_scenario(scenario)
    elif scenario != posture:
        raise InputError(
            "robot.scenario",
            f"the bundled scenario {scenario!r} contradicts patient.posture {posture!r}",
        )
    instrument = case.instrument
    if instrument.kind == "urdf":
        urdf = resolve_path(instrument.urdf, base_dir, "instrument.urdf")
        instrument = replace(instrument, urdf=str(urdf))
        instrument.instrument(sites[0])  # a URDF the instrument cannot be read from stops here
    return replace(
        case,
        instrument=instrument,
        name=source.stem if case.name is None else case.name,
        source=source,
        mesh=replace(mesh, path=resolve_path(mesh.path, base_dir, "mesh.path")),
        sites=tuple(sites),
        robot=replace(case.robot, scenario=scenario),
    )
