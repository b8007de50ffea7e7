"""The MOPRP scenario schema (models/scenarios/*.yaml; DESIGN.md section 5): typed dataclasses
read from YAML through systems.validate's typed sections, as the case is: unknown keys, duplicate
keys and bad values are errors naming the field (``obstacles[2].radius_m``).

A scenario is the room and the problem of one robot placement: the Oral (feeding target) pose in
World, the bounds of the base position in Oral, the cart under the base and condition 1's joint-2
range, the patient and chair obstacles, the actuator, the index settings (joint error, feed),
the clearance, and the GA settings. :func:`load_scenario` reads a bundled one by name or a file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from implantplan import models
from implantplan.systems import actuator as act
from implantplan.systems import validate as v
from implantplan.systems.errors import InputError
from implantplan.systems.files import read_yaml
from implantplan.systems.frames import rpy_to_rotation, transform


@dataclass(frozen=True)
class Obstacle:
    """A patient/chair primitive in the world frame: a capsule (p0, p1, radius) or a box."""

    name: str
    kind: str  # "capsule" | "box"
    p0: np.ndarray = field(default_factory=lambda: np.zeros(3))
    p1: np.ndarray = field(default_factory=lambda: np.zeros(3))
    radius: float = 0.0
    X_WB: np.ndarray = field(default_factory=lambda: np.eye(4))  # box centre pose
    half_size: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True)
class Actuator:
    """Implanting actuator geometry (m), defaults = systems.actuator's modelled actuator: the rod
    along the flange +z to the TCP (End) at ``rod_length`` with the flange's axes, the head at the
    TCP; an optional motor body (``body_length`` > 0) from the flange face. ``rod_length`` sets
    the TCP (:meth:`X_FT`); the collision shapes are the plant's actuator URDF
    (systems.robot.arm_collision), the other fields are read and validated for the file format.
    The scenario's ``actuator:`` section (keys ``<field>_m``)."""

    rod_length: float = v.spec(v.positive, act.ROD_LENGTH, key="rod_length_m")
    rod_radius: float = v.spec(v.positive, act.ROD_RADIUS, key="rod_radius_m")
    head_radius: float = v.spec(v.positive, act.HEAD_RADIUS, key="head_radius_m")
    implant_length: float = v.spec(v.nonneg, act.IMPLANT_LENGTH, key="implant_length_m")
    implant_radius: float = v.spec(v.nonneg, act.IMPLANT_RADIUS, key="implant_radius_m")
    body_length: float = v.spec(v.nonneg, 0.0, key="body_length_m")
    body_radius: float = v.spec(v.nonneg, 0.0, key="body_radius_m")

    def X_FT(self) -> np.ndarray:
        """TCP in the flange frame, translation (0, 0, rod_length) (systems.actuator.X_FT)."""
        return act.X_FT(self.rod_length)


@dataclass(frozen=True)
class Scenario:
    """A placement problem (see models/scenarios/*.yaml for the file format).

    Attributes:
        name, posture: labels ("lying" / "sitting" for the bundled ones).
        X_WO: Oral (feeding target) pose in the world.
        lower, upper: (3,) bounds of the base position in Oral (m).
        joint2_range: (2,) condition 1, joint 2 range in rad.
        X_BC, cabinet_half: cabinet/cart box below the base, pose in Base and half sizes (m).
        obstacles: patient and chair primitives in the world.
        actuator: actuator geometry; X_FT its TCP in the flange frame.
        eps: joint error radius (rad) of the error range index.
        feed_length: m; feed_samples: poses along the feed (>= 2).
        clearance: minimum capsule clearance (m) counted as collision-free.
        max_joint_step: largest joint step between feed samples still counted continuous (rad).
        limits: "175" or "360" (AUBO variants).
        joint_headroom: the smallest distance (rad) every joint keeps from its limit along the
            feed and under the head motions (DESIGN.md section 7; default 10 deg).
        head_translation, head_rotation: the envelope of the head motions the feed must follow
            (m, rad): breathing (<= 2 mm), a swallow (<= 5 mm) and a minute of drift (<= 5 mm,
            1 deg); a startle is not followed (the head guard stops and backs out).
        pop, gen, seed, patience, hv_tol: NSGA-II settings.
        percentile_samples: random feasible bases for the percentile ranks.
    """

    name: str
    posture: str
    X_WO: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    joint2_range: np.ndarray
    X_BC: np.ndarray
    cabinet_half: np.ndarray
    obstacles: tuple[Obstacle, ...]
    actuator: Actuator
    X_FT: np.ndarray
    eps: float
    feed_length: float
    feed_samples: int
    clearance: float
    max_joint_step: float
    limits: str
    joint_headroom: float
    head_translation: float
    head_rotation: float
    pop: int
    gen: int
    seed: int
    patience: int | None
    hv_tol: float
    percentile_samples: int


BUNDLED = ("lying", "sitting")


def scenario_path(name: str) -> Path:
    """Path of a bundled scenario file (models/scenarios/NAME.yaml)."""
    return models.MODELS_DIR / "scenarios" / f"{name}.yaml"


def load_scenario(spec: str | Path, *, X_FT=None) -> Scenario:
    """Load and validate a scenario: a bundled name (``lying``/``sitting``) or a YAML file path.

    Args:
        spec: name or path.
        X_FT: TCP pose in the flange frame overriding the one built from the file's actuator
            section (e.g. diagrams.actuator_urdf.X_FT of the modelled actuator).
    """
    path = scenario_path(str(spec)) if str(spec) in BUNDLED else Path(spec)
    data = read_yaml(path, field="scenario")
    try:
        return scenario_from_dict(data, X_FT=X_FT, source=str(path))
    except InputError as exc:  # say which file: a case names its scenario by path
        raise InputError(exc.field, f"{exc.message} (in the scenario file {path})") from None


# -- the file's schema (systems.validate typed sections; m and deg as the keys say) --------------


def _sizes(value, where: str) -> np.ndarray:
    size = v.vec3(value, where)
    if np.any(size <= 0):
        raise InputError(where, "expected positive sizes")
    return size


def _bounds(value, where: str) -> np.ndarray:
    pair = v.vector(value, where, 2)
    if not pair[0] < pair[1]:
        raise InputError(where, f"expected [lower, upper] with lower < upper, got {pair.tolist()} "
                         "(inverted or empty bounds)")
    return pair


@dataclass(frozen=True)
class PoseSpec:
    """``{xyz_m: [x, y, z], rpy_deg: [r, p, y]}`` (rpy optional, default 0)."""

    xyz: np.ndarray = v.spec(v.vec3, key="xyz_m")
    rpy_deg: np.ndarray = v.spec(v.vec3, [0, 0, 0])

    @property
    def X(self) -> np.ndarray:
        return transform(rpy_to_rotation(np.deg2rad(self.rpy_deg)), self.xyz)


@dataclass(frozen=True)
class BaseBoundsSpec:
    """``base_bounds_m``: [lower, upper] of the base position in Oral per axis (m)."""

    x: np.ndarray = v.spec(_bounds)
    y: np.ndarray = v.spec(_bounds)
    z: np.ndarray = v.spec(_bounds)


@dataclass(frozen=True)
class CabinetBoxSpec:
    center: np.ndarray = v.spec(v.vec3, key="center_m")
    size: np.ndarray = v.spec(_sizes, key="size_m")


@dataclass(frozen=True)
class CabinetSpec:
    """``cabinet``: condition 1's joint-2 range and the cart box below the base (in Base)."""

    joint2_range_deg: np.ndarray = v.spec(v.interval)
    box: CabinetBoxSpec = v.spec(v.section(CabinetBoxSpec))


@dataclass(frozen=True, kw_only=True)
class CapsuleSpec:
    name: str | None = v.spec(v.label, None)
    type: str = v.spec(v.one_of("capsule"))
    p0: np.ndarray = v.spec(v.vec3, key="p0_m")
    p1: np.ndarray = v.spec(v.vec3, key="p1_m")
    radius: float = v.spec(v.positive, key="radius_m")


@dataclass(frozen=True, kw_only=True)
class BoxSpec:
    name: str | None = v.spec(v.label, None)
    type: str = v.spec(v.one_of("box"))
    center: np.ndarray = v.spec(v.vec3, key="center_m")
    size: np.ndarray = v.spec(_sizes, key="size_m")
    rpy_deg: np.ndarray = v.spec(v.vec3, [0, 0, 0])


def _obstacles(value, where: str) -> tuple:
    if not isinstance(value, list):
        raise InputError(where, f"expected a list of obstacles, got {value!r}")
    kind = v.variant("type", capsule=CapsuleSpec, box=BoxSpec)
    return tuple(kind(item, f"{where}[{i}]") for i, item in enumerate(value))


@dataclass(frozen=True)
class GaSpec:
    """``ga``: the NSGA-II settings (``patience: null`` = no stagnation stop)."""

    pop: int = v.spec(partial(v.integer, low=4), 500)
    gen: int = v.spec(partial(v.integer, low=1), 500)
    patience: int | None = v.spec(partial(v.integer, low=1), 20, nullable=True)
    hv_tol: float = v.spec(v.nonneg, 1e-3)


@dataclass(frozen=True)
class HeadEnvelopeSpec:
    """``head_motion:`` the head motions a feed must follow with the joint headroom kept: a
    translation up to ``translation_mm`` along each Oral axis and a rotation up to
    ``rotation_deg`` about each, about the Oral origin (the mouth)."""

    translation_mm: float = v.spec(partial(v.number, low=0.0, high=50.0), 5.0)
    rotation_deg: float = v.spec(partial(v.number, low=0.0, high=20.0), 1.0)


@dataclass(frozen=True, kw_only=True)
class ScenarioFile:
    """The scenario file as written; :func:`scenario_from_dict` turns it into a
    :class:`Scenario`."""

    schema_version: int = v.spec(v.version(1))
    name: str | None = v.spec(v.label, None)
    posture: str = v.spec(v.one_of("lying", "sitting", "other"))
    oral: PoseSpec = v.spec(v.section(PoseSpec))
    base_bounds_m: BaseBoundsSpec = v.spec(v.section(BaseBoundsSpec))
    cabinet: CabinetSpec = v.spec(v.section(CabinetSpec))
    obstacles: tuple = v.spec(_obstacles, [])
    actuator: Actuator = v.spec(v.section(Actuator), {})
    joint_error_deg: float = v.spec(v.positive)
    feed_length_m: float = v.spec(v.positive)
    feed_samples: int = v.spec(partial(v.integer, low=2), 11)
    clearance_m: float = v.spec(v.nonneg, 0.005)
    max_joint_step_deg: float = v.spec(v.positive, 20.0)
    joint_limits_deg: str = v.spec(lambda x, w: v.choice(str(x), w, ("175", "360")), "175")
    joint_headroom_deg: float = v.spec(partial(v.number, low=0.0, high=90.0), 10.0)
    head_motion: HeadEnvelopeSpec = v.spec(v.section(HeadEnvelopeSpec), {})
    ga: GaSpec = v.spec(v.section(GaSpec), {})
    percentile_samples: int = v.spec(partial(v.integer, low=1), 2000)
    seed: int = v.spec(partial(v.integer, low=0), 0)


def _obstacle(k: int, ob) -> Obstacle:
    name = f"obstacle{k}" if ob.name is None else ob.name
    if isinstance(ob, CapsuleSpec):
        return Obstacle(name=name, kind="capsule", p0=ob.p0, p1=ob.p1, radius=ob.radius)
    return Obstacle(name=name, kind="box",
                    X_WB=transform(rpy_to_rotation(np.deg2rad(ob.rpy_deg)), ob.center),
                    half_size=ob.size / 2)


def scenario_from_dict(data: dict, *, X_FT=None, source: str = "scenario") -> Scenario:
    """Validate a scenario mapping (as read from YAML, :class:`ScenarioFile`); every error names
    the field."""
    f = v.parse(ScenarioFile, data, "")
    b = f.base_bounds_m
    return Scenario(
        name=Path(source).stem if f.name is None else f.name,
        posture=f.posture,
        X_WO=f.oral.X,
        lower=np.array([b.x[0], b.y[0], b.z[0]]),
        upper=np.array([b.x[1], b.y[1], b.z[1]]),
        joint2_range=np.deg2rad(f.cabinet.joint2_range_deg),
        X_BC=transform(np.eye(3), f.cabinet.box.center),
        cabinet_half=f.cabinet.box.size / 2,
        obstacles=tuple(_obstacle(k, ob) for k, ob in enumerate(f.obstacles)),
        actuator=f.actuator,
        X_FT=f.actuator.X_FT() if X_FT is None else v.pose(X_FT, "X_FT"),
        eps=np.deg2rad(f.joint_error_deg),
        feed_length=f.feed_length_m,
        feed_samples=f.feed_samples,
        clearance=f.clearance_m,
        max_joint_step=np.deg2rad(f.max_joint_step_deg),
        limits=f.joint_limits_deg,
        joint_headroom=np.deg2rad(f.joint_headroom_deg),
        head_translation=f.head_motion.translation_mm * 1e-3,
        head_rotation=np.deg2rad(f.head_motion.rotation_deg),
        pop=f.ga.pop,
        gen=f.ga.gen,
        seed=f.seed,
        patience=f.ga.patience,
        hv_tol=f.ga.hv_tol,
        percentile_samples=f.percentile_samples,
    )
