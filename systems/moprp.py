"""MOPRP: multi-objective preoperative robot (base) placement (seed 001; DESIGN.md section 5).

The paper's equations were lost from its text; DESIGN.md section 5 is the spec. The pipeline for
a batch of base positions p (P, 3), all vectorized:

1. **Target** (paper "Target position and posture"): End (actuator TCP) coincides with Oral, End Y
   along Oral Z, End X along -Oral Y; Base X || Oral X, Base Z || Oral Y. So the rotation Base->End
   is a constant and only the position varies: X_BE(p) = X_OB(p)^-1 X_OE (:func:`target_pose`).
2. **IK enumeration** (paper Eq. 6): all 8 closed-form branches (systems.kinematics.ik), each
   keeping its branch index, at ``feed_samples`` poses along the straight feed from the pre-feed
   pose (TCP backed out along the feeding axis, End -Z, by the feed length) to the target.
3. **Removing invalid results** (paper Eq. 7, the collision-free principle): a branch survives if
   it exists within the joint limits at every feed sample and moves continuously (no joint steps
   more than ``max_joint_step`` between samples, so the same branch is followed along the feed);
   condition 1: joint 2 within the range that keeps the upper arm off the cabinet; condition 2:
   the actuator clear of the arm's links; plus the arm clear of the patient/chair and of the
   cabinet box; collision tests with capsules (systems.collision_primitives) at the pre-feed and
   target configurations.
4. **Indices** (paper Eq. 8-22, all minimized), from the body Jacobian J = [J_w; J_v] at the target
   (:func:`indices`): dexterity I_d = max(cond J_v, cond J_w); error range I_e = eps sigma_max(J_v)
   (the largest TCP position error for a joint error ball ||dq|| <= eps, Eq. 15-19); joint variation
   I_j = sum over joints of the distance travelled along the feed (Eq. 22-23, sampled).
   The paper's Eq. 20 claims the angular error range eps sigma_max(J_w) is a constant; we compute
   it alongside (``angular_error_range``) so the claim can be checked numerically.
5. **Score-based selection** (paper Fig. 4): rank each index among a base's surviving branches,
   sum the ranks, the smallest sum wins; ties broken by the seeded generator (:func:`select`).
6. The GA's problem (:func:`evaluate_bases`): objectives (P, 3) of the selected branch, constraint
   violation (P,) (0 when some branch survives, else a graded measure of how far the best branch
   is from surviving), the branch index and q.

Departures from the paper, each for a reason: the feeding axis is the actuator's rod (End -Z),
which the paper's Fig. 6 implies but does not state; joint variation follows the sampled straight
feed on the same branch instead of only its two end configurations (the paper's Eq. 23 measures
travelled distance, not the end-to-end difference); the patient/chair and the cabinet box are
extra collision checks that the paper handled by condition 1 alone.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from implantplan import models
from implantplan.systems import actuator as act
from implantplan.systems import collision_primitives as cp
from implantplan.systems import kinematics as kin
from implantplan.systems import validate
from implantplan.systems.errors import InputError
from implantplan.systems.files import read_yaml
from implantplan.systems.frames import invert, rpy_to_rotation, transform

# Base axes in Oral (columns): Base X = Oral X, Base Y = -Oral Z, Base Z = Oral Y.
R_OB = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
# End axes in Oral (columns): End X = -Oral Y, End Y = Oral Z, End Z = X x Y = -Oral X.
R_OE = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
R_BE = R_OB.T @ R_OE
X_OE = transform(R_OE, np.zeros(3))  # End in Oral (or in Tool, for a site's target)
INDEX_NAMES = ("dexterity", "error_range", "joint_variation")

# Which capsules are tested against which (names from collision_primitives).
ACTUATOR = ("actuator_rod", "actuator_head", "actuator_implant", "actuator_body")
SELF_PAIRS = tuple(
    [(a, b) for a in ACTUATOR for b in
     ("base", "shoulder", "upper_arm_housing", "upper_arm", "forearm_housing", "forearm")]
    + [(a, b) for a in ("wrist2", "wrist3") for b in
       ("base", "shoulder", "upper_arm_housing", "upper_arm")]
    + [("forearm", "base"), ("forearm", "shoulder")]
)
# Parts tested against the patient/chair and the cabinet: the arm beyond the shoulder and the
# actuator's body. The rod and head enter the mouth by design; their clearance is seed 000's
# feeding-line safety, not this check.
ENV_PARTS = ("upper_arm", "forearm_housing", "forearm", "wrist1", "wrist2", "wrist3",
             "actuator_body")  # actuator_body only when the actuator has one


# --------------------------------------------------------------------------------------------
# Scenario
# --------------------------------------------------------------------------------------------


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
    TCP; an optional motor body (``body_length`` > 0) from the flange face."""

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

    def capsules(self) -> tuple[cp.Capsule, ...]:
        return cp.actuator_capsules(
            rod_length=self.rod_length,
            rod_radius=self.rod_radius,
            head_radius=self.head_radius,
            implant_length=self.implant_length,
            implant_radius=self.implant_radius,
            body_length=self.body_length,
            body_radius=self.body_radius,
        )


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


def scenario_path(name: str) -> Path:
    """Path of a bundled scenario file (models/scenarios/NAME.yaml)."""
    return models.MODELS_DIR / "scenarios" / f"{name}.yaml"


def load_scenario(spec: str | Path, *, X_FT=None) -> Scenario:
    """Load and validate a scenario: a bundled name (``lying``/``sitting``) or a YAML file path.

    Args:
        spec: name or path.
        X_FT: TCP pose in the flange frame overriding the one built from the file's actuator
            section (e.g. diagrams.tools.X_FT of the modelled actuator).
    """
    path = scenario_path(str(spec)) if str(spec) in BUNDLED else Path(spec)
    data = read_yaml(path, field="scenario")
    return scenario_from_dict(data, X_FT=X_FT, source=str(path))


def _get(d: dict, key: str, where: str, default=None, required=True):
    if key not in d:
        if required and default is None:
            raise InputError(f"{where}{key}", "missing")
        return default
    return d[key]


def _pose(d, field_name: str) -> np.ndarray:
    if not isinstance(d, dict):
        raise InputError(field_name, "expected a mapping with xyz_m and rpy_deg")
    xyz = validate.vector(_get(d, "xyz_m", field_name + "."), field_name + ".xyz_m", 3)
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
    X_WO = _pose(_get(data, "oral", ""), "oral")

    bounds = _get(data, "base_bounds_m", "")
    if not isinstance(bounds, dict):
        raise InputError("base_bounds_m", "expected a mapping with x, y, z: [lower, upper]")
    lower, upper = np.zeros(3), np.zeros(3)
    for i, axis in enumerate("xyz"):
        pair = validate.vector(_get(bounds, axis, "base_bounds_m."), f"base_bounds_m.{axis}", 2)
        if not pair[0] < pair[1]:
            raise InputError(
                f"base_bounds_m.{axis}",
                f"expected [lower, upper] with lower < upper, got {pair.tolist()} "
                "(inverted or empty bounds)",
            )
        lower[i], upper[i] = pair

    cab = _get(data, "cabinet", "")
    if not isinstance(cab, dict):
        raise InputError("cabinet", "expected a mapping")
    j2 = np.deg2rad(validate.vector(_get(cab, "joint2_range_deg", "cabinet."),
                                    "cabinet.joint2_range_deg", 2))
    if not j2[0] < j2[1]:
        raise InputError("cabinet.joint2_range_deg", "expected [lower, upper] with lower < upper")
    box = _get(cab, "box", "cabinet.")
    if not isinstance(box, dict):
        raise InputError("cabinet.box", "expected a mapping with center_m and size_m")
    X_BC = transform(np.eye(3), validate.vector(_get(box, "center_m", "cabinet.box."),
                                     "cabinet.box.center_m", 3))
    size = validate.vector(_get(box, "size_m", "cabinet.box."), "cabinet.box.size_m", 3)
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
                p0=validate.vector(_get(ob, "p0_m", where + "."), where + ".p0_m", 3),
                p1=validate.vector(_get(ob, "p1_m", where + "."), where + ".p1_m", 3),
                radius=validate.number(_get(ob, "radius_m", where + "."), where + ".radius_m",
                                       positive=True),
            ))
        elif kind == "box":
            bsize = validate.vector(_get(ob, "size_m", where + "."), where + ".size_m", 3)
            if np.any(bsize <= 0):
                raise InputError(where + ".size_m", "expected positive sizes")
            rpy = validate.vector(ob.get("rpy_deg", [0, 0, 0]), where + ".rpy_deg", 3)
            obstacles.append(Obstacle(
                name=oname, kind="box",
                X_WB=transform(rpy_to_rotation(np.deg2rad(rpy)),
                               validate.vector(_get(ob, "center_m", where + "."),
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
    X_FT = actuator.X_FT() if X_FT is None else kin._check_pose(X_FT, "X_FT")

    eps = np.deg2rad(validate.number(_get(data, "joint_error_deg", ""), "joint_error_deg",
                                     positive=True))
    feed_length = validate.number(_get(data, "feed_length_m", ""), "feed_length_m", positive=True)
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


# --------------------------------------------------------------------------------------------
# Target, feed, IK
# --------------------------------------------------------------------------------------------


def base_pose(xyz) -> np.ndarray:
    """X_OB (..., 4, 4): the base at position ``xyz`` in Oral with the fixed orientation R_OB."""
    return transform(R_OB, np.asarray(xyz, dtype=float))


def target_pose(xyz, X_OT=None) -> np.ndarray:
    """X_BE (..., 4, 4): the TCP target seen from the base at ``xyz``.

    The target is End = Oral rotated by R_OE (the paper's convention), or, for several implant
    sites served from one base, End = T rotated by R_OE where ``X_OT`` is the site's feeding
    target (seed 000's Tool frame) in Oral: the base keeps its orientation R_OB relative to
    Oral, only the target moves.
    """
    xyz = np.asarray(xyz, dtype=float)
    if X_OT is None:
        return transform(R_BE, -np.einsum("ji,...j->...i", R_OB, xyz))
    return invert(base_pose(xyz)) @ np.asarray(X_OT, dtype=float) @ X_OE


def feed_poses(xyz, feed_length: float, samples: int, X_OT=None) -> np.ndarray:
    """X_BE along the straight feed (..., samples, 4, 4): sample 0 is the pre-feed pose (TCP backed
    out along End -Z by ``feed_length``), the last is the target (see :func:`target_pose`)."""
    X = target_pose(xyz, X_OT)
    s = np.linspace(-feed_length, 0.0, samples)  # offset along End Z
    z_B = X[..., None, :3, 2]
    out = np.broadcast_to(X[..., None, :, :], X.shape[:-2] + (samples, 4, 4)).copy()
    out[..., :3, 3] += s[:, None] * z_B
    return out


# --------------------------------------------------------------------------------------------
# Indices (paper Eq. 8-23)
# --------------------------------------------------------------------------------------------


def _sv_extremes(A) -> tuple[np.ndarray, np.ndarray]:
    """(sigma_min, sigma_max) of (..., 3, n) matrices from the eigenvalues of A A^T."""
    ev = np.linalg.eigvalsh(A @ np.swapaxes(A, -1, -2))
    ev = np.clip(ev, 0.0, None)
    return np.sqrt(ev[..., 0]), np.sqrt(ev[..., -1])


def indices(q, q_path, *, eps: float, X_FT) -> dict[str, np.ndarray]:
    """The three MOPRP indices (and the angular error range, for the Eq. 20 check).

    Args:
        q: (..., 6) target configurations.
        q_path: (..., K, 6) configurations along the feed ending at ``q`` (same branch).
        eps: joint error radius (rad).
        X_FT: TCP in the flange frame.

    Returns:
        dict with ``dexterity`` = max(cond J_v, cond J_w) (Eq. 8-9), ``error_range`` =
        eps sigma_max(J_v) (m, Eq. 15-19), ``angular_error_range`` = eps sigma_max(J_w) (rad,
        Eq. 20), ``joint_variation`` = sum_i sum_k |q_i(k+1) - q_i(k)| (rad, Eq. 22-23).
    """
    J = kin.jacobian_body(q, X_FT)
    Jw, Jv = J[..., :3, :], J[..., 3:, :]
    wmin, wmax = _sv_extremes(Jw)
    vmin, vmax = _sv_extremes(Jv)
    with np.errstate(divide="ignore"):
        cond_w = np.where(wmin > 0, wmax / np.where(wmin > 0, wmin, 1.0), np.inf)
        cond_v = np.where(vmin > 0, vmax / np.where(vmin > 0, vmin, 1.0), np.inf)
    travel = np.abs(np.diff(np.asarray(q_path, dtype=float), axis=-2)).sum(axis=(-1, -2))
    return {
        "dexterity": np.maximum(cond_v, cond_w),
        "error_range": eps * vmax,
        "angular_error_range": eps * wmax,
        "joint_variation": travel,
    }


# --------------------------------------------------------------------------------------------
# Score-based selection (paper Fig. 4)
# --------------------------------------------------------------------------------------------


def select(values, valid, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Pick one representative branch per base by rank points, ties broken by ``rng``.

    Args:
        values: (P, B, 3) indices of each base's B candidate branches (all minimized).
        valid: (P, B) which candidates survived the collision-free principle.
        rng: generator for the tie-break (one uniform draw per candidate).

    Returns:
        ``(choice, score)``: chosen branch (P,) (-1 when none is valid) and the winner's score
        (sum over indices of its rank among the valid candidates, 0 = best in all; -1 if none).
    """
    values = np.asarray(values, dtype=float)
    valid = np.asarray(valid, dtype=bool)
    v = np.where(valid[..., None], values, np.inf)
    # rank = number of valid candidates strictly better in that index (ties share the rank)
    better = (v[:, None, :, :] < v[:, :, None, :]) & valid[:, None, :, None]
    rank = better.sum(axis=2)  # (P, B, 3)
    score = np.where(valid, rank.sum(axis=-1), np.iinfo(np.int64).max // 4).astype(float)
    key = score + 0.5 * rng.random(valid.shape)  # tie-break inside equal integer scores
    choice = np.argmin(key, axis=1)
    any_valid = valid.any(axis=1)
    best = np.take_along_axis(score, choice[:, None], axis=1)[:, 0]
    return np.where(any_valid, choice, -1), np.where(any_valid, best, -1).astype(int)


# --------------------------------------------------------------------------------------------
# Collision-free principle (paper Eq. 7)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CollisionModel:
    """Capsule pairs for one scenario, precomputed once."""

    capsules: tuple[cp.Capsule, ...]
    self_i: np.ndarray
    self_j: np.ndarray
    env_parts: np.ndarray

    @classmethod
    def for_scenario(cls, sc: Scenario) -> CollisionModel:
        caps = cp.ARM_CAPSULES + sc.actuator.capsules()
        names = [c.name for c in caps]
        pairs = [(a, b) for a, b in SELF_PAIRS if a in names and b in names]
        si = np.array([names.index(a) for a, _ in pairs])
        sj = np.array([names.index(b) for _, b in pairs])
        env = np.array([names.index(n) for n in ENV_PARTS if n in names])
        return cls(capsules=caps, self_i=si, self_j=sj, env_parts=env)


def collision_clearance(q, xyz, sc: Scenario, model: CollisionModel | None = None):
    """Smallest clearances (m) of configurations ``q`` (N, 6) with the base at ``xyz`` (N, 3).

    Returns:
        dict with ``self`` (actuator/wrist vs arm links, condition 2), ``environment`` (arm vs
        patient/chair, in the world), ``cabinet`` (arm vs the cart box under the base), each (N,);
        +inf when there is nothing to test.
    """
    model = model or CollisionModel.for_scenario(sc)
    seg, rad = cp.arm_capsules(q, model.capsules)  # (N, K, 2, 3) in Base
    n = seg.shape[0]
    d_self = cp.min_capsule_clearance(seg, rad, seg, rad,
                                      np.stack([model.self_i, model.self_j], axis=1))
    parts = seg[:, model.env_parts]  # (N, E, 2, 3)
    r_parts = rad[model.env_parts]
    d_cab = cp.min_box_clearance(parts, r_parts, sc.X_BC[None, :3, :3],
                                 np.broadcast_to(sc.X_BC[:3, 3], (n, 1, 3)),
                                 sc.cabinet_half[None])
    d_env = np.full(n, np.inf)
    if sc.obstacles:
        # world -> base: X_BW = X_OB^-1 X_OW = X_OB^-1 X_WO^-1 (rotation constant, shift by xyz)
        X_BW = invert(base_pose(xyz)) @ invert(sc.X_WO)  # (N, 4, 4)
        R_BW = X_BW[0, :3, :3]
        t = X_BW[:, None, None, :3, 3]  # (N, 1, 1, 3)
        caps = [o for o in sc.obstacles if o.kind == "capsule"]
        boxes = [o for o in sc.obstacles if o.kind == "box"]
        if caps:
            oseg = np.array([[o.p0, o.p1] for o in caps])  # (C, 2, 3) in World
            orad = np.array([o.radius for o in caps])
            oseg_B = oseg @ R_BW.T + t  # (N, C, 2, 3)
            d_env = np.minimum(d_env, cp.min_capsule_clearance(parts, r_parts, oseg_B, orad))
        if boxes:
            X_WBx = np.array([o.X_WB for o in boxes])  # (Bx, 4, 4)
            R_box = R_BW @ X_WBx[:, :3, :3]
            p_box = X_WBx[:, :3, 3] @ R_BW.T + X_BW[:, None, :3, 3]  # (N, Bx, 3)
            half = np.array([o.half_size for o in boxes])
            d_env = np.minimum(d_env, cp.min_box_clearance(parts, r_parts, R_box, p_box, half))
    return {"self": d_self, "environment": d_env, "cabinet": d_cab}


_BOX_CORNERS = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
_BOX_EDGES = np.array([(a, b) for a in range(8) for b in range(a + 1, 8)
                       if np.sum(_BOX_CORNERS[a] != _BOX_CORNERS[b]) == 1])


def box_edges(X, half) -> np.ndarray:
    """The 12 edges (..., 12, 2, 3) of boxes: centre poses X (..., 4, 4), half sizes (..., 3)."""
    corners = (_BOX_CORNERS * np.asarray(half)[..., None, :]) @ np.swapaxes(
        np.asarray(X)[..., :3, :3], -1, -2) + np.asarray(X)[..., None, :3, 3]
    return corners[..., _BOX_EDGES, :]


def cart_clearance(xyz, sc: Scenario) -> np.ndarray:
    """Clearance (m) between the cart/cabinet box (fixed under the base) and the patient/chair,
    per base position (P,). Two boxes overlap iff an edge of one meets the other or one holds
    the other's centre, so box-box is tested by edges both ways plus the centres (0 = touching
    or overlapping; the clearance is exact when the closest features are an edge and a face)."""
    xyz = np.atleast_2d(np.asarray(xyz, dtype=float))
    n = xyz.shape[0]
    out = np.full(n, np.inf)
    if not sc.obstacles:
        return out
    X_BW = invert(base_pose(xyz)) @ invert(sc.X_WO)  # (P, 4, 4)
    R_BW = X_BW[0, :3, :3]
    cart_edges = box_edges(sc.X_BC, sc.cabinet_half)  # (12, 2, 3) in Base
    cart_seg = np.broadcast_to(cart_edges, (n, 12, 2, 3))
    cart_R = sc.X_BC[None, :3, :3]
    cart_p = np.broadcast_to(sc.X_BC[:3, 3], (n, 1, 3))
    zeros12 = np.zeros(12)
    for o in sc.obstacles:
        if o.kind == "capsule":
            seg_B = np.array([o.p0, o.p1]) @ R_BW.T + X_BW[:, None, :3, 3]  # (P, 2, 3)
            d = cp.min_box_clearance(seg_B[:, None], np.array([o.radius]), cart_R, cart_p,
                                     sc.cabinet_half[None])
        else:
            R_box = (R_BW @ o.X_WB[:3, :3])[None]
            p_box = (o.X_WB[:3, 3] @ R_BW.T + X_BW[:, :3, 3])[:, None]  # (P, 1, 3)
            d1 = cp.min_box_clearance(cart_seg, zeros12, R_box, p_box, o.half_size[None])
            X_o = transform(R_box[0], p_box[:, 0])  # (P, 4, 4)
            d2 = cp.min_box_clearance(box_edges(X_o, o.half_size), zeros12, cart_R, cart_p,
                                      sc.cabinet_half[None])
            inside = np.all(np.abs(p_box[:, 0] - sc.X_BC[:3, 3]) <= sc.cabinet_half, axis=1)
            local = (sc.X_BC[:3, 3] - p_box[:, 0]) @ R_box[0]
            inside |= np.all(np.abs(local) <= o.half_size, axis=1)
            d = np.where(inside, 0.0, np.minimum(d1, d2))
        out = np.minimum(out, d)
    return out


# --------------------------------------------------------------------------------------------
# The problem evaluated by the GA
# --------------------------------------------------------------------------------------------


@dataclass
class BaseEvaluation:
    """Evaluation of P base positions (see :func:`evaluate_bases`).

    Attributes:
        objectives: (P, 3) [dexterity, error_range, joint_variation] of the selected branch
            (+inf where infeasible).
        violation: (P,) 0 when feasible, else > 0 (how far the closest branch is from surviving).
        branch: (P,) selected branch index 0..7, -1 when infeasible.
        q, q_pre: (P, 6) selected configuration at the target / at the pre-feed pose (NaN if none).
        valid: (P, 8) which branches survived.
        reason: (P, 8) int, why each branch was dropped (see ``DROP_REASONS``).
        candidate_indices: (P, 8, 3) indices of every surviving branch (inf elsewhere).
        angular_error_range: (P, 8) eps sigma_max(J_w) per surviving branch (NaN elsewhere).
    """

    objectives: np.ndarray
    violation: np.ndarray
    branch: np.ndarray
    q: np.ndarray
    q_pre: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    candidate_indices: np.ndarray
    angular_error_range: np.ndarray

    @property
    def feasible(self) -> np.ndarray:
        return self.branch >= 0


(DROP_OK, DROP_IK, DROP_CONTINUITY, DROP_JOINT2, DROP_SELF, DROP_ENV, DROP_CABINET,
 DROP_CART) = range(8)
DROP_REASONS = {
    DROP_OK: "ok",
    DROP_IK: "no IK solution within the joint limits somewhere along the feed",
    DROP_CONTINUITY: "branch jumps between feed samples (not continuous)",
    DROP_JOINT2: "condition 1: joint 2 outside the range clear of the cabinet",
    DROP_SELF: "condition 2: actuator or wrist hits the arm",
    DROP_ENV: "arm hits the patient or chair",
    DROP_CABINET: "arm hits the cabinet",
    DROP_CART: "the cart itself overlaps the patient or chair at this base position",
}


def ik_closed_form(X_BT, *, limits, X_FT):
    """The default IK enumeration: closed form, 8 branches with stable branch indices."""
    r = kin.ik(X_BT, limits=limits, X_FT=X_FT)
    return r.q, r.valid


def evaluate_bases(
    xyz,
    sc: Scenario,
    rng: np.random.Generator,
    *,
    ik_solver=ik_closed_form,
    model: CollisionModel | None = None,
    X_OT=None,
) -> BaseEvaluation:
    """Evaluate base positions ``xyz`` (P, 3) in Oral: the GA's vectorized problem.

    Args:
        xyz: (P, 3) base positions (m, in Oral).
        sc: scenario.
        rng: generator for the score-based selection's tie-breaks.
        ik_solver: ``(X_BT (..., 4, 4), limits=, X_FT=) -> (q (..., B, 6), valid (..., B))``;
            slot b must be the same branch at every feed sample (the closed form guarantees it;
            other solvers must track their solutions, see analyses.robot_place).
        model: precomputed collision model (built from ``sc`` if None).
        X_OT: the feeding target (Tool frame) in Oral when it is not Oral itself (several
            implant sites from one base; see :func:`target_pose`).
    """
    xyz = np.atleast_2d(np.asarray(xyz, dtype=float))
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError("xyz", f"expected (P, 3) base positions, got {xyz.shape}")
    P = xyz.shape[0]
    model = model or CollisionModel.for_scenario(sc)
    K = sc.feed_samples
    X = feed_poses(xyz, sc.feed_length, K, X_OT)  # (P, K, 4, 4)
    q, ok = ik_solver(X, limits=sc.limits, X_FT=sc.X_FT)  # (P, K, B, 6), (P, K, B)
    B = q.shape[2]
    q = np.swapaxes(q, 1, 2)  # (P, B, K, 6)
    ok = np.swapaxes(ok, 1, 2)  # (P, B, K)
    ik_fail = (~ok).sum(axis=-1) / K
    alive = ik_fail == 0
    reason = np.where(alive, DROP_OK, DROP_IK)
    step = np.abs(np.diff(q, axis=2)).max(axis=(-1, -2))
    jump = alive & (step > sc.max_joint_step)
    reason = np.where(jump, DROP_CONTINUITY, reason)
    alive &= ~jump
    viol = ik_fail + np.where(jump, 0.5, 0.0)

    # the cart under the base must stand clear of the patient and chair (independent of q)
    d_cart = cart_clearance(xyz, sc)
    cart_bad = d_cart < sc.clearance
    viol = viol + np.where(cart_bad, sc.clearance - np.minimum(d_cart, sc.clearance) + 1e-3,
                           0.0)[:, None]
    reason = np.where(alive & cart_bad[:, None], DROP_CART, reason)
    alive &= ~cart_bad[:, None]

    lo2, hi2 = sc.joint2_range
    q2 = q[..., 1]  # (P, B, K)
    j2_excess = np.maximum(np.maximum(lo2 - q2, q2 - hi2), 0.0).max(axis=-1)
    j2_bad = alive & (j2_excess > 0)
    reason = np.where(j2_bad, DROP_JOINT2, reason)
    viol = viol + np.where(alive, j2_excess, 0.0)
    alive &= ~j2_bad

    # collisions at the pre-feed and target configurations of the surviving branches
    pb, bb = np.nonzero(alive)
    if pb.size:
        q_ends = np.stack([q[pb, bb, 0], q[pb, bb, -1]], axis=1).reshape(-1, 6)
        xyz_ends = np.repeat(xyz[pb], 2, axis=0)
        d = collision_clearance(q_ends, xyz_ends, sc, model)
        deficit_total = np.zeros(pb.size)
        for key, code in (("cabinet", DROP_CABINET), ("environment", DROP_ENV),
                          ("self", DROP_SELF)):
            dk = d[key].reshape(-1, 2).min(axis=1)
            bad = dk < sc.clearance
            deficit_total += np.maximum(sc.clearance - dk, 0.0)
            sub = reason[pb, bb]
            reason[pb, bb] = np.where(bad, code, sub)
        hit = deficit_total > 0
        viol[pb, bb] += deficit_total + np.where(hit, 1e-3, 0.0)
        alive[pb[hit], bb[hit]] = False

    cand = np.full((P, B, 3), np.inf)
    ang = np.full((P, B), np.nan)
    pb, bb = np.nonzero(alive)
    if pb.size:
        ind = indices(q[pb, bb, -1], q[pb, bb], eps=sc.eps, X_FT=sc.X_FT)
        cand[pb, bb] = np.stack([ind[n] for n in INDEX_NAMES], axis=-1)
        ang[pb, bb] = ind["angular_error_range"]
        finite = np.all(np.isfinite(cand[pb, bb]), axis=-1)
        alive[pb[~finite], bb[~finite]] = False  # exactly singular: not a usable candidate

    choice, _ = select(cand, alive, rng)
    feasible = choice >= 0
    c = np.where(feasible, choice, 0)
    rows = np.arange(P)
    objectives = np.where(feasible[:, None], cand[rows, c], np.inf)
    q_sel = np.where(feasible[:, None], q[rows, c, -1], np.nan)
    q_pre = np.where(feasible[:, None], q[rows, c, 0], np.nan)
    violation = np.where(feasible, 0.0, np.maximum(viol.min(axis=1), 1e-6))
    return BaseEvaluation(
        objectives=objectives, violation=violation, branch=choice, q=q_sel, q_pre=q_pre,
        valid=alive, reason=reason, candidate_indices=cand, angular_error_range=ang,
    )


def problem(sc: Scenario, *, ik_solver=ik_closed_form):
    """The GA's evaluate callable: ``(X (n, 3), rng) -> (objectives, violation)``."""
    model = CollisionModel.for_scenario(sc)

    def evaluate(X, rng):
        ev = evaluate_bases(X, sc, rng, ik_solver=ik_solver, model=model)
        F = np.where(np.isfinite(ev.objectives), ev.objectives, 1e12)
        return F, ev.violation

    return evaluate


# --------------------------------------------------------------------------------------------
# After the GA: selection on the front, percentile ranks, GII
# --------------------------------------------------------------------------------------------


def knee_point(F, weights=None) -> int:
    """Index of the selected front point: each objective normalized to [0, 1] over the front, the
    smallest weighted sum (equal weights: the point farthest below the plane through the
    normalized extremes, a knee in the sense of Das 1999)."""
    F = np.asarray(F, dtype=float)
    if F.ndim != 2 or F.shape[0] == 0:
        raise InputError("front", "expected a non-empty (n, m) front")
    w = np.ones(F.shape[1]) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (F.shape[1],) or np.any(w < 0) or not np.any(w > 0):
        raise InputError("weights", f"expected {F.shape[1]} non-negative weights, not all 0")
    lo, hi = F.min(axis=0), F.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    return int(np.argmin(((F - lo) / span) @ w))


def random_feasible(sc: Scenario, n: int, rng: np.random.Generator, *, ik_solver=ik_closed_form,
                    max_tries: int = 50, batch: int | None = None):
    """Up to ``n`` uniformly random feasible bases in the bounds (rejection sampling).

    Returns ``(xyz (m, 3), evaluation)`` with m <= n (fewer when feasible bases are rare)."""
    model = CollisionModel.for_scenario(sc)
    batch = batch or max(4 * n, 1000)
    found_x, found_f = [], []
    count = 0
    for _ in range(max_tries):
        X = sc.lower + rng.random((batch, 3)) * (sc.upper - sc.lower)
        ev = evaluate_bases(X, sc, rng, ik_solver=ik_solver, model=model)
        keep = ev.feasible
        found_x.append(X[keep])
        found_f.append(ev.objectives[keep])
        count += int(keep.sum())
        if count >= n:
            break
    xyz = np.concatenate(found_x)[:n]
    F = np.concatenate(found_f)[:n]
    return xyz, F


def percentiles(f_selected, F_random, *, strict: bool = False) -> np.ndarray:
    """Percentile rank per index: % of random feasible bases that the selection beats or ties
    (index value >= the selection's; all indices are minimized), or only beats (> ) when
    ``strict`` (the two differ where an index has a plateau, e.g. dexterity at sqrt(3))."""
    F_random = np.asarray(F_random, dtype=float)
    if F_random.shape[0] == 0:
        return np.full(np.shape(f_selected), np.nan)
    f = np.asarray(f_selected)[None, :]
    worse = F_random > f if strict else F_random >= f
    return 100.0 * np.mean(worse, axis=0)


def gii_poses(n: int, rng: np.random.Generator, *, half_size=0.025,
              half_angle=0.4363323129985824) -> np.ndarray:
    """``n`` random poses X_OE' in a cube (2 * half_size) and an rpy box (2 * half_angle, rad;
    default 25 deg) about the target End pose (DESIGN.md section 5: 50 mm cube, 50 deg)."""
    dp = rng.uniform(-half_size, half_size, (n, 3))
    drpy = rng.uniform(-half_angle, half_angle, (n, 3))
    return X_OE @ transform(rpy_to_rotation(drpy), dp)


def gii(xyz, branch: int, sc: Scenario, rng: np.random.Generator, n: int = 100) -> dict:
    """General Isotropy Index (paper Eq. 24): sigma_min over sigma_max across the 6x6 body
    Jacobians of ``n`` random poses about Oral, reached on the selected branch.

    Returns dict(gii, reached, poses) (gii over the reached poses; NaN if none is reached).
    """
    X_OEp = gii_poses(n, rng)
    X_BEp = invert(base_pose(xyz)) @ X_OEp
    q, ok = ik_closed_form(X_BEp, limits=sc.limits, X_FT=sc.X_FT)
    ok_b = ok[:, branch]
    if not np.any(ok_b):
        return {"gii": float("nan"), "reached": 0, "poses": n}
    J = kin.jacobian_body(q[ok_b, branch], sc.X_FT)
    s = np.linalg.svd(J, compute_uv=False)
    return {"gii": float(s.min() / s.max()), "reached": int(ok_b.sum()), "poses": n}
