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
from implantplan.systems.anatomy.cbct import is_volume_path
from implantplan.systems.errors import InputError
from implantplan.systems.files import MAX_MESH_BYTES, input_file, read_yaml
from implantplan.systems.robot.scenario import load_scenario
from implantplan.systems.safety import SafetySpec

MM = 1e-3
DEFAULT_CASE = "cases/default.yaml"  # under models/
# Upper bounds of the case's counts and lengths (docs/formats.md, "Bounds"): each is checked when
# the case is read, before any work; a value past one is a typo, not a request.
COORD_MM = 10_000.0  # any point in mm (the mesh frame: a scan of 10 m is not a mouth)
SITE_MM = 300.0      # a site's position in Center, mm
MAX_RUNS = 100       # feeding simulations per site (simulation.runs, --runs)
_coord = partial(v.vector, n=3, limit=COORD_MM)
_length_mm = partial(v.number, positive=True, high=1000.0)


def resolve_path(value: str, base_dir: Path, field_name: str, *, folder_ok: bool = False) -> Path:
    """``package://implantplan/REL`` -> models/REL; a relative path is relative to the case file.
    With ``folder_ok`` a folder is accepted too (a DICOM series)."""
    if not isinstance(value, str) or not value:
        raise InputError(field_name, f"expected a file path, got {value!r}")
    prefix = "package://implantplan/"
    if value.startswith(prefix):
        path = models.MODELS_DIR / value[len(prefix):]
    else:
        path = Path(value).expanduser()
        if not path.is_absolute():
            path = base_dir / path
    if folder_ok and path.is_dir():
        return path  # a DICOM series folder (its files are checked when the series is read)
    return input_file(path, field_name, max_bytes=MAX_MESH_BYTES)


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
    ``path`` is the text of the file; in a loaded :class:`Case`, the file it names. A DICOM
    series folder or a NIfTI file is a CBCT (systems.anatomy.cbct): its surfaces are extracted
    at ``air_threshold_hu`` (the oral cavity's air/tissue boundary) and ``bone_threshold_hu``,
    and the case's frames are DICOM's patient frame (LPS, mm; ``units`` must be mm)."""

    path: str | Path = v.spec(v.text)
    units: str = v.spec(v.one_of("mm", "m"), "mm")
    close_open_cuts: bool = v.spec(v.boolean, False)
    cap_radius: float | None = v.spec(partial(v.number, positive=True, high=200.0), None,
                                      key="cap_radius_mm", scale=MM)
    mouth_opening_deg: float = v.spec(partial(v.number, low=0.0, high=45.0), 0.0)
    hinge_point: np.ndarray | None = v.spec(_coord, None, key="hinge_point_mm", scale=MM)
    hinge_axis: np.ndarray | None = v.spec(v.direction, None)
    occlusal_point: np.ndarray | None = v.spec(_coord, None, key="occlusal_point_mm", scale=MM)
    occlusal_normal: np.ndarray | None = v.spec(v.direction, None)
    blend: float = v.spec(_length_mm, 20.0, key="opening_blend_mm", scale=MM)
    air_threshold_hu: float = v.spec(partial(v.number, low=-1000.0, high=0.0), -500.0)
    bone_threshold_hu: float = v.spec(partial(v.number, low=100.0, high=2000.0), 300.0)

    @property
    def jaw(self) -> dict:
        """The jaw-opening model's keyword arguments of systems.fpsm.oral_mesh.open_mouth and
        opening_map (m), whatever the angle."""
        return {"hinge_point": self.hinge_point, "hinge_axis": self.hinge_axis,
                "occlusal_point": self.occlusal_point, "occlusal_normal": self.occlusal_normal,
                "blend": self.blend}

    @property
    def opening(self) -> dict:
        """Keyword arguments of systems.fpsm.oral_mesh.open_mouth (m); empty when 0 deg."""
        return {} if self.mouth_opening_deg <= 0 else self.jaw


@dataclass(frozen=True)
class CenterSection:
    """``center:`` the Center frame in the (opened) mesh frame."""

    origin: np.ndarray = v.spec(_coord, key="origin_mm", scale=MM)
    z_axis: np.ndarray = v.spec(v.direction)
    x_hint: np.ndarray | None = v.spec(v.direction, None)


@dataclass(frozen=True)
class FpsmSection:
    """``fpsm:`` the FPSM fit (systems.fpsm.fit.fit_fpsm). ``margin`` is the fit's offset from
    the wall, not the clinical margin (that is ``safety.clearance_margin``)."""

    slices: int = v.spec(partial(v.integer, low=2, high=200), 15)
    control_points: int = v.spec(partial(v.integer, low=3, high=100), 15)
    samples: int = v.spec(partial(v.integer, low=8, high=2000), 150)
    method: str = v.spec(v.one_of("exact", "paper"), "exact")
    margin: float = v.spec(partial(v.number, nonneg=True, high=20.0), 0.0, key="margin_mm",
                           scale=MM)
    z_range: np.ndarray | None = v.spec(v.interval, None, key="z_range_mm", scale=MM)

    def __post_init__(self):
        if self.z_range is not None and np.abs(self.z_range).max() > SITE_MM * MM:
            raise InputError("fpsm.z_range_mm", f"expected heights within +-{SITE_MM:g} mm of "
                             f"the Center origin, got {np.round(self.z_range / MM, 3).tolist()}")


@dataclass(frozen=True, kw_only=True)
class Site:
    """One implant site. position (m) and axis (unit, from the bone into the cavity) in Center;
    ``name`` is ``site<k>`` in a loaded :class:`Case` when the file gives none."""

    name: str | None = v.spec(v.safe_name, None)
    position: np.ndarray = v.spec(partial(v.vector, n=3, limit=SITE_MM), key="position_mm",
                                  scale=MM)
    axis: np.ndarray = v.spec(v.direction)
    # seed 000's d12: the actuator head's centre to the implant tip (not the implant's length;
    # the key was ``implant_length_mm``, still read with a note)
    implant_length: float = v.spec(partial(v.number, low=1.0, high=100.0), 31.0,
                                   key="head_to_tip_mm", scale=MM)
    rod_radius: float = v.spec(partial(v.number, nonneg=True, high=20.0), 6.0,
                               key="rod_radius_mm", scale=MM)
    # the implant placed in the bone, from the entry point (the site) to its apex: its length
    # and diameter (the card, the figures, plan.dcm and its STL)
    placed_length: float = v.spec(partial(v.number, low=4.0, high=25.0), 10.0,
                                  key="placed_implant_length_mm", scale=MM)
    implant_diameter: float = v.spec(partial(v.number, low=2.0, high=8.0), 4.0,
                                     key="implant_diameter_mm", scale=MM)


@dataclass(frozen=True)
class SiteCheckSection:
    """``site_check:`` how far a site may lie from the scanned tissue (systems.fpsm.sites)."""

    tolerance: float = v.spec(partial(v.number, positive=True, high=10.0), 1.0,
                              key="tolerance_mm", scale=MM)


@dataclass(frozen=True)
class PlacementSection:
    """``placement:`` the instrument placement's objective (Eq. 14, 21 or 22)."""

    objective: str = v.spec(v.one_of("eq14", "eq21", "eq22"), "eq14")


@dataclass(frozen=True)
class PatientSection:
    """``patient:`` the posture; ``id`` and ``name`` label plan.dcm when the scan is not a DICOM
    series (a series' own identifiers win)."""

    posture: str = v.spec(v.one_of("lying", "sitting"), "lying")
    id: str | None = v.spec(v.text, None)
    name: str | None = v.spec(v.text, None)


@dataclass(frozen=True)
class RobotSection:
    """``robot:`` the MOPRP scenario and the NSGA-II size. ``scenario`` is as written (None:
    the patient's posture); in a loaded :class:`Case`, a bundled name or the file's path,
    validated when the case is loaded."""

    scenario: str | None = v.spec(v.text, None)
    pop: int = v.spec(partial(v.integer, low=4, high=1000), 100)
    gen: int = v.spec(partial(v.integer, low=1, high=500), 60)
    # the joint-limit headroom (rad) along every feed and under the head motions; None: the
    # scenario's ``joint_headroom_deg`` (10 deg in the bundled ones)
    joint_headroom: float | None = v.spec(partial(v.number, low=0.0, high=90.0), None,
                                          key="joint_headroom_deg", scale=np.pi / 180.0)


@dataclass(frozen=True)
class CapabilitySection:
    """``capability:`` the capability map around the feeding targets (seed 004)."""

    voxel: float = v.spec(partial(v.number, low=10.0, high=500.0), 50.0, key="voxel_mm",
                          scale=MM)
    directions: int = v.spec(partial(v.integer, low=4, high=2000), 100)


@dataclass(frozen=True)
class SimulationSection:
    """``simulation:`` the teleoperated feeding runs per site."""

    runs: int = v.spec(partial(v.integer, low=0, high=MAX_RUNS), 1)
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


def _polyline(value, where: str) -> np.ndarray:
    """At least two points [x, y, z] (mm in the file, m here), at most 10,000."""
    arr = np.asarray(value if isinstance(value, list) else [], dtype=object)
    if arr.ndim != 2 or arr.shape[1] != 3 or not 2 <= len(arr) <= 10_000:
        raise InputError(where, f"expected a list of 2 to 10000 points [x, y, z] (mm), got "
                         f"{str(value)[:60]}")
    return np.array([v.vec3(p, f"{where}[{i}]") for i, p in enumerate(value)]) * MM


@dataclass(frozen=True)
class Canal:
    """A nerve canal (the inferior alveolar canal): a polyline in the scan's frame as scanned
    (a CBCT's patient frame, LPS), with its radius."""

    polyline: np.ndarray = v.spec(_polyline, key="polyline_mm")
    radius: float = v.spec(partial(v.number, low=0.0, high=5.0), 1.2, key="radius_mm", scale=MM)


@dataclass(frozen=True)
class AnatomySection:
    """``anatomy:`` what the clinical distance checks measure (systems.anatomy.distances):
    ``canals`` (a list of polylines with radii) and/or ``canals_file`` (a canals YAML as
    ``implantplan phantom`` writes it, relative to the case file), in the scan's frame as
    scanned; ``teeth_threshold_hu`` the HU above which a CBCT voxel is tooth."""

    canals: tuple = v.spec(v.sections(Canal), [])
    canals_file: str | None = v.spec(v.text, None)
    teeth_threshold_hu: float = v.spec(partial(v.number, low=500.0, high=4000.0), 1800.0)


def _anatomy(value, where: str) -> AnatomySection | None:
    return None if value is None else v.parse(AnatomySection, value, where)


def load_canals(path: Path, field: str = "anatomy.canals_file") -> tuple:
    """The canals of a canals YAML (``radius_mm``, ``canals: [{polyline_mm}]``)."""
    data = read_yaml(path, field=field)
    if not isinstance(data, dict) or not isinstance(data.get("canals"), list):
        raise InputError(field, f"{path}: expected a mapping with a 'canals' list")
    radius = data.get("radius_mm", 1.2)
    return tuple(v.parse(Canal, {"polyline_mm": c.get("polyline_mm") if isinstance(c, dict)
                                 else None, "radius_mm": radius}, f"{field}: canals[{i}]")
                 for i, c in enumerate(data["canals"]))


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


PAPER_SITE_KEYS = ("rod_radius_mm", "head_to_tip_mm")  # the paper tool's shape, per site


def _paper_keys_only_for_paper(data) -> None:
    """A site's ``rod_radius_mm`` / ``head_to_tip_mm`` shape the paper's tool; with another
    instrument its own shapes hold, so writing them is an error naming the key (not ignored)."""
    if not isinstance(data, dict) or not isinstance(data.get("sites"), list):
        return  # the typed parse names what is wrong
    instrument = _instrument(data.get("instrument", "actuator"), "instrument")
    if instrument.kind == "paper":
        return
    for k, site in enumerate(data["sites"]):
        for key in (*PAPER_SITE_KEYS, "implant_length_mm"):
            if isinstance(site, dict) and key in site:
                raise InputError(f"sites[{k}].{key}", f"applies to instrument: paper only (seed "
                                 f"000's thin tool); the {instrument.kind} instrument's rod and "
                                 "d12 are its own shapes: remove the key or set instrument: paper")


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
    name: str | None = v.spec(v.safe_name, None)
    seed: int = v.spec(partial(v.integer, low=0, high=2**63 - 1), 0)
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
    instrument: InstrumentSection = v.spec(_instrument, "actuator")
    anatomy: AnatomySection | None = v.spec(_anatomy, None)
    source: Path | None = None

    def instrument_at(self, site: Site):
        """The instrument the plan checks at ``site`` (:meth:`InstrumentSection.instrument`)."""
        return self.instrument.instrument(site)


SPACING_BEYOND_DIAMETER_MM = 1.5  # DESIGN.md section 4, clinical spacing


def _check_spacing(sites) -> None:
    """Sites closer than an implant's diameter + 1.5 mm (DESIGN.md section 4's clinical spacing;
    the diameter is the actuator's implant, systems.actuator) are an InputError naming the later
    site and the one it is too close to."""
    from implantplan.systems.actuator import IMPLANT_RADIUS

    if len(sites) < 2:
        return
    P = np.array([s.position for s in sites])
    D = np.linalg.norm(P[:, None] - P[None], axis=-1)
    minimum = 2 * IMPLANT_RADIUS + SPACING_BEYOND_DIAMETER_MM * MM
    i, j = np.nonzero(np.triu(D < minimum, k=1))
    if i.size:
        a, b = int(i[0]), int(j[0])
        raise InputError(f"sites[{b}].position_mm", f"site {sites[b].name!r} lies "
                         f"{D[a, b] / MM:.2f} mm from site {sites[a].name!r}; expected at least "
                         f"{minimum / MM:g} mm (implant diameter {2 * IMPLANT_RADIUS / MM:g} mm "
                         f"+ {SPACING_BEYOND_DIAMETER_MM:g} mm)")


def _stem_name(source: Path) -> str:
    """The case file's stem as a safe name (analyses.batch's folder rule: other characters
    become ``_``)."""
    import re

    return re.sub(r"[^A-Za-z0-9._-]", "_", source.stem)[:64].strip(".") or "case"


def case_from_dict(data: dict, *, source: Path) -> Case:
    """Validate a case mapping (:class:`Case`'s sections) and resolve it: paths against the case
    file's folder, default names, the scenario (read and validated now, so a bad scenario file
    stops the plan before any stage runs), the cross-field rules."""
    _paper_keys_only_for_paper(data)
    case = v.parse(Case, data, "")
    base_dir = source.resolve().parent
    mesh = case.mesh
    if mesh.mouth_opening_deg > 0:
        for key, value in (("hinge_point_mm", mesh.hinge_point), ("hinge_axis", mesh.hinge_axis),
                           ("occlusal_point_mm", mesh.occlusal_point),
                           ("occlusal_normal", mesh.occlusal_normal)):
            if value is None:
                raise InputError(f"mesh.{key}", "missing (required)")

    mesh = replace(mesh, path=resolve_path(mesh.path, base_dir, "mesh.path", folder_ok=True))
    if is_volume_path(mesh.path) and mesh.units != "mm":
        raise InputError("mesh.units", f"{mesh.units!r} for a CBCT; expected 'mm' (DICOM's "
                         "patient frame is in mm)")

    sites, names = [], set()
    for k, s in enumerate(case.sites):
        name = f"site{k + 1}" if s.name is None else s.name
        if name in names:
            raise InputError(f"sites[{k}].name", f"site name {name!r} is used twice")
        names.add(name)
        sites.append(replace(s, name=name))

    _check_spacing(sites)
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
    anatomy = case.anatomy
    if anatomy is not None and anatomy.canals_file is not None:
        file = resolve_path(anatomy.canals_file, base_dir, "anatomy.canals_file")
        anatomy = replace(anatomy, canals_file=str(file),
                          canals=anatomy.canals + load_canals(file))
    return replace(
        case,
        anatomy=anatomy,
        instrument=instrument,
        name=_stem_name(source) if case.name is None else case.name,
        source=source,
        mesh=mesh,
        sites=tuple(sites),
        robot=replace(case.robot, scenario=scenario),
    )
