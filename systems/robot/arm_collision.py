"""The arm's fast conservative collision model, generated from the plant's collision geometry.

One collision model of the arm (DESIGN.md section 5): the shapes are read from the
model files the Drake plant loads (``models/aubo_i10/*.urdf``, the actuator URDF welded to the
flange) and from the MOPRP scenario (the patient/chair obstacles in World and the cart box under
the base, the geometry diagrams/plant.py registers), and the pairs are every pair the plant's
SceneGraph does not filter. ``tests/diagrams/test_arm_collision.py`` checks both against the
SceneGraph inspector of ``diagrams.plant.build_plant`` shape by shape and pair by pair.

**Enclosures.** Every collision shape G is covered by one or more primitives E_1..E_m with an
exact fast distance, each containing G: a box stays a box, a capsule or sphere stays itself, a
cylinder of radius r and length L gets three: the capsule of the same radius over the same axis
segment (it holds the cylinder, round ends sticking out by r on the axis), the box 2r x 2r x L
(its corners stick out 0.41 r) and that box turned 45 deg about the axis. Since each E_k
contains G, the distance from any other set to E_k is a lower bound of its distance to G, so
the largest of these lower bounds is one too: the model uses ``max_k d(E_k, .)``. For a point on
the cylinder's side the capsule is exact; off a rim the boxes cut the capsule's round end. The
model can only report a distance below SceneGraph's, never above it (never "free" where
SceneGraph says "closer than the clearance"); it can reject a few free configurations.

**Distances** (m, < 0 overlap): capsule-capsule is the segment distance minus both radii
(exact); capsule-box is the segment-to-box distance minus the radius (exact: the squared
point-box distance is a convex piecewise quadratic along the segment, minimized piece by piece,
:func:`seg_box`); box-box is 0 when one
box holds the other's centre, else the smallest distance of an edge of one to the other solid
box (both ways): for two disjoint convex polyhedra the closest pair always involves an edge
point of one of them, and overlapping boxes have an edge of one inside the other or hold each
other's centre, so this is exact when apart and 0 when touching (penetration depth is not
needed for a verdict). A bounding-sphere test skips the exact distance of pairs farther than a
cutoff (their bounding-sphere lower bound is reported instead, still below the true distance).

**Frames.** Frame index 0 is base_link (the cart is welded to it), 1..6 are the joint child
frames of :func:`systems.robot.kinematics.joint_frames` (the actuator is welded to the flange,
wrist3_Link = 6, at the identity), 7 is World (the patient and chair), posed per configuration
by X_BW = (X_WO X_OB)^-1.

**Pairs.** SceneGraph filters (mirrored here, each rule named): shapes on one body; bodies
joined by a joint (MultibodyPlant's adjacency rule and the URDF's collision filter groups);
bodies welded together (World, patient, base_link and cart; wrist3_Link and the actuator); and
the actuator against the patient (:data:`TOOL_VS_PATIENT_FILTERED`: the rod, head and implant
enter the mouth by design, their clearance is the FPSM's job, seed 000). Every other pair is
checked, in three groups: ``self`` (arm and actuator), ``environment`` (vs patient and chair),
``cabinet`` (vs the cart).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from implantplan import models
from implantplan.systems.errors import InputError
from implantplan.systems.frames import frame_from_z, invert, rot_z, rpy_to_rotation, transform
from implantplan.systems.jit import numba
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.robot.collision_primitives import point_box, seg_seg

ARM_URDF = {"175": "aubo_i10/aubo_i10.urdf", "360": "aubo_i10/aubo_i10_360.urdf"}
ACTUATOR_URDF = "tools/implanting_actuator.urdf"
# Model-instance scopes of the SceneGraph names (diagrams.plant's ARM, ACTUATOR, PATIENT, CART).
ARM_SCOPE, ACTUATOR_SCOPE, PATIENT_SCOPE, CART_SCOPE = "aubo", "actuator", "patient", "cart"
WORLD = 7  # frame index of World
FLANGE = 6  # wrist3_Link, where the actuator is welded
GROUPS = ("self", "environment", "cabinet")
# The actuator's shapes are not checked against the patient/chair (they enter the mouth by
# design); diagrams.plant.filter_environment_pairs applies the same rule to SceneGraph.
TOOL_VS_PATIENT_FILTERED = True
KIND_CAPSULE, KIND_BOX = 0, 1
# Verdict tolerance (m): the fast distances are exact lower bounds in real arithmetic; a shape
# pair resting exactly at the clearance (wrist1's box and wrist3's disc at q5 = +-pi are 5.000 mm
# apart by construction) comes out 1e-16 m either side of it after rounding.
ROUNDING = 1e-12


@dataclass(frozen=True)
class Shape:
    """One collision shape of the scene.

    Attributes:
        name: its SceneGraph name (``scope::name``).
        body: the body it is fixed to (``base_link`` ... ``wrist3_Link``, ``actuator_base``,
            ``cart``, ``patient``).
        frame: frame index it is posed in (0 base_link, 1..6 joint frames, 7 World).
        kind: "box", "cylinder", "capsule" or "sphere".
        X_FG: (4, 4) pose of the shape in that frame (m); a cylinder's/capsule's axis is its z.
        size: box (lx, ly, lz) full extents; cylinder/capsule (radius, length) (a capsule's
            length excludes its round ends, as in Drake and SDFormat); sphere (radius,).
    """

    name: str
    body: str
    frame: int
    kind: str
    X_FG: np.ndarray
    size: tuple[float, ...]


def _floats(text: str | None, n: int, where: str) -> np.ndarray:
    values = np.array([float(v) for v in (text or " ".join(["0"] * n)).split()])
    if values.shape != (n,):
        raise InputError(where, f"expected {n} numbers, got {text!r}")
    return values


def _urdf_shapes(path: Path, scope: str, frame_of: dict[str, int]) -> tuple[list[Shape], dict]:
    """Collision shapes of a URDF and its joints/filter groups (what MultibodyPlant reads)."""
    root = ET.parse(path).getroot()
    shapes = []
    for link in root.findall("link"):
        lname = link.get("name")
        for k, col in enumerate(link.findall("collision")):
            where = f"{path.name}: {lname} collision {k}"
            origin = col.find("origin")
            xyz = _floats(origin.get("xyz") if origin is not None else None, 3, where)
            rpy = _floats(origin.get("rpy") if origin is not None else None, 3, where)
            geom = list(col.find("geometry"))[0]
            tag = geom.tag.split("}")[-1]
            if tag == "box":
                kind, size = "box", tuple(_floats(geom.get("size"), 3, where))
            elif tag in ("cylinder", "capsule"):
                kind, size = tag, (float(geom.get("radius")), float(geom.get("length")))
            elif tag == "sphere":
                kind, size = "sphere", (float(geom.get("radius")),)
            else:
                raise InputError(where, f"expected box, cylinder, capsule or sphere, got {tag}")
            name = col.get("name") or f"{lname}_collision_{k}"
            shapes.append(Shape(f"{scope}::{name}", lname, frame_of[lname], kind,
                                transform(rpy_to_rotation(rpy), xyz), size))
    joints = [(j.find("parent").get("link"), j.find("child").get("link"))
              for j in root.findall("joint")]
    groups = []
    for g in root.iter():
        if g.tag.split("}")[-1] != "collision_filter_group":
            continue
        members = {m.get("link") for m in g if m.tag.split("}")[-1] == "member"}
        ignored = {m.get("name") for m in g if m.tag.split("}")[-1] ==
                   "ignored_collision_filter_group"}
        if g.get("name") in ignored:
            groups.append(members)
    return shapes, {"joints": joints, "groups": groups}


def scene_shapes(sc, *, tool: bool = True) -> tuple[list[Shape], set[frozenset[str]]]:
    """The scene's collision shapes and its filtered body pairs, as diagrams.plant builds it.

    Args:
        sc: a :class:`systems.robot.moprp.Scenario` (its obstacles, cart box and joint limits), or
            None for the bare arm (with the actuator when ``tool``).

    Returns:
        ``(shapes, filtered)``: the shapes, and the set of unordered body-name pairs SceneGraph
        filters (a body paired with itself stands for "shapes on one body").
    """
    limits = "175" if sc is None else sc.limits
    frame_of = {name: i for i, name in enumerate(kin.LINK_NAMES)}
    shapes, arm = _urdf_shapes(models.model_path(ARM_URDF[limits]), ARM_SCOPE, frame_of)
    adjacent = [frozenset(p) for p in arm["joints"]]
    groups = list(arm["groups"])
    welded = [{kin.LINK_NAMES[0]}]  # base_link is welded to World
    if tool:
        tshapes, _ = _urdf_shapes(models.model_path(ACTUATOR_URDF), ACTUATOR_SCOPE,
                                  {"actuator_base": FLANGE})
        shapes += tshapes
        welded.append({kin.LINK_NAMES[FLANGE], "actuator_base"})
    if sc is not None:
        for o in sc.obstacles:
            if o.kind == "box":
                shapes.append(Shape(f"{PATIENT_SCOPE}::{o.name}", PATIENT_SCOPE, WORLD, "box",
                                    np.asarray(o.X_WB, float), tuple(2 * o.half_size)))
            else:
                axis = np.asarray(o.p1) - np.asarray(o.p0)
                length = float(np.linalg.norm(axis))
                z = axis / length if length > 0 else np.array([0.0, 0.0, 1.0])
                shapes.append(Shape(f"{PATIENT_SCOPE}::{o.name}", PATIENT_SCOPE, WORLD,
                                    "capsule", frame_from_z((o.p0 + o.p1) / 2, z),
                                    (float(o.radius), length)))
        shapes.append(Shape(f"{CART_SCOPE}::{CART_SCOPE}", CART_SCOPE, 0, "box",
                            np.asarray(sc.X_BC, float), tuple(2 * sc.cabinet_half)))
        welded[0] |= {PATIENT_SCOPE, CART_SCOPE}
    bodies = {s.body for s in shapes}
    filtered = {frozenset([b]) for b in bodies}
    filtered |= set(adjacent)
    for members in groups + welded:
        filtered |= {frozenset([a, b]) for a in members for b in members}
    if tool and sc is not None and TOOL_VS_PATIENT_FILTERED:
        filtered.add(frozenset(["actuator_base", PATIENT_SCOPE]))
    return shapes, filtered


def enclosures(shape: Shape) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Primitives that each contain ``shape``: ``(kind, X_FE, dims)`` with dims (a, r, 0) for a
    capsule (segment from -a to +a on E's z, radius r) and the half extents for a box."""
    X = np.asarray(shape.X_FG, dtype=float)
    if shape.kind == "box":
        return [(KIND_BOX, X, np.asarray(shape.size, float) / 2)]
    if shape.kind == "capsule":
        r, length = shape.size
        return [(KIND_CAPSULE, X, np.array([length / 2, r, 0.0]))]
    if shape.kind == "sphere":
        return [(KIND_CAPSULE, X, np.array([0.0, shape.size[0], 0.0]))]
    if shape.kind == "cylinder":
        r, length = shape.size
        half = np.array([r, r, length / 2])
        X45 = X @ transform(rot_z(np.pi / 4), np.zeros(3))
        return [(KIND_CAPSULE, X, np.array([length / 2, r, 0.0])), (KIND_BOX, X, half),
                (KIND_BOX, X45, half)]
    raise InputError("shape.kind", f"expected box, cylinder, capsule or sphere, got {shape.kind}")


def bounding_radius(shape: Shape) -> float:
    """Radius of a sphere about the shape's origin that contains it (m)."""
    s = shape.size
    if shape.kind == "box":
        return float(np.linalg.norm(s) / 2)
    if shape.kind == "capsule":
        return s[1] / 2 + s[0]
    if shape.kind == "sphere":
        return s[0]
    return float(np.hypot(s[0], s[1] / 2))


def _group(a: Shape, b: Shape) -> int:
    bodies = {a.body, b.body}
    if CART_SCOPE in bodies:
        return 2
    if PATIENT_SCOPE in bodies:
        return 1
    return 0


@dataclass(frozen=True)
class ArmCollisionModel:
    """The fast model of one scene: shapes, their enclosures and the checked pairs (arrays for the
    compiled kernel). Build with :func:`model_for`."""

    shapes: tuple[Shape, ...]
    pairs: np.ndarray  # (M, 2) shape indices
    pair_group: np.ndarray  # (M,) index into GROUPS
    enc_frame: np.ndarray  # (E,)
    enc_kind: np.ndarray  # (E,)
    enc_X: np.ndarray  # (E, 4, 4) enclosure pose in its frame
    enc_dims: np.ndarray  # (E, 3)
    shape_enc: np.ndarray  # (S + 1,) enclosures of shape s: shape_enc[s]:shape_enc[s + 1]
    shape_frame: np.ndarray  # (S,)
    shape_centre: np.ndarray  # (S, 3) bounding-sphere centre in its frame
    shape_radius: np.ndarray  # (S,)

    def pair_names(self, m: int) -> tuple[str, str]:
        i, j = self.pairs[m]
        return self.shapes[i].name, self.shapes[j].name

    @classmethod
    def for_scenario(cls, sc) -> ArmCollisionModel:
        """The model of a scenario's scene (see :func:`model_for`)."""
        return model_for(sc)

    @classmethod
    def from_shapes(cls, shapes, filtered) -> ArmCollisionModel:
        shapes = tuple(shapes)
        pairs, group = [], []
        for i in range(len(shapes)):
            for j in range(i + 1, len(shapes)):
                if frozenset([shapes[i].body, shapes[j].body]) in filtered:
                    continue
                if shapes[i].frame == shapes[j].frame:
                    continue  # fixed relative to each other (would be one body in the plant)
                pairs.append((i, j))
                group.append(_group(shapes[i], shapes[j]))
        enc = [enclosures(s) for s in shapes]
        starts = np.concatenate([[0], np.cumsum([len(e) for e in enc])]).astype(np.int64)
        flat = [e for es in enc for e in es]
        frames = np.array([s.frame for s in shapes], dtype=np.int64)
        return cls(
            shapes=shapes,
            pairs=np.array(pairs, dtype=np.int64).reshape(-1, 2),
            pair_group=np.array(group, dtype=np.int64),
            enc_frame=np.repeat(frames, np.diff(starts)),
            enc_kind=np.array([k for k, _, _ in flat], dtype=np.int64),
            enc_X=np.ascontiguousarray([X for _, X, _ in flat], dtype=float),
            enc_dims=np.ascontiguousarray([d for _, _, d in flat], dtype=float),
            shape_enc=starts,
            shape_frame=frames,
            shape_centre=np.array([s.X_FG[:3, 3] for s in shapes], dtype=float),
            shape_radius=np.array([bounding_radius(s) for s in shapes], dtype=float),
        )

    def scene_frames(self, q, X_BW=None) -> np.ndarray:
        """(N, 8, 4, 4) frames: identity (base_link), the 6 joint frames, X_BW (World in Base)."""
        q = np.asarray(q, dtype=float).reshape(-1, 6)
        F = np.empty((q.shape[0], 8, 4, 4))
        F[:, 0] = np.eye(4)
        F[:, 1:7] = kin.joint_frames(q)
        F[:, 7] = np.eye(4) if X_BW is None else np.broadcast_to(X_BW, (q.shape[0], 4, 4))
        return F

    def posed_shapes(self, q, X_BW=None) -> list[tuple[Shape, np.ndarray]]:
        """Each shape with its pose in base_link at one configuration ``q`` (6,) (for plots)."""
        F = self.scene_frames(np.asarray(q, dtype=float)[None], X_BW)[0]
        return [(s, F[s.frame] @ s.X_FG) for s in self.shapes]

    def clearance(self, q, X_BW=None, *, cutoff: float = np.inf):
        """Lower bounds of the signed distance per pair group, and the closest pair.

        Args:
            q: (N, 6) joint vectors (rad).
            X_BW: (N, 4, 4) or (4, 4) World in base_link (needed with obstacles in World).
            cutoff: pairs whose bounding spheres are farther apart than this (m) report that
                lower bound instead of their exact distance (a verdict at a clearance c only
                needs cutoff >= c).

        Returns:
            ``(d, pair)``: d (N, 3) smallest distance per group of :data:`GROUPS` (m; +inf when
            the group is empty), pair (N, 3) index of the closest pair into ``pairs`` (-1).
        """
        F = np.ascontiguousarray(self.scene_frames(q, X_BW))
        n = F.shape[0]
        d = np.full((n, len(GROUPS)), np.inf)
        arg = np.full((n, len(GROUPS)), -1, dtype=np.int64)
        if self.pairs.shape[0]:
            _clearance_kernel(F, self.enc_frame, self.enc_kind, self.enc_X, self.enc_dims,
                              self.shape_enc, self.shape_frame, self.shape_centre,
                              self.shape_radius, self.pairs, self.pair_group, float(cutoff),
                              d, arg)
        return d, arg


@lru_cache(maxsize=32)
def _cached(key):
    return ArmCollisionModel.from_shapes(*scene_shapes(key[0], tool=key[1]))


def model_for(sc=None, *, tool: bool = True) -> ArmCollisionModel:
    """The fast model of a scenario's scene (None: the bare arm), built once per scenario."""
    if sc is None:
        return _cached((None, tool))
    return ArmCollisionModel.from_shapes(*scene_shapes(sc, tool=tool))


def world_in_base(xyz, X_WO, R_OB) -> np.ndarray:
    """X_BW (N, 4, 4) for base positions ``xyz`` (N, 3) in Oral with base axes R_OB."""
    X_OB = transform(R_OB, np.atleast_2d(np.asarray(xyz, dtype=float)))
    return invert(X_OB) @ invert(np.asarray(X_WO, dtype=float))


# --------------------------------------------------------------------------------------------
# compiled distances
# --------------------------------------------------------------------------------------------


@numba.njit(cache=True)
def _crossing(a, d, h):  # pragma: no cover - compiled
    """(t at a + t d = -h, t at a + t d = +h), -1 where not inside (0, 1)."""
    if d == 0.0:
        return -1.0, -1.0
    t0 = (-h - a) / d
    t1 = (h - a) / d
    return (t0 if 0.0 < t0 < 1.0 else -1.0), (t1 if 0.0 < t1 < 1.0 else -1.0)


@numba.njit(cache=True)
def _piece_min(ax, ay, az, dx, dy, dz, hx, hy, hz, lo, hi):  # pragma: no cover - compiled
    """Minimum of the point-box distance on [lo, hi], a piece where no coordinate crosses +-h:
    the quadratic of the piece's active coordinates minimized in closed form."""
    tm = 0.5 * (lo + hi)
    A = 0.0
    B = 0.0
    for a, d, h in ((ax, dx, hx), (ay, dy, hy), (az, dz, hz)):
        v = a + tm * d
        if v > h:
            A += d * d
            B += d * (a - h)
        elif v < -h:
            A += d * d
            B += d * (a + h)
    t = lo if A <= 0.0 else min(max(-B / A, lo), hi)
    return point_box(ax + t * dx, ay + t * dy, az + t * dz, hx, hy, hz)


@numba.njit(cache=True)
def seg_box(ax, ay, az, dx, dy, dz, hx, hy, hz):  # pragma: no cover - compiled
    """Exact distance from the segment a + t d (t in [0, 1], box frame) to the solid box of half
    sizes h. The squared point-box distance sum_c max(|a_c + t d_c| - h_c, 0)^2 is a convex
    piecewise quadratic in t whose pieces change where a coordinate crosses +-h_c (at most 6
    breakpoints): the smallest value at the ends and breakpoints brackets the minimum between
    its two neighbours, and the quadratic of each of those two pieces is minimized in closed
    form (no allocation, no sort)."""
    x0, x1 = _crossing(ax, dx, hx)
    y0, y1 = _crossing(ay, dy, hy)
    z0, z1 = _crossing(az, dz, hz)
    cands = (0.0, 1.0, x0, x1, y0, y1, z0, z1)
    best = np.inf
    tb = 0.0
    for t in cands:
        if t >= 0.0:
            f = point_box(ax + t * dx, ay + t * dy, az + t * dz, hx, hy, hz)
            if f < best:
                best = f
                tb = t
    if best <= 0.0:
        return 0.0
    left = -1.0
    right = 2.0
    for t in cands:
        if t >= 0.0:
            if left < t < tb:
                left = t
            if tb < t < right:
                right = t
    if left >= 0.0:
        best = min(best, _piece_min(ax, ay, az, dx, dy, dz, hx, hy, hz, left, tb))
    if right <= 1.0:
        best = min(best, _piece_min(ax, ay, az, dx, dy, dz, hx, hy, hz, tb, right))
    return best


@numba.njit(cache=True)
def _to_local(W, px, py, pz):  # pragma: no cover - compiled
    """Point p (scene coordinates) in the frame W: R^T (p - t)."""
    ux, uy, uz = px - W[0, 3], py - W[1, 3], pz - W[2, 3]
    return (W[0, 0] * ux + W[1, 0] * uy + W[2, 0] * uz,
            W[0, 1] * ux + W[1, 1] * uy + W[2, 1] * uz,
            W[0, 2] * ux + W[1, 2] * uy + W[2, 2] * uz)


@numba.njit(cache=True)
def _capsule_box(Wc, a, r, Wb, h):  # pragma: no cover - compiled
    zx, zy, zz = Wc[0, 2] * a, Wc[1, 2] * a, Wc[2, 2] * a
    p0 = _to_local(Wb, Wc[0, 3] - zx, Wc[1, 3] - zy, Wc[2, 3] - zz)
    p1 = _to_local(Wb, Wc[0, 3] + zx, Wc[1, 3] + zy, Wc[2, 3] + zz)
    return seg_box(p0[0], p0[1], p0[2], p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2],
                          h[0], h[1], h[2]) - r


@numba.njit(cache=True)
def _edges_to_box(WA, hA, WB, hB):  # pragma: no cover - compiled
    """Smallest lower-bound distance of the 12 edges of box A to the solid box B."""
    best = np.inf
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3
        for su in (-1.0, 1.0):
            for sv in (-1.0, 1.0):
                # edge along A's `axis` at (su hA[u], sv hA[v]) in A's frame
                cx = WA[0, 3] + su * hA[u] * WA[0, u] + sv * hA[v] * WA[0, v]
                cy = WA[1, 3] + su * hA[u] * WA[1, u] + sv * hA[v] * WA[1, v]
                cz = WA[2, 3] + su * hA[u] * WA[2, u] + sv * hA[v] * WA[2, v]
                ex, ey, ez = hA[axis] * WA[0, axis], hA[axis] * WA[1, axis], hA[axis] * WA[2, axis]
                p0 = _to_local(WB, cx - ex, cy - ey, cz - ez)
                p1 = _to_local(WB, cx + ex, cy + ey, cz + ez)
                d = seg_box(p0[0], p0[1], p0[2], p1[0] - p0[0], p1[1] - p0[1],
                                   p1[2] - p0[2], hB[0], hB[1], hB[2])
                if d < best:
                    best = d
    return best


@numba.njit(cache=True)
def _face_gap(WA, hA, WB, hB):  # pragma: no cover - compiled
    """Largest separation of the boxes along A's face normals (a lower bound of their
    distance: a projection onto a unit axis never lengthens a segment)."""
    gap = -np.inf
    for k in range(3):
        ux, uy, uz = WA[0, k], WA[1, k], WA[2, k]
        c = abs((WB[0, 3] - WA[0, 3]) * ux + (WB[1, 3] - WA[1, 3]) * uy
                + (WB[2, 3] - WA[2, 3]) * uz)
        rB = 0.0
        for j in range(3):
            rB += hB[j] * abs(WB[0, j] * ux + WB[1, j] * uy + WB[2, j] * uz)
        g = c - hA[k] - rB
        if g > gap:
            gap = g
    return gap


@numba.njit(cache=True)
def box_box(WA, hA, WB, hB, cutoff=np.inf):  # pragma: no cover - compiled
    gap = max(_face_gap(WA, hA, WB, hB), _face_gap(WB, hB, WA, hA))
    if gap >= cutoff:
        return gap  # a lower bound, already beyond what the verdict needs
    c = _to_local(WB, WA[0, 3], WA[1, 3], WA[2, 3])
    if abs(c[0]) <= hB[0] and abs(c[1]) <= hB[1] and abs(c[2]) <= hB[2]:
        return 0.0
    c = _to_local(WA, WB[0, 3], WB[1, 3], WB[2, 3])
    if abs(c[0]) <= hA[0] and abs(c[1]) <= hA[1] and abs(c[2]) <= hA[2]:
        return 0.0
    return min(_edges_to_box(WA, hA, WB, hB), _edges_to_box(WB, hB, WA, hA))


@numba.njit(cache=True)
def _enclosure_distance(kA, WA, dA, kB, WB, dB, cutoff):  # pragma: no cover - compiled
    if kA == 0 and kB == 0:
        ax, ay, az = WA[0, 2] * dA[0], WA[1, 2] * dA[0], WA[2, 2] * dA[0]
        bx, by, bz = WB[0, 2] * dB[0], WB[1, 2] * dB[0], WB[2, 2] * dB[0]
        s = seg_seg(WA[0, 3] - ax, WA[1, 3] - ay, WA[2, 3] - az,
                     WA[0, 3] + ax, WA[1, 3] + ay, WA[2, 3] + az,
                     WB[0, 3] - bx, WB[1, 3] - by, WB[2, 3] - bz,
                     WB[0, 3] + bx, WB[1, 3] + by, WB[2, 3] + bz)
        return s - dA[1] - dB[1]
    if kA == 0:
        return _capsule_box(WA, dA[0], dA[1], WB, dB)
    if kB == 0:
        return _capsule_box(WB, dB[0], dB[1], WA, dA)
    return box_box(WA, dA, WB, dB, cutoff)


@numba.njit(cache=True)
def _clearance_kernel(F, enc_frame, enc_kind, enc_X, enc_dims, shape_enc, shape_frame,
                      shape_centre, shape_radius, pairs, pair_group, cutoff, out,
                      out_pair):  # pragma: no cover - compiled
    E = enc_frame.shape[0]
    S = shape_frame.shape[0]
    W = np.zeros((E, 4, 4))
    W[:, 3, 3] = 1.0
    C = np.empty((S, 3))
    for n in range(F.shape[0]):
        for e in range(E):
            Fe = F[n, enc_frame[e]]
            Xe = enc_X[e]
            for r in range(3):
                for c in range(4):
                    W[e, r, c] = (Fe[r, 0] * Xe[0, c] + Fe[r, 1] * Xe[1, c]
                                  + Fe[r, 2] * Xe[2, c])
                W[e, r, 3] += Fe[r, 3]
        for s in range(S):
            Fs = F[n, shape_frame[s]]
            for c in range(3):
                C[s, c] = (Fs[c, 0] * shape_centre[s, 0] + Fs[c, 1] * shape_centre[s, 1]
                           + Fs[c, 2] * shape_centre[s, 2] + Fs[c, 3])
        for m in range(pairs.shape[0]):
            i, j = pairs[m, 0], pairs[m, 1]
            dx, dy, dz = C[i, 0] - C[j, 0], C[i, 1] - C[j, 1], C[i, 2] - C[j, 2]
            lb = np.sqrt(dx * dx + dy * dy + dz * dz) - shape_radius[i] - shape_radius[j]
            g = pair_group[m]
            if lb >= cutoff or lb >= out[n, g]:
                d = lb
            else:
                d = -np.inf
                for a in range(shape_enc[i], shape_enc[i + 1]):
                    for b in range(shape_enc[j], shape_enc[j + 1]):
                        dab = _enclosure_distance(enc_kind[a], W[a], enc_dims[a],
                                                  enc_kind[b], W[b], enc_dims[b], cutoff)
                        if dab > d:
                            d = dab
                            if d >= cutoff:
                                break
                    if d >= cutoff:
                        break
                if d < lb:
                    d = lb  # both are lower bounds: keep the larger
            if d < out[n, g]:
                out[n, g] = d
                out_pair[n, g] = m
