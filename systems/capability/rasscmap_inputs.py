"""RASSCMAP inputs (seed 004 Listings 1-3): the patient (body part, access), the task poses and
the robot (capability map, base pose ranges), read from YAML with field-named errors.

Everything in world W (z up), metres and radians in the dataclasses; the files give angles in
degrees (``*_deg``). Relative paths in a robot file are relative to that file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from implantplan.systems import validate as v
from implantplan.systems.capability.rasscmap import Instrument, Trocar, arc_radius
from implantplan.systems.errors import InputError
from implantplan.systems.files import read_yaml
from implantplan.systems.frames import rot_z, rpy_to_rotation, transform

# -- file schemas (systems.validate typed sections) ----------------------------------------------


@dataclass(frozen=True)
class PoseSpec:
    """``{xyz: [m, m, m], rpy_deg: [deg, deg, deg], id: name}`` (rpy_deg optional, default 0)."""

    xyz: np.ndarray = v.spec(v.vec3)
    rpy_deg: np.ndarray = v.spec(v.vec3, [0.0, 0.0, 0.0])
    id: str | None = v.spec(v.label, None)

    @property
    def X(self) -> np.ndarray:
        return transform(rpy_to_rotation(np.deg2rad(self.rpy_deg)), self.xyz)


@dataclass(frozen=True)
class BodySpec:
    arc_length: float = v.spec(v.positive)
    chord: float = v.spec(v.positive)
    length: float = v.spec(v.positive)


@dataclass(frozen=True)
class TrocarSpec:
    cannula_length: float = v.spec(v.nonneg, 0.05)
    alpha_max_deg: float = v.spec(partial(v.number, positive=True, high=90.0), 90.0)
    beta_max_deg: float = v.spec(partial(v.number, positive=True, high=90.0), 90.0)


@dataclass(frozen=True)
class InstrumentSpec:
    shaft_length: float = v.spec(v.positive, 0.40)
    instrument_length: float = v.spec(v.positive, 0.02)
    joint_limit_deg: float = v.spec(partial(v.number, positive=True, high=90.0), 90.0)


@dataclass(frozen=True)
class PatientSpec:
    id: str = v.spec(v.label)
    access: str = v.spec(v.one_of("unconstrained", "constrained"))
    pose: PoseSpec = v.spec(v.section(PoseSpec))
    voxel_size: float = v.spec(v.positive)
    map_depth: float = v.spec(v.nonneg)
    rotation_step_deg: float = v.spec(v.positive, 5.0)
    translation_step: float = v.spec(v.positive, 0.05)
    body: BodySpec | None = v.spec(v.section(BodySpec), None)
    access_points: tuple | None = v.spec(v.sections(PoseSpec, min_items=1), None)
    trocar: TrocarSpec = v.spec(v.section(TrocarSpec), {})
    instrument: InstrumentSpec = v.spec(v.section(InstrumentSpec), {})


@dataclass(frozen=True)
class BoxSpec:
    """A grid of task positions: ``counts`` points per axis from ``min`` to ``max`` (m)."""

    min: np.ndarray = v.spec(v.vec3)
    max: np.ndarray = v.spec(v.vec3)
    counts: tuple = v.spec(lambda c, w: tuple(v.integer(x, f"{w}[{i}]", low=1)
                                              for i, x in enumerate(_three(c, w))))
    rpy_deg: np.ndarray = v.spec(v.vec3, [0.0, 0.0, 0.0])


def _three(value, where: str) -> list:
    if not isinstance(value, list) or len(value) != 3:
        raise InputError(where, f"expected 3 positive integers, got {value!r}")
    return value


@dataclass(frozen=True)
class TaskSpec:
    id: str = v.spec(v.label)
    poses: tuple = v.spec(v.sections(PoseSpec), [])
    boxes: tuple = v.spec(v.sections(BoxSpec), [])


def _range(value, where: str) -> np.ndarray:
    """A base range axis: [min, max] or one number (min = max)."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value, value]
    pair = v.vector(value, where, 2)
    if pair[1] < pair[0]:
        raise InputError(where, f"expected [min, max] with min <= max, got {value!r}")
    return pair


@dataclass(frozen=True)
class BaseRangeSpec:
    x: np.ndarray = v.spec(_range, 0.0)
    y: np.ndarray = v.spec(_range, 0.0)
    z: np.ndarray = v.spec(_range, 0.0)
    yaw_deg: np.ndarray = v.spec(_range, 0.0)


def _limits(value, where: str) -> str:
    return v.choice(str(value), where, ("175", "360"))


@dataclass(frozen=True)
class MapBuildSpec:
    """``build``: how ``capmap plan`` builds the robot's map when its file is missing (the
    options of ``capmap build``; ``limits`` None: the robot's)."""

    voxel_mm: float = v.spec(v.positive, 50.0)
    directions: int = v.spec(partial(v.integer, low=1), 100)
    limits: str | None = v.spec(_limits, None)
    tool: str | None = v.spec(v.one_of("flange", "actuator"), None)
    rolls: int | None = v.spec(partial(v.integer, low=1), None)
    workers: int | None = v.spec(partial(v.integer, low=1), None)
    self_collision: bool = v.spec(v.boolean, False)
    cell: str = v.spec(v.one_of("certified", "centre"), "certified")


@dataclass(frozen=True)
class RobotSpec:
    name: str = v.spec(v.label)
    map: str = v.spec(v.text)
    base_ranges: tuple = v.spec(v.sections(BaseRangeSpec, min_items=1))
    translation_step: float = v.spec(v.positive, 0.05)
    rotation_step_deg: float = v.spec(v.positive, 5.0)
    store: str | None = v.spec(v.text, None)
    build: MapBuildSpec | None = v.spec(v.section(MapBuildSpec), None)
    limits: str | None = v.spec(_limits, None)


def _file(path, key: str, cls):
    """The ``key:`` section of a YAML file, parsed as ``cls``."""
    data = read_yaml(path, field=key)
    if not isinstance(data, dict) or not isinstance(data.get(key), dict):
        raise InputError(key, "missing or not a mapping")
    v.unknown_keys(data, (key,), "")
    return v.parse(cls, data[key], key)


# -- what the planner uses (SI) ------------------------------------------------------------------


@dataclass
class Patient:
    """Listing 1: id, body-part pose, voxel size, map depth, access (points or body measures)."""

    id: str
    X_WP: np.ndarray
    voxel: float
    depth: float
    access: str
    d_rot: float
    d_trans: float
    body: dict | None = None
    access_points: list = field(default_factory=list)  # [(id, X_WA)]
    trocar: Trocar | None = None
    instrument: Instrument | None = None


def load_patient(path) -> Patient:
    """Read and validate a patient YAML (Listing 1)."""
    f = _file(path, "patient", PatientSpec)
    pat = Patient(f.id, f.pose.X, f.voxel_size, f.map_depth, f.access,
                  np.deg2rad(f.rotation_step_deg), f.translation_step)
    if f.access == "unconstrained":
        if f.body is None:
            raise InputError("patient.body", "missing or not a mapping")
        b = f.body
        arc_radius(b.arc_length, b.chord, field="patient.body")
        pat.body = {"arc_length": b.arc_length, "chord": b.chord, "length": b.length}
    else:
        if f.access_points is None:
            raise InputError("patient.access_points", "expected a non-empty list of poses")
        pat.access_points = [(ap.id or f"AP{i + 1}", ap.X) for i, ap in enumerate(f.access_points)]
        pat.trocar = Trocar(cannula_length=f.trocar.cannula_length, depth=f.map_depth,
                            alpha_max=np.deg2rad(f.trocar.alpha_max_deg),
                            beta_max=np.deg2rad(f.trocar.beta_max_deg))
        pat.instrument = Instrument(shaft_length=f.instrument.shaft_length,
                                    instrument_length=f.instrument.instrument_length,
                                    joint_limit=np.deg2rad(f.instrument.joint_limit_deg))
    return pat


@dataclass
class Task:
    """Listing 2: task id and task poses in W (z = approach direction of the mapped frame)."""

    id: str
    poses: np.ndarray


def load_task(path) -> Task:
    """Read a task YAML (Listing 2): ``poses`` (list of xyz/rpy_deg) and/or ``boxes`` (grids)."""
    f = _file(path, "task", TaskSpec)
    poses = [p.X for p in f.poses]
    for i, b in enumerate(f.boxes):
        if np.any(b.max < b.min):
            raise InputError(f"task.boxes[{i}]", "max must be >= min on every axis")
        R = rpy_to_rotation(np.deg2rad(b.rpy_deg))
        axes = [np.linspace(b.min[k], b.max[k], b.counts[k]) for k in range(3)]
        g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        poses.extend(transform(np.broadcast_to(R, (len(g), 3, 3)), g))
    if not poses:
        raise InputError("task.poses", "expected at least one task pose (poses or boxes)")
    return Task(f.id, np.stack(poses))


@dataclass
class BaseRange:
    """One range of base poses (Listing 3): x, y, z (m) and yaw (rad) intervals."""

    lo: np.ndarray  # (4,) x, y, z, yaw
    hi: np.ndarray
    step: np.ndarray  # (4,) translation, translation, translation, rotation

    def axes(self) -> list[np.ndarray]:
        return [
            self.lo[k]
            + self.step[k]
            * np.arange(int(np.floor((self.hi[k] - self.lo[k]) / self.step[k] + 1e-9)) + 1)
            for k in range(4)
        ]

    @property
    def dims(self) -> tuple[int, int, int, int]:
        return tuple(len(a) for a in self.axes())


@dataclass
class Robot:
    """Listing 3: robot name, CMAP path, base pose ranges, store, optional map build params."""

    name: str
    map_path: Path
    ranges: list
    store: Path | None = None
    build: MapBuildSpec | None = None
    limits: str | None = None


def load_robot(path) -> Robot:
    """Read and validate a robot YAML (Listing 3); relative paths are relative to the file."""
    path = Path(path)
    f = _file(path, "robot", RobotSpec)
    step = np.array([f.translation_step] * 3 + [np.deg2rad(f.rotation_step_deg)])
    scale = np.array([1.0, 1.0, 1.0, np.pi / 180])
    ranges = []
    for r in f.base_ranges:
        pairs = np.stack([r.x, r.y, r.z, r.yaw_deg]) * scale[:, None]
        ranges.append(BaseRange(pairs[:, 0].copy(), pairs[:, 1].copy(), step.copy()))
    return Robot(
        f.name, (path.parent / f.map).resolve(), ranges,
        (path.parent / f.store).resolve() if f.store else None, f.build, f.limits,
    )  # fmt: skip


def base_candidates(ranges: list) -> tuple[np.ndarray, np.ndarray]:
    """All base poses X_WB (n, 4, 4) and their grid coordinates (n, 5): range, ix, iy, iz, iyaw."""
    poses, coords = [], []
    for ri, r in enumerate(ranges):
        ax = r.axes()
        grid = np.stack(np.meshgrid(*[np.arange(len(a)) for a in ax], indexing="ij"), -1).reshape(
            -1, 4
        )
        vals = np.stack([ax[k][grid[:, k]] for k in range(4)], axis=-1)
        poses.append(transform(rot_z(vals[:, 3]), vals[:, :3]))
        coords.append(np.concatenate([np.full((len(grid), 1), ri), grid], axis=1))
    return np.concatenate(poses), np.concatenate(coords)
