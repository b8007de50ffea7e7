"""The instrument in the mouth: one definition every safety layer takes its shapes from.

An :class:`Instrument` is a list of solid primitives (cylinders, capsules, spheres) in seed 000's
Tool frame T: origin at the head centre (the actuator's ``tcp``), x along the handle rod out of
the mouth, z along the implant axis, the implant pointing to -z. Two sources:

- :meth:`Instrument.from_urdf` / :meth:`Instrument.actuator`: the collision shapes of an actuator
  URDF (the shipped ``models/tools/implanting_actuator.urdf`` by default, or a case's own), taken
  into T through the URDF's ``tcp`` frame and R_TF (T's axes are F's -z, -x and y: the rod
  leaves the head along -F z, the implant points along -F y). The shipped actuator: rod a
  cylinder r 6 mm from the flange to 4 mm short of the TCP, head a cylinder r 8 mm x 14 mm
  coaxial with the implant, implant a cylinder r 2 mm x 24 mm ending 31 mm (d12) below the TCP.
- :meth:`Instrument.paper`: the paper's thin tool (seed 000 Eq. 19, for reproducing it): the rod
  a capsule of radius r from P1 = [r, 0, 0] along +x, the head a sphere of radius r at the
  origin, the implant its axis from [r, 0, 0] to P2 = [r, 0, -d12] (radius 0, line2).

**Two views of the same shapes.** The exact reference (FCL) takes the primitives as they are
(:meth:`Instrument.fcl_shapes`). The fast bound of the FPSM (systems.placement.tool_clearance)
takes capsules only, so :meth:`Instrument.capsules_T` gives a *cover*: capsules whose union
contains every primitive (sound: the cover's clearance is a lower bound of the body's). A
capsule is its own cover and a sphere a capsule of length 0. A cylinder of radius R and axis
a-b lies in the capsule a-b of radius R, which overshoots each flat end by R along the axis;
for a wide cylinder (R above :data:`COVER_RADIUS`: the actuator's head) the cover is instead 7
capsules of radius R/2 on the same length, axes at the centre and at 6 points R sqrt(3)/2 from it
(the 7 discs of radius R/2 in that hexagonal layout cover the disc of radius R: each outer disc
reaches the rim's arc of 60 deg and the inner disc the rest), so the overshoot is R/2.
Where the cover's bound cannot decide, the exact reference resolves it.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from implantplan.systems import actuator
from implantplan.systems.errors import InputError
from implantplan.systems.frames import rpy_to_rotation

KINDS = ("cylinder", "capsule", "sphere")
# T's axes in the flange frame F (columns): x_T = -z_F (rod out), y_T = -x_F, z_T = y_F (implant
# points to -z_T = -y_F). The same rotation as systems.robot.moprp.R_OE's transpose.
R_FT = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
COVER_RADIUS = 0.007  # m: a cylinder wider than this is covered by 7 thinner capsules
_HEX = np.vstack([[0.0, 0.0], np.sqrt(3) / 2 * np.c_[np.cos(np.arange(6) * np.pi / 3),
                                                   np.sin(np.arange(6) * np.pi / 3)]])


REACH_SAMPLES = 3600  # rim angles of :meth:`Instrument.shape_reach_T`'s cylinder maximum


@dataclass(frozen=True, eq=False)
class Shape:
    """One solid of the instrument in T: a cylinder or capsule of axis a-b and ``radius``, or a
    sphere of ``radius`` at a (= b)."""

    name: str
    kind: str
    a: np.ndarray
    b: np.ndarray
    radius: float

    def __post_init__(self):
        if self.kind not in KINDS:
            raise InputError(f"instrument.{self.name}", f"expected one of {KINDS}")
        a, b = (np.asarray(v, dtype=float).reshape(3) for v in (self.a, self.b))
        r = float(self.radius)
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and np.isfinite(r) and r >= 0):
            raise InputError(f"instrument.{self.name}", "expected finite points and a radius "
                             ">= 0 (m)")
        if self.kind == "cylinder" and (r == 0 or np.linalg.norm(b - a) == 0):
            raise InputError(f"instrument.{self.name}", "a cylinder needs a radius and a length")
        object.__setattr__(self, "a", a)
        object.__setattr__(self, "b", b)
        object.__setattr__(self, "radius", r)

    def _key(self) -> tuple:
        return (self.name, self.kind, tuple(self.a), tuple(self.b), self.radius)

    def __eq__(self, other) -> bool:
        return isinstance(other, Shape) and self._key() == other._key()

    def __hash__(self) -> int:  # value semantics: equal instruments share compiled caches
        return hash(self._key())

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.b - self.a))

    def cover(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Capsules (starts (c, 3), ends (c, 3), radii (c,)) whose union contains the shape."""
        if self.kind != "cylinder" or self.radius <= COVER_RADIUS:
            return self.a[None], self.b[None], np.array([self.radius])
        u = (self.b - self.a) / self.length
        e1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(u, e1)
        off = self.radius * (_HEX[:, :1] * e1 + _HEX[:, 1:] * e2)
        return self.a + off, self.b + off, np.full(len(_HEX), self.radius / 2)

    def to_dict(self) -> dict:
        return {"name": self.name, "kind": self.kind, "a": self.a.tolist(), "b": self.b.tolist(),
                "radius": self.radius}


@dataclass(frozen=True)
class Instrument:
    """The instrument's solids in T and the numbers the planner's lines take (module notes).

    Attributes:
        name: ``"actuator"`` (the shipped URDF), ``"paper"`` or the URDF's file name.
        shapes: the solids.
        rod_radius: the handle rod's radius r (m): line1 of Eq. 19 is checked against the FPSM
            shrunk by r.
        implant_length: d12 (m), head centre to implant tip along -z.
        rod_length: flange face to the TCP (m).
        source: where the shapes came from (a path, or the paper's section).
        line_offset: x of the Eq. 19 lines' starts in T (the paper's P1 = [r, 0, 0]; 0 for a
            URDF's implant, coaxial with the head).
    """

    name: str
    shapes: tuple[Shape, ...]
    rod_radius: float
    implant_length: float
    rod_length: float = actuator.ROD_LENGTH
    source: str = ""
    line_offset: float = 0.0

    def __post_init__(self):
        if not self.shapes:
            raise InputError("instrument", "expected at least one shape")
        for name, value in (("rod_radius", self.rod_radius),
                            ("implant_length", self.implant_length),
                            ("rod_length", self.rod_length)):
            v = float(value)
            if np.isnan(v) or v < 0 or (name != "rod_radius" and v == 0) or (
                    name != "rod_length" and not np.isfinite(v)):
                raise InputError(f"instrument.{name}", "expected a finite length (m), "
                                 f"{'>= 0' if name == 'rod_radius' else '> 0'}, got {value!r}")
            object.__setattr__(self, name, v)
        object.__setattr__(self, "shapes", tuple(self.shapes))

    # -- sources ----------------------------------------------------------------------------

    @classmethod
    def paper(cls, rod_radius: float = actuator.ROD_RADIUS,
              implant_length: float = actuator.IMPLANT_LENGTH,
              rod_length: float = actuator.ROD_LENGTH, *, head_radius: float | None = None,
              implant_radius: float = 0.0) -> Instrument:
        """Seed 000's thin tool (module notes): rod capsule, head sphere of the rod's radius,
        the implant as its axis. ``head_radius`` / ``implant_radius`` thicken the head sphere
        and the implant capsule in the same layout (then named ``"paper-layout"``)."""
        r, d12 = _length("rod_radius", rod_radius), _length("implant_length", implant_length, True)
        _length("rod_length", rod_length, True, finite=False)
        head = r if head_radius is None else _length("head_radius", head_radius)
        implant_radius = _length("implant_radius", implant_radius)
        length = min(float(rod_length), 1.0)
        shapes = (Shape("rod", "capsule", [r, 0, 0], [r + length, 0, 0], r),
                  Shape("head", "sphere", [0, 0, 0], [0, 0, 0], head),
                  Shape("implant", "capsule", [r, 0, 0], [r, 0, -d12], implant_radius))
        plain = head_radius is None and implant_radius == 0.0
        return cls("paper" if plain else "paper-layout", shapes, rod_radius=r,
                   implant_length=d12, rod_length=rod_length,
                   source="seed 000 Eq. 19 (head as thick as the rod, the implant its axis)",
                   line_offset=r)

    @classmethod
    def actuator(cls) -> Instrument:
        """The shipped actuator URDF's collision shapes."""
        from implantplan import models

        inst = cls.from_urdf(models.model_path("tools/implanting_actuator.urdf"))
        return replace(inst, name="actuator")

    @classmethod
    def from_urdf(cls, path, *, field: str = "instrument.urdf") -> Instrument:
        """The collision shapes of an actuator URDF (cylinders, spheres, capsules; boxes and
        meshes are refused by name) in T through its ``tcp`` frame; d12 from its
        ``implant_tip`` frame; the rod radius from the collision named ``rod_collision`` (or
        the first shape along the rod)."""
        path = Path(path)
        try:
            root = ET.parse(path).getroot()
        except (OSError, ET.ParseError) as exc:
            raise InputError(field, f"{path}: expected a readable URDF ({exc})") from None
        frames = {f.get("name"): f for f in root.iter("frame")}
        if "tcp" not in frames or "implant_tip" not in frames:
            raise InputError(field, f"{path}: expected <frame name='tcp'> and "
                             "<frame name='implant_tip'> (the head centre and the implant tip)")

        def xyz_rpy(el):
            o = el.find("origin") if el.tag != "frame" else el
            if o is None:
                return np.zeros(3), np.eye(3)
            xyz = np.array([float(s) for s in (o.get("xyz") or "0 0 0").split()])
            rpy = np.array([float(s) for s in (o.get("rpy") or "0 0 0").split()])
            return xyz, rpy_to_rotation(rpy)

        p_tcp, R_tcp = xyz_rpy(frames["tcp"])
        if not np.allclose(R_tcp, np.eye(3)):
            raise InputError(field, f"{path}: expected the tcp frame with the link's orientation")
        tip = R_FT.T @ (xyz_rpy(frames["implant_tip"])[0] - p_tcp)
        if not np.allclose(tip[:2], 0.0, atol=1e-9) or tip[2] >= 0:
            raise InputError(field, f"{path}: expected the implant tip below the tcp on the "
                             "implant axis (-y of the link)")

        def to_T(p):
            return R_FT.T @ (p - p_tcp)

        shapes, rod_radius = [], None
        for k, col in enumerate(root.iter("collision")):
            name = (col.get("name") or f"shape{k}").removesuffix("_collision")
            geom = col.find("geometry")
            xyz, R = xyz_rpy(col)
            kinds = [g.tag for g in (geom if geom is not None else [])]
            if kinds[:1] in (["cylinder"], ["capsule"]):
                g = geom[0]
                r, length = float(g.get("radius")), float(g.get("length"))
                half = 0.5 * length * R[:, 2]
                shapes.append(Shape(name, kinds[0], to_T(xyz - half), to_T(xyz + half), r))
            elif kinds[:1] == ["sphere"]:
                c = to_T(xyz)
                shapes.append(Shape(name, "sphere", c, c, float(geom[0].get("radius"))))
            else:
                raise InputError(field, f"{path}: collision {name!r} is a {kinds[:1] or 'nothing'}"
                                 "; expected a cylinder, capsule or sphere")
            if name == "rod":
                rod_radius = shapes[-1].radius
        if rod_radius is None:
            raise InputError(field, f"{path}: expected a collision named 'rod_collision'")
        rod = next(s for s in shapes if s.name == "rod")
        return cls(path.stem, tuple(shapes), rod_radius=rod_radius, implant_length=-tip[2],
                   rod_length=float(max(rod.a[0], rod.b[0])), source=str(path), line_offset=0.0)

    # -- what the layers take ---------------------------------------------------------------

    def capsules_T(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The capsule cover of every shape (module notes): starts (C, 3), ends (C, 3), radii
        (C,) in T."""
        parts = [s.cover() for s in self.shapes]
        return (np.vstack([p[0] for p in parts]), np.vstack([p[1] for p in parts]),
                np.concatenate([p[2] for p in parts]))

    def reach_T(self) -> np.ndarray:
        """(C,) per cover capsule the largest distance of a point of its axis from the rod axis
        (Tool x) (m): a rotation by a small angle a about a point of the rod axis moves that
        axis point by at most a * reach relative to the rod axis."""
        a, b, _ = self.capsules_T()
        return np.maximum(np.hypot(a[:, 1], a[:, 2]), np.hypot(b[:, 1], b[:, 2]))

    def shape_reach_T(self) -> np.ndarray:
        """(S,) per shape the largest distance of a point of the solid from the rod axis (Tool
        x) (m), an upper bound within 0.01 mm. The distance to a line is convex, so its maximum
        over a convex solid sits at an extreme point: for a capsule or sphere an end of its axis
        plus its radius (exact); for a cylinder a point of a cap's rim, c + R (cos p e1 +
        sin p e2), maximized over p at :data:`REACH_SAMPLES` angles plus the most the distance
        can grow between two of them (it changes by at most R per radian)."""
        return self._reach(lambda P: np.hypot(P[..., 1], P[..., 2]))

    def origin_reach_T(self) -> np.ndarray:
        """(S,) per shape the largest distance of a point of the solid from the Tool origin (the
        TCP) (m), an upper bound within 0.01 mm, found as :meth:`shape_reach_T` (the distance
        to a point is convex too): a turn by a about the TCP moves no point of the solid by more
        than a times it."""
        return self._reach(lambda P: np.linalg.norm(P, axis=-1))

    def turns_about_tcp(self) -> np.ndarray:
        """(S,) per shape whether the fixture's turns reach it as turns about the TCP: its
        farthest point from the TCP is as far from the rod axis (the head and the implant, not
        the long rod, which the fixture holds by its axis at the mouth opening)."""
        return np.abs(self.origin_reach_T() - self.shape_reach_T()) <= 1e-9

    def _reach(self, distance) -> np.ndarray:
        p = np.linspace(0.0, 2 * np.pi, REACH_SAMPLES, endpoint=False)
        out = []
        for s in self.shapes:
            if s.kind != "cylinder":
                out.append(max(distance(s.a), distance(s.b)) + s.radius)
                continue
            u = (s.b - s.a) / s.length
            e1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(u, e1)
            rim = s.radius * (np.cos(p)[:, None] * e1 + np.sin(p)[:, None] * e2)
            far = max(distance(c + rim).max() for c in (s.a, s.b))
            out.append(far + s.radius * np.pi / REACH_SAMPLES)
        return np.array(out)

    def lines_T(self) -> tuple[np.ndarray, np.ndarray]:
        """Eq. 19's lines in T: the starts P1 = [o, 0, 0] (line1, the rod) and P2 = [o, 0, -d12]
        (line2, the implant tip's path), o = :attr:`line_offset`, and their direction +x."""
        o, d12 = self.line_offset, self.implant_length
        return np.array([[o, 0.0, 0.0], [o, 0.0, -d12]]), np.array([1.0, 0.0, 0.0])

    @property
    def head(self) -> float:
        """The widest radius among the shapes other than the rod (m): the feed backs the tool
        out until its origin is ``head + implant_length`` above the mouth opening."""
        return max((s.radius for s in self.shapes if s.name != "rod"), default=0.0)

    @classmethod
    def from_dict(cls, d: dict, *, field: str = "instrument") -> Instrument:
        """The instrument :meth:`to_dict` wrote (a plan's ``placement.verification.tool``)."""
        try:
            shapes = tuple(Shape(s["name"], s["kind"], s["a"], s["b"], s["radius"])
                           for s in d["shapes"])
            return cls(d["name"], shapes, rod_radius=d["rod_radius"],
                       implant_length=d["implant_length"], rod_length=d["rod_length"],
                       source=d.get("source", ""), line_offset=d.get("line_offset", 0.0))
        except (KeyError, TypeError) as exc:
            raise InputError(field, f"expected an instrument's shapes and lengths ({exc})") \
                from None

    def to_dict(self) -> dict:
        return {"name": self.name, "source": self.source, "line_offset": self.line_offset,
                "rod_radius": self.rod_radius,
                "implant_length": self.implant_length, "rod_length": self.rod_length,
                "shapes": [s.to_dict() for s in self.shapes], "units": "m",
                "frame": "Tool: origin at the head centre, x along the rod out of the mouth, "
                         "z along the implant axis (the implant points to -z)"}


def _length(name: str, value, positive: bool = False, *, finite: bool = True) -> float:
    """A length (m) >= 0 (> 0 when ``positive``; infinite allowed when not ``finite``)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"instrument.{name}", f"expected a number (m), got {value!r}") from None
    if np.isnan(v) or v < 0 or (positive and v == 0) or (finite and not np.isfinite(v)):
        kind = "positive" if positive else ">= 0"
        raise InputError(f"instrument.{name}", f"expected a {kind} length (m), got {value!r}")
    return v
