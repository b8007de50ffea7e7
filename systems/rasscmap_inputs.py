"""RASSCMAP inputs (seed 004 Listings 1-3): the patient (body part, access), the task poses and
the robot (capability map, base pose ranges), read from YAML with field-named errors.

Everything in world W (z up), metres and radians in the dataclasses; the files give angles in
degrees (``*_deg``). Relative paths in a robot file are relative to that file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from implantplan.systems.errors import InputError
from implantplan.systems.files import read_yaml
from implantplan.systems.frames import rot_z, rpy_to_rotation, transform
from implantplan.systems.rasscmap import Instrument, Trocar, arc_radius


def _num(d: dict, key: str, where: str, *, positive=True, default=None) -> float:
    if key not in d:
        if default is not None:
            return float(default)
        raise InputError(f"{where}.{key}", "missing (expected a number)")
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise InputError(f"{where}.{key}", f"expected a number, got {v!r}")
    if positive and v <= 0:
        raise InputError(f"{where}.{key}", f"expected a positive number, got {v!r}")
    if not positive and v < 0:
        raise InputError(f"{where}.{key}", f"expected a number >= 0, got {v!r}")
    return float(v)


def _vec(v, where: str, n: int = 3) -> np.ndarray:
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise InputError(where, f"expected a list of {n} numbers, got {v!r}")
    out = []
    for x in v:
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not np.isfinite(x):
            raise InputError(where, f"expected a list of {n} numbers, got {v!r}")
        out.append(float(x))
    return np.array(out)


def parse_pose(d, where: str) -> np.ndarray:
    """``{xyz: [m, m, m], rpy_deg: [deg, deg, deg]}`` -> 4x4 (rpy_deg optional, default 0)."""
    if not isinstance(d, dict) or "xyz" not in d:
        raise InputError(where, "expected a mapping with 'xyz' (m) and optional 'rpy_deg'")
    unknown = set(d) - {"xyz", "rpy_deg", "id"}
    if unknown:
        raise InputError(where, f"unknown keys {sorted(unknown)} (expected xyz, rpy_deg)")
    p = _vec(d["xyz"], f"{where}.xyz")
    rpy = np.deg2rad(_vec(d.get("rpy_deg", [0, 0, 0]), f"{where}.rpy_deg"))
    return transform(rpy_to_rotation(rpy), p)


def _mapping(data: dict, key: str, where: str) -> dict:
    v = data.get(key)
    if not isinstance(v, dict):
        raise InputError(f"{where}.{key}" if where else key, "missing or not a mapping")
    return v


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
    data = _mapping(read_yaml(path, field="patient"), "patient", "")
    w = "patient"
    pid = str(data.get("id", ""))
    if not pid:
        raise InputError("patient.id", "missing (expected a non-empty id)")
    X_WP = parse_pose(data.get("pose"), "patient.pose")
    voxel = _num(data, "voxel_size", w)
    depth = _num(data, "map_depth", w, positive=False)
    d_rot = np.deg2rad(_num(data, "rotation_step_deg", w, default=5.0))
    d_trans = _num(data, "translation_step", w, default=0.05)
    access = data.get("access")
    if access not in ("unconstrained", "constrained"):
        raise InputError(
            "patient.access", f"expected 'unconstrained' or 'constrained', got {access!r}"
        )
    pat = Patient(pid, X_WP, voxel, depth, access, d_rot, d_trans)
    if access == "unconstrained":
        body = _mapping(data, "body", w)
        a = _num(body, "arc_length", "patient.body")
        c = _num(body, "chord", "patient.body")
        ln = _num(body, "length", "patient.body")
        arc_radius(a, c, field="patient.body")
        pat.body = {"arc_length": a, "chord": c, "length": ln}
    else:
        aps = data.get("access_points")
        if not isinstance(aps, list) or not aps:
            raise InputError("patient.access_points", "expected a non-empty list of poses")
        for i, ap in enumerate(aps):
            X = parse_pose(ap, f"patient.access_points[{i}]")
            pat.access_points.append((str(ap.get("id", f"AP{i + 1}")), X))
        tr = data.get("trocar", {})
        if not isinstance(tr, dict):
            raise InputError("patient.trocar", "expected a mapping")
        pat.trocar = Trocar(
            cannula_length=_num(
                tr, "cannula_length", "patient.trocar", positive=False, default=0.05
            ),
            depth=depth,
            alpha_max=np.deg2rad(_num(tr, "alpha_max_deg", "patient.trocar", default=90.0)),
            beta_max=np.deg2rad(_num(tr, "beta_max_deg", "patient.trocar", default=90.0)),
        )
        if pat.trocar.alpha_max > np.pi / 2 + 1e-12 or pat.trocar.beta_max > np.pi / 2 + 1e-12:
            raise InputError("patient.trocar", "alpha_max_deg and beta_max_deg must be <= 90")
        ins = data.get("instrument", {})
        if not isinstance(ins, dict):
            raise InputError("patient.instrument", "expected a mapping")
        pat.instrument = Instrument(
            shaft_length=_num(ins, "shaft_length", "patient.instrument", default=0.40),
            instrument_length=_num(ins, "instrument_length", "patient.instrument", default=0.02),
            joint_limit=np.deg2rad(
                _num(ins, "joint_limit_deg", "patient.instrument", default=90.0)
            ),
        )
        if pat.instrument.joint_limit > np.pi / 2 + 1e-12:
            raise InputError("patient.instrument.joint_limit_deg", "must be <= 90")
    return pat


@dataclass
class Task:
    """Listing 2: task id and task poses in W (z = approach direction of the mapped frame)."""

    id: str
    poses: np.ndarray


def load_task(path) -> Task:
    """Read a task YAML (Listing 2): ``poses`` (list of xyz/rpy_deg) and/or ``boxes`` (grids)."""
    data = _mapping(read_yaml(path, field="task"), "task", "")
    tid = str(data.get("id", ""))
    if not tid:
        raise InputError("task.id", "missing (expected a non-empty id)")
    poses = []
    for i, p in enumerate(data.get("poses", []) or []):
        poses.append(parse_pose(p, f"task.poses[{i}]"))
    for i, b in enumerate(data.get("boxes", []) or []):
        w = f"task.boxes[{i}]"
        if not isinstance(b, dict):
            raise InputError(w, "expected a mapping with min, max, counts, rpy_deg")
        lo, hi = _vec(b.get("min"), f"{w}.min"), _vec(b.get("max"), f"{w}.max")
        counts = b.get("counts")
        if not (
            isinstance(counts, list)
            and len(counts) == 3
            and all(isinstance(c, int) and c >= 1 for c in counts)
        ):
            raise InputError(f"{w}.counts", f"expected 3 positive integers, got {counts!r}")
        if np.any(hi < lo):
            raise InputError(w, "max must be >= min on every axis")
        R = rpy_to_rotation(np.deg2rad(_vec(b.get("rpy_deg", [0, 0, 0]), f"{w}.rpy_deg")))
        axes = [np.linspace(lo[k], hi[k], counts[k]) for k in range(3)]
        g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        poses.extend(transform(np.broadcast_to(R, (len(g), 3, 3)), g))
    if not poses:
        raise InputError("task.poses", "expected at least one task pose (poses or boxes)")
    return Task(tid, np.stack(poses))


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
    build: dict | None = None
    limits: str | None = None


def load_robot(path) -> Robot:
    """Read and validate a robot YAML (Listing 3); relative paths are relative to the file."""
    path = Path(path)
    data = _mapping(read_yaml(path, field="robot"), "robot", "")
    name = str(data.get("name", ""))
    if not name:
        raise InputError("robot.name", "missing (expected the robot's name)")
    if not isinstance(data.get("map"), str):
        raise InputError("robot.map", "missing (expected the path of the capability map .h5)")
    map_path = (path.parent / data["map"]).resolve()
    t_step = _num(data, "translation_step", "robot", default=0.05)
    r_step = np.deg2rad(_num(data, "rotation_step_deg", "robot", default=5.0))
    ranges = []
    raw = data.get("base_ranges")
    if not isinstance(raw, list) or not raw:
        raise InputError("robot.base_ranges", "expected a non-empty list of ranges")
    for i, r in enumerate(raw):
        w = f"robot.base_ranges[{i}]"
        if not isinstance(r, dict):
            raise InputError(w, "expected a mapping with x, y, z ([min, max] m) and yaw_deg")
        lo, hi = [], []
        for key, scale in (("x", 1.0), ("y", 1.0), ("z", 1.0), ("yaw_deg", np.pi / 180)):
            v = r.get(key, [0.0, 0.0])
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                v = [v, v]
            pair = _vec(v, f"{w}.{key}", 2) * scale
            if pair[1] < pair[0]:
                raise InputError(f"{w}.{key}", f"expected [min, max] with min <= max, got {v!r}")
            lo.append(pair[0])
            hi.append(pair[1])
        ranges.append(BaseRange(np.array(lo), np.array(hi), np.array([t_step] * 3 + [r_step])))
    store = data.get("store")
    build = data.get("build")
    if build is not None and not isinstance(build, dict):
        raise InputError("robot.build", "expected a mapping (voxel_mm, directions, limits)")
    limits = data.get("limits")
    if limits is not None and str(limits) not in ("175", "360"):
        raise InputError("robot.limits", f"expected '175' or '360', got {limits!r}")
    return Robot(
        name, map_path, ranges, (path.parent / store).resolve() if store else None, build,
        None if limits is None else str(limits),
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
