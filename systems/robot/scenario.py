"""The MOPRP scenario schema (models/scenarios/*.yaml; DESIGN.md section 5): typed dataclasses
read from YAML, every error naming its field (through systems.validate).

A scenario is the room and the problem of one robot placement: the Oral (feeding target) pose in
World, the bounds of the base position in Oral, the cart under the base and condition 1's joint-2
range, the patient and chair obstacles, the actuator, the index settings (joint error, feed),
the clearance, and the GA settings. :func:`load_scenario` reads a bundled one by name or a file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from implantplan import models
from implantplan.systems import actuator as act
from implantplan.systems import validate
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
    (systems.robot.arm_collision), the other fields are read and validated for the file format."""

    rod_length: float = act.ROD_LENGTH
    rod_radius: float = act.ROD_RADIUS
    head_radius: float = act.HEAD_RADIUS
    implant_length: float = act.IMPLANT_LENGTH
    implant_radius: float = act.IMPLANT_RADIUS
    body_length: float = 0.0
    body_radius: float = 0.0

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
    pop: int
    gen: int
    seed: int
    patience: int | None
    hv_tol: float
    percentile_samples: int


BUNDLED = ("lying", "sitting")
_req = validate.require


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
    return scenario_from_dict(data, X_FT=X_FT, source=str(path))


def _pose(d, field_name: str) -> np.ndarray:
    d = validate.mapping(d, field_name)
    xyz = validate.vector(_req(d, "xyz_m", field_name + "."), field_name + ".xyz_m", 3)
    rpy = validate.vector(d.get("rpy_deg", [0, 0, 0]), field_name + ".rpy_deg", 3)
    return transform(rpy_to_rotation(np.deg2rad(rpy)), xyz)


def scenario_from_dict(data: dict, *, X_FT=None, source: str = "scenario") -> Scenario:
    """Validate a scenario mapping (as read from YAML); every error names the field."""
    if not isinstance(data, dict):
        raise InputError("scenario", f"{source} must be a mapping")
    version = data.get("schema_version")
    if version != 1:
        raise InputError("schema_version", f"expected 1, got {version!r}")
    name = str(data.get("name", Path(source).stem))
    posture = data.get("posture")
    if posture not in ("lying", "sitting", "other"):
        raise InputError("posture", f"expected lying, sitting or other, got {posture!r}")
    X_WO = _pose(_req(data, "oral", ""), "oral")

    bounds = _req(data, "base_bounds_m", "")
    if not isinstance(bounds, dict):
        raise InputError("base_bounds_m", "expected a mapping with x, y, z: [lower, upper]")
    lower, upper = np.zeros(3), np.zeros(3)
    for i, axis in enumerate("xyz"):
        pair = validate.vector(_req(bounds, axis, "base_bounds_m."), f"base_bounds_m.{axis}", 2)
        if not pair[0] < pair[1]:
            raise InputError(
                f"base_bounds_m.{axis}",
                f"expected [lower, upper] with lower < upper, got {pair.tolist()} "
                "(inverted or empty bounds)",
            )
        lower[i], upper[i] = pair

    cab = _req(data, "cabinet", "")
    if not isinstance(cab, dict):
        raise InputError("cabinet", "expected a mapping")
    j2 = np.deg2rad(validate.vector(_req(cab, "joint2_range_deg", "cabinet."),
                                    "cabinet.joint2_range_deg", 2))
    if not j2[0] < j2[1]:
        raise InputError("cabinet.joint2_range_deg", "expected [lower, upper] with lower < upper")
    box = _req(cab, "box", "cabinet.")
    if not isinstance(box, dict):
        raise InputError("cabinet.box", "expected a mapping with center_m and size_m")
    X_BC = transform(np.eye(3), validate.vector(_req(box, "center_m", "cabinet.box."),
                                     "cabinet.box.center_m", 3))
    size = validate.vector(_req(box, "size_m", "cabinet.box."), "cabinet.box.size_m", 3)
    if np.any(size <= 0):
        raise InputError("cabinet.box.size_m", "expected positive sizes")

    obstacles = []
    for k, ob in enumerate(data.get("obstacles", []) or []):
        where = f"obstacles[{k}]"
        if not isinstance(ob, dict):
            raise InputError(where, "expected a mapping")
        kind = ob.get("type")
        oname = str(ob.get("name", f"obstacle{k}"))
        if kind == "capsule":
            obstacles.append(Obstacle(
                name=oname, kind="capsule",
                p0=validate.vector(_req(ob, "p0_m", where + "."), where + ".p0_m", 3),
                p1=validate.vector(_req(ob, "p1_m", where + "."), where + ".p1_m", 3),
                radius=validate.number(_req(ob, "radius_m", where + "."), where + ".radius_m",
                                       positive=True),
            ))
        elif kind == "box":
            bsize = validate.vector(_req(ob, "size_m", where + "."), where + ".size_m", 3)
            if np.any(bsize <= 0):
                raise InputError(where + ".size_m", "expected positive sizes")
            rpy = validate.vector(ob.get("rpy_deg", [0, 0, 0]), where + ".rpy_deg", 3)
            obstacles.append(Obstacle(
                name=oname, kind="box",
                X_WB=transform(rpy_to_rotation(np.deg2rad(rpy)),
                               validate.vector(_req(ob, "center_m", where + "."),
                                               where + ".center_m", 3)),
                half_size=bsize / 2,
            ))
        else:
            raise InputError(where + ".type", f"expected capsule or box, got {kind!r}")

    act = data.get("actuator", {}) or {}
    if not isinstance(act, dict):
        raise InputError("actuator", "expected a mapping")
    defaults = Actuator()
    actuator = Actuator(**{
        key: validate.number(act.get(f"{key}_m", getattr(defaults, key)), f"actuator.{key}_m",
                  positive=key.startswith(("rod", "head")), nonneg=True)
        for key in ("rod_length", "rod_radius", "head_radius", "implant_length",
                    "implant_radius", "body_length", "body_radius")
    })
    X_FT = actuator.X_FT() if X_FT is None else validate.pose(X_FT, "X_FT")

    eps = np.deg2rad(validate.number(_req(data, "joint_error_deg", ""), "joint_error_deg",
                                     positive=True))
    feed_length = validate.number(_req(data, "feed_length_m", ""), "feed_length_m", positive=True)
    feed_samples = int(validate.number(data.get("feed_samples", 11), "feed_samples", positive=True,
                            integer=True))
    if feed_samples < 2:
        raise InputError("feed_samples", f"expected >= 2 samples, got {feed_samples}")
    clearance = validate.number(data.get("clearance_m", 0.005), "clearance_m", nonneg=True)
    step = np.deg2rad(validate.number(data.get("max_joint_step_deg", 20.0), "max_joint_step_deg",
                           positive=True))
    limits = str(data.get("joint_limits_deg", "175"))
    if limits not in ("175", "360"):
        raise InputError("joint_limits_deg", f"expected 175 or 360, got {limits!r}")

    ga = data.get("ga", {}) or {}
    if not isinstance(ga, dict):
        raise InputError("ga", "expected a mapping")
    pop = int(validate.number(ga.get("pop", 500), "ga.pop", positive=True, integer=True))
    gen = int(validate.number(ga.get("gen", 500), "ga.gen", positive=True, integer=True))
    if pop < 4:
        raise InputError("ga.pop", f"expected at least 4, got {pop}")
    patience = ga.get("patience", 20)
    if patience is not None:
        patience = int(validate.number(patience, "ga.patience", positive=True, integer=True))
    hv_tol = validate.number(ga.get("hv_tol", 1e-3), "ga.hv_tol", nonneg=True)
    seed = int(validate.number(data.get("seed", 0), "seed", nonneg=True, integer=True))
    n_pct = int(validate.number(data.get("percentile_samples", 2000), "percentile_samples",
                                positive=True, integer=True))

    return Scenario(
        name=name, posture=posture, X_WO=X_WO, lower=lower, upper=upper, joint2_range=j2,
        X_BC=X_BC, cabinet_half=size / 2, obstacles=tuple(obstacles), actuator=actuator,
        X_FT=X_FT, eps=eps, feed_length=feed_length, feed_samples=feed_samples,
        clearance=clearance, max_joint_step=step, limits=limits, pop=pop, gen=gen, seed=seed,
        patience=patience, hv_tol=hv_tol, percentile_samples=n_pct,
    )
