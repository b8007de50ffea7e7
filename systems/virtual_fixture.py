"""The conical virtual fixture (VF) that guards the feed (seed 000 Sec. 2.2, its ref. [12]).

Geometry. The allowed region is a solid of revolution about the VF axis, line1 of the placement
(through the feeding target T = Tool origin, direction D out of the mouth). With s the axial
coordinate from T along D and rho the distance from the axis, the region is
    s >= 0 (when ``cap`` is set: the tool may not pass the target) and rho <= R(s),
where R is the profile: the cylinder of the tool's radius ``cylinder_radius`` from s = 0 to the
entry point at the mouth opening (s_entry, where line1 crosses the top slice plane), then a chain
of conical segments of given lengths and half-angles, each widening the radius by
length * tan(half_angle), and beyond the last segment a cylinder of the final radius.

Queries are batched over points: the signed distance to the region's boundary is computed exactly
in the meridian half-plane (s, rho) as the distance to the profile polyline, negative inside; its
gradient is the outward normal. The admittance law pushes a tool point back when it leaves:
    F = -(k * violation + b * max(v . n, 0)) * n      (zero inside),
and ``correct_velocity`` passes motion along the axis and removes the outward component of a
command at or over the boundary (plus a return velocity proportional to the violation).
Departure from ref. [12]: its segment sizes are not published; the defaults here (a 30 mm cone of
15 deg then a 50 mm cone of 30 deg outside the mouth) are ours and are stored in the plan.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from implantplan.systems.errors import InputError


def _perpendicular(u: np.ndarray) -> np.ndarray:
    a = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e = a - np.dot(a, u) * u
    return e / np.linalg.norm(e)


@dataclass
class VirtualFixture:
    """A chain of cones ending in a cylinder on the feeding axis (all lengths in m, Center frame).

    Attributes:
        origin: (3,) feeding target T on the axis (s = 0).
        direction: (3,) unit axis D, pointing out of the mouth.
        entry_distance: s of the entry point at the mouth opening (m).
        cylinder_radius: radius of the final (innermost) cylinder, the tool's radius (m).
        segment_lengths: (S,) axial lengths of the cones beyond the entry, inner to outer (m).
        half_angles: (S,) half-angles of those cones (rad), in [0, pi/2).
        cap: forbid s < 0 (passing the target).
    """

    origin: np.ndarray
    direction: np.ndarray
    entry_distance: float
    cylinder_radius: float
    segment_lengths: np.ndarray
    half_angles: np.ndarray
    cap: bool = True

    def __post_init__(self):
        self.origin = np.asarray(self.origin, dtype=float).reshape(3)
        d = np.asarray(self.direction, dtype=float).reshape(3)
        n = np.linalg.norm(d)
        if not np.all(np.isfinite(self.origin)):
            raise InputError("vf.origin", "expected 3 finite coordinates (m)")
        if not np.isfinite(n) or n < 1e-12:
            raise InputError("vf.direction", "expected a finite, non-zero direction")
        self.direction = d / n
        self.segment_lengths = np.atleast_1d(np.asarray(self.segment_lengths, dtype=float))
        self.half_angles = np.atleast_1d(np.asarray(self.half_angles, dtype=float))
        if self.segment_lengths.shape != self.half_angles.shape or self.segment_lengths.ndim != 1:
            raise InputError("vf.segment_lengths", "expected one half-angle per segment")
        if np.any(~np.isfinite(self.segment_lengths)) or np.any(self.segment_lengths <= 0):
            raise InputError("vf.segment_lengths", "expected lengths > 0 m")
        if np.any(~np.isfinite(self.half_angles)) or np.any(
            (self.half_angles < 0) | (self.half_angles >= np.pi / 2)
        ):
            raise InputError("vf.half_angles", "expected half-angles in [0, pi/2) rad")
        self.entry_distance = float(self.entry_distance)
        self.cylinder_radius = float(self.cylinder_radius)
        if not np.isfinite(self.entry_distance) or self.entry_distance < 0:
            raise InputError("vf.entry_distance", "expected a distance >= 0 m")
        if not np.isfinite(self.cylinder_radius) or self.cylinder_radius < 0:
            raise InputError("vf.cylinder_radius", "expected a radius >= 0 m")
        self.cap = bool(self.cap)
        self._e1 = _perpendicular(self.direction)
        s, r = self.profile()
        far = s[-1] + 1e3  # the last radius continues as a cylinder
        self._s = np.concatenate([s, [far]])
        self._r = np.concatenate([r, [r[-1]]])
        if self.cap:  # the cap disc at s = 0 from the axis to the cylinder
            self._s = np.concatenate([[0.0], self._s])
            self._r = np.concatenate([[0.0], self._r])
        else:  # the cylinder continues past the target
            self._s = np.concatenate([[-1e3], self._s])
            self._r = np.concatenate([[r[0]], self._r])

    # -- construction -------------------------------------------------------------------------

    @classmethod
    def from_placement(
        cls,
        placement,
        fpsm,
        *,
        cylinder_radius: float | None = None,
        segment_lengths=(0.03, 0.05),
        half_angles_deg=(15.0, 30.0),
        cap: bool = True,
    ) -> VirtualFixture:
        """The VF of a placement: axis = line1 through the Tool origin, entry where line1
        crosses the model's top slice plane (the mouth opening; 0 if it never does), cylinder
        radius = the rod radius unless given."""
        X_CT = np.asarray(placement.X_CT, dtype=float)
        origin = X_CT[:3, 3]
        direction = X_CT[:3, 0]  # Tool x is along line1 (Eq. 19)
        z_top = fpsm.z_range[1]
        entry = (z_top - origin[2]) / direction[2] if direction[2] > 1e-12 else 0.0
        r = placement.rod_radius if cylinder_radius is None else cylinder_radius
        return cls(
            origin=origin,
            direction=direction,
            entry_distance=max(float(entry), 0.0),
            cylinder_radius=r,
            segment_lengths=segment_lengths,
            half_angles=np.deg2rad(np.asarray(half_angles_deg, dtype=float)),
            cap=cap,
        )

    def profile(self) -> tuple[np.ndarray, np.ndarray]:
        """Profile vertices (s, R(s)) from the target out to the end of the last cone."""
        s = np.concatenate(
            [[0.0, self.entry_distance], self.entry_distance + np.cumsum(self.segment_lengths)]
        )
        widen = np.cumsum(self.segment_lengths * np.tan(self.half_angles))
        r = np.concatenate([[self.cylinder_radius] * 2, self.cylinder_radius + widen])
        return s, r

    @property
    def entry_point(self) -> np.ndarray:
        return self.origin + self.entry_distance * self.direction

    def radius_at(self, s) -> np.ndarray:
        """Allowed radius R(s) (m); NaN where s < 0 and the cap is set."""
        s = np.asarray(s, dtype=float)
        prof_s, prof_r = self.profile()
        r = np.interp(s, prof_s, prof_r)  # constant beyond both ends
        return np.where((s < 0) & self.cap, np.nan, r)

    # -- queries ------------------------------------------------------------------------------

    def _meridian(self, p: np.ndarray):
        rel = p - self.origin
        s = rel @ self.direction
        radial = rel - s[..., None] * self.direction
        rho = np.linalg.norm(radial, axis=-1)
        safe = rho > 1e-15
        e_rho = np.where(safe[..., None], radial / np.where(safe, rho, 1.0)[..., None], self._e1)
        return s, rho, e_rho

    def _signed(self, p: np.ndarray):
        """Signed distance (..., ) and outward unit normal (..., 3)."""
        s, rho, e_rho = self._meridian(p)
        a_s, a_r = self._s[:-1], self._r[:-1]
        b_s, b_r = self._s[1:], self._r[1:]
        ds, dr = b_s - a_s, b_r - a_r
        ps, pr = s[..., None] - a_s, rho[..., None] - a_r  # (..., E)
        seg2 = ds * ds + dr * dr
        t = np.clip((ps * ds + pr * dr) / np.where(seg2 > 0, seg2, 1.0), 0.0, 1.0)
        qs, qr = ps - t * ds, pr - t * dr  # point minus closest point on each edge
        dist2 = qs * qs + qr * qr
        k = np.argmin(dist2, axis=-1)
        qs = np.take_along_axis(qs, k[..., None], -1)[..., 0]
        qr = np.take_along_axis(qr, k[..., None], -1)[..., 0]
        dist = np.sqrt(qs * qs + qr * qr)
        R = np.interp(s, self._s, self._r)
        inside = (rho <= R) & ((s >= 0) | ~self.cap)
        sign = np.where(inside, -1.0, 1.0)
        # outward normal in the meridian plane: from the closest point away from the inside
        with np.errstate(invalid="ignore", divide="ignore"):
            ns, nr = sign * qs / dist, sign * qr / dist
        # on the boundary (dist = 0) use the edge's outward normal
        on = dist < 1e-15
        es = np.take_along_axis(np.broadcast_to(ds, ps.shape), k[..., None], -1)[..., 0]
        er = np.take_along_axis(np.broadcast_to(dr, ps.shape), k[..., None], -1)[..., 0]
        el = np.hypot(es, er)
        ns = np.where(on, -er / el, ns)  # edge direction (es, er) turned by +90 deg
        nr = np.where(on, es / el, nr)
        normal = ns[..., None] * self.direction + nr[..., None] * e_rho
        return sign * dist, normal

    def distance(self, points) -> np.ndarray:
        """Signed distance (m) of tool points (..., 3) to the region's boundary, < 0 inside."""
        return self._signed(self._points(points))[0]

    def violation(self, points) -> np.ndarray:
        """How far (m) points are outside the allowed region, >= 0."""
        return np.maximum(self.distance(points), 0.0)

    def normal(self, points) -> np.ndarray:
        """Outward unit normal of the nearest boundary, (..., 3)."""
        return self._signed(self._points(points))[1]

    def force(self, points, velocities, *, stiffness: float, damping: float = 0.0) -> np.ndarray:
        """Restoring force (N) by the admittance law: -(k * violation + b * max(v.n, 0)) n
        for points outside, zero inside. ``stiffness`` N/m, ``damping`` N s/m."""
        p = self._points(points)
        v = np.asarray(velocities, dtype=float)
        d, n = self._signed(p)
        out = d > 0
        vn = np.maximum(np.sum(v * n, axis=-1), 0.0)
        mag = np.where(out, stiffness * np.maximum(d, 0.0) + damping * vn, 0.0)
        return -mag[..., None] * n

    def correct_velocity(
        self,
        points,
        v_cmd,
        *,
        dt: float | None = None,
        return_gain: float = 10.0,
        tolerance: float = 1e-9,
    ) -> np.ndarray:
        """Filter commanded tool velocities (m/s) so the tool stays in the region.

        Motion along the boundary (and along the axis) passes. The outward normal component is
        limited to what reaches the boundary in one step ``dt`` (if given), or removed at or over
        the boundary (within ``tolerance``); a point outside also gets a return velocity
        ``-return_gain * violation * n`` (1/s).
        """
        p = self._points(points)
        v = np.array(np.broadcast_to(np.asarray(v_cmd, dtype=float), p.shape))
        d, n = self._signed(p)
        vn = np.sum(v * n, axis=-1)
        if dt is None:
            allowed = np.where(d < -tolerance, np.inf, 0.0)
        else:
            allowed = np.maximum(-d, 0.0) / float(dt)
        excess = np.maximum(vn - allowed, 0.0)
        v = v - excess[..., None] * n
        return v - (return_gain * np.maximum(d, 0.0))[..., None] * n

    @staticmethod
    def _points(points) -> np.ndarray:
        p = np.asarray(points, dtype=float)
        if p.shape[-1:] != (3,) or not np.all(np.isfinite(p)):
            raise InputError("points", "expected finite points of shape (..., 3) in m")
        return p

    # -- files --------------------------------------------------------------------------------

    def to_dict(self) -> dict:
        return {
            "frame": "Center",
            "origin": self.origin.tolist(),
            "direction": self.direction.tolist(),
            "entry_distance": self.entry_distance,
            "entry_point": self.entry_point.tolist(),
            "cylinder_radius": self.cylinder_radius,
            "segment_lengths": self.segment_lengths.tolist(),
            "half_angles": self.half_angles.tolist(),
            "cap": self.cap,
        }

    @classmethod
    def from_dict(cls, data: dict) -> VirtualFixture:
        if not isinstance(data, dict):
            raise InputError("vf", "expected a mapping")
        keys = (
            "origin",
            "direction",
            "entry_distance",
            "cylinder_radius",
            "segment_lengths",
            "half_angles",
        )
        missing = [k for k in keys if k not in data]
        if missing:
            raise InputError("vf", f"missing {', '.join(missing)}")
        return cls(**{k: data[k] for k in keys}, cap=data.get("cap", True))
