"""Clinical distances of a planned implant to the anatomy (DESIGN.md sections 4 and 12), in the
CBCT's patient frame (m).

An implant is a cylinder of radius r around the segment apex -> entry (flat ends). Distances
between implants and to the canal (a tube around a polyline: a capsule per segment) are FCL's
signed distances between those solids (python-fcl; GJK/EPA, exact to about 1e-10 m here,
tested against hand-derived values). Distances to voxel anatomy (teeth above a HU threshold,
bone) are bounded conservatively: a voxel of size h may hold its boundary anywhere within
sqrt(3) h / 2 of its centre, so that much is taken off every distance measured to voxel centres
(the verdict may refuse a few safe implants, never accept one too close).

Clinical bounds (DESIGN.md section 4): >= 2 mm implant to the inferior alveolar canal, >= 1.5 mm
to an adjacent tooth, >= 3 mm between implants, >= 1 mm of bone around the implant, >= 1.5 mm on
its facial side in the anterior maxilla (FDI 11-13, 21-23; deciduous 51-53, 61-63).
"""

from __future__ import annotations

import numpy as np

MIN_CANAL = 2.0e-3
MIN_TOOTH = 1.5e-3
MIN_INTER_IMPLANT = 3.0e-3
MIN_BONE = 1.0e-3
MIN_BONE_FACIAL_ANTERIOR_MAXILLA = 1.5e-3
ANTERIOR_MAXILLA = frozenset({11, 12, 13, 21, 22, 23, 51, 52, 53, 61, 62, 63})  # FDI
FACIAL_HALF_ANGLE = np.deg2rad(60.0)  # the facial side: directions within this of facial


def anterior_maxilla(site: str) -> bool:
    """True when a site's name is an FDI tooth number of the anterior maxilla (incisors and
    canines of the upper jaw), where the facial bone's bound is 1.5 mm."""
    return str(site).isdigit() and int(site) in ANTERIOR_MAXILLA


def point_cylinder_distance(points, apex, entry, radius: float) -> np.ndarray:
    """Exact distance of points (n, 3) to the solid cylinder of ``radius`` around apex -> entry
    (0 inside): with the axial coordinate a and radial distance rho of a point, the distance is
    hypot(max(-a, a - L, 0), max(rho - r, 0))."""
    axis = np.asarray(entry, float) - np.asarray(apex, float)
    L = float(np.linalg.norm(axis))
    axis = axis / L
    rel = points - apex
    a = rel @ axis
    rho = np.linalg.norm(rel - a[:, None] * axis, axis=1)
    return np.hypot(np.maximum(np.maximum(-a, a - L), 0.0), np.maximum(rho - radius, 0.0))


def _along(a, b):
    """(R, t) of a z-aligned FCL shape spanning the segment a -> b: rotation taking z to b - a,
    the midpoint."""
    from implantplan.systems.frames import frame_from_z

    X = frame_from_z(0.5 * (np.asarray(a, float) + np.asarray(b, float)),
                     np.asarray(b, float) - np.asarray(a, float))
    return X[:3, :3], X[:3, 3]


def implant_object(entry, apex, radius: float):
    """The implant as an FCL cylinder (apex -> entry)."""
    import fcl

    R, t = _along(apex, entry)
    return fcl.CollisionObject(fcl.Cylinder(radius, float(np.linalg.norm(entry - apex))),
                               fcl.Transform(R, t))


def _signed_distance(o1, o2) -> float:
    import fcl

    req = fcl.DistanceRequest(enable_signed_distance=True)
    return float(fcl.distance(o1, o2, req, fcl.DistanceResult()))


def canal_clearance(entry, apex, radius: float, polyline, canal_radius: float) -> float:
    """Surface distance (m) of the implant cylinder to a canal (the tube of ``canal_radius``
    around a polyline: one capsule per segment), by FCL (signed: negative inside)."""
    import fcl

    implant = implant_object(entry, apex, radius)
    poly = np.asarray(polyline, dtype=float)
    out = np.inf
    for a, b in zip(poly[:-1], poly[1:], strict=True):
        R, t = _along(a, b)
        seg = fcl.CollisionObject(fcl.Capsule(canal_radius, float(np.linalg.norm(b - a))),
                                  fcl.Transform(R, t))
        out = min(out, _signed_distance(implant, seg))
    return float(out)


def inter_implant_clearances(entries, apexes, radii) -> np.ndarray:
    """(n, n) surface distances (m) between the implant cylinders (FCL; diagonal +inf)."""
    objs = [implant_object(e, a, r) for e, a, r in zip(entries, apexes, radii, strict=True)]
    n = len(objs)
    d = np.full((n, n), np.inf)
    for i in range(n):
        for j in range(i + 1, n):
            d[i, j] = d[j, i] = _signed_distance(objs[i], objs[j])
    return d


def voxel_points(volume, mask: np.ndarray) -> np.ndarray:
    """Centres (m, patient frame) of the voxels of ``mask`` [k, j, i]."""
    kji = np.argwhere(mask)
    return volume.to_patient(kji[:, ::-1].astype(float)) * 1e-3


def tooth_clearance(volume, entry, apex, radius: float, threshold_hu: float, *,
                    reach: float = 15e-3) -> float:
    """Conservative distance (m) from the implant's surface to the nearest voxel at or above
    ``threshold_hu`` (teeth) within ``reach`` of it (+inf when none)."""
    h = float(np.max(volume.spacing)) * 1e-3
    lo = np.minimum(entry, apex) - reach - radius
    hi = np.maximum(entry, apex) + reach + radius
    inv = np.linalg.inv(volume.affine)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])]) * 1e3
    ijk = corners @ inv[:3, :3].T + inv[:3, 3]
    shape = np.array(volume.hu.shape[::-1])
    i0 = np.clip(np.floor(ijk.min(axis=0)).astype(int), 0, shape - 1)
    i1 = np.clip(np.ceil(ijk.max(axis=0)).astype(int) + 1, 0, shape)
    box = volume.hu[i0[2]:i1[2], i0[1]:i1[1], i0[0]:i1[0]] >= threshold_hu
    if not box.any():
        return float("inf")
    kji = np.argwhere(box) + i0[::-1]
    pts = volume.to_patient(kji[:, ::-1].astype(float)) * 1e-3
    d = point_cylinder_distance(pts, apex, entry, radius) - np.sqrt(3) / 2 * h
    return float(min(np.min(d), reach))


def bone_margin(volume, entry, apex, radius: float, threshold_hu: float, *,
                rings: int = 20, around: int = 24, reach: float = 6e-3,
                slope: float = 2e-3, facial=None) -> tuple[float, float]:
    """Bone around the implant (m): its least lateral bone thickness, and the depth (m) below
    the entry where bone begins (the crest).

    The crest is the first point of the axis, from the entry down, inside bone (HU >=
    ``threshold_hu``, nearest voxel). On ``rings`` rings of ``around`` points on the implant's
    surface from the crest to the apex, a ray runs outwards (perpendicular to the axis) in steps
    of half the smallest voxel until it meets a voxel outside bone (up to ``reach``); the
    thickness is that distance less one step and the voxel's half-diagonal (the boundary may
    lie anywhere in the voxel), so the value never exceeds the true lateral thickness. On each
    side the bone may begin up to ``slope`` below the crest (a sloping ridge): the points above
    that side's first point in bone, and within a voxel's diagonal below it (the top is known
    to a voxel's diagonal: a ray along a flat top at its level runs on its blurred edge), are
    not measured (the apex ring always is); a side whose bone begins deeper, or a
    surface point outside bone below it, or the apex outside bone, gives a negative value
    (dehiscence, perforation). With ``facial`` (a direction, m-frame; its part across the axis
    is taken) only the directions within :data:`FACIAL_HALF_ANGLE` of it count: the facial
    wall. Returns (-inf, nan) when the axis never enters bone."""
    h_max = float(np.max(volume.spacing)) * 1e-3
    step = 0.5 * float(np.min(volume.spacing)) * 1e-3
    half_diag = np.sqrt(3) / 2 * h_max
    axis = (entry - apex) / np.linalg.norm(entry - apex)
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    w = np.cross(axis, u)
    inv = np.linalg.inv(volume.affine)
    shape = np.array(volume.hu.shape)

    def is_bone(points):
        ijk = np.rint((points * 1e3) @ inv[:3, :3].T + inv[:3, 3]).astype(int)[..., ::-1]
        ok = np.all((ijk >= 0) & (ijk < shape), axis=-1)
        ijk = np.clip(ijk, 0, shape - 1)
        return ok & (volume.hu[ijk[..., 0], ijk[..., 1], ijk[..., 2]] >= threshold_hu)

    length = float(np.linalg.norm(entry - apex))
    depth = np.linspace(0.0, length, 4 * rings + 1)
    in_bone = is_bone(entry - depth[:, None] * axis)
    if not in_bone.any():
        return -float("inf"), float("nan")
    crest = float(depth[int(np.argmax(in_bone))])
    ring_depth = np.linspace(crest, length, rings)
    phi = np.linspace(0, 2 * np.pi, around, endpoint=False)
    radial = np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * w  # (A, 3)
    surface = (entry - ring_depth[:, None] * axis)[:, None] + radius * radial[None]  # (R, A, 3)
    t = np.arange(0.0, reach + step, step)
    samples = surface[:, :, None] + t[None, None, :, None] * radial[None, :, None]
    bone = is_bone(samples)  # (R, A, T)
    first_out = np.where(bone.all(axis=2), len(t), np.argmin(bone, axis=2))
    thickness = np.where(first_out == 0, -half_diag, t[np.maximum(first_out - 1, 0)]
                         - half_diag)
    thickness = np.where(first_out == len(t), reach, thickness)
    in_bone_surface = bone[:, :, 0]  # (R, A)
    side_starts = np.where(in_bone_surface.any(axis=0), np.argmax(in_bone_surface, axis=0),
                           rings)  # per direction, the first ring in bone
    # a side's bone top is known to a voxel's diagonal (the voxel, and the blur of a
    # reconstructed or resampled series): the rings within it below the side's first point in
    # bone run along a flat top's blurred edge, so the side is measured from below them
    start_depth = ring_depth[np.minimum(side_starts, rings - 1)]
    above = ring_depth[:, None] < start_depth[None, :] + 2 * half_diag
    above &= (np.arange(rings)[:, None] < rings - 1)  # the apex ring is always measured
    deep = ring_depth[np.minimum(side_starts, rings - 1)] - crest > slope
    measured = ~above | deep[None, :]
    thickness = np.where(above & deep[None, :], -half_diag, thickness)
    thickness = np.where(measured, thickness, np.inf)
    if facial is not None:
        f = np.asarray(facial, float) - (np.asarray(facial, float) @ axis) * axis
        f /= np.linalg.norm(f)
        thickness = np.where((radial @ f >= np.cos(FACIAL_HALF_ANGLE))[None, :], thickness,
                             np.inf)
    apex_out = not bool(is_bone(apex[None])[0])
    value = float(np.min(thickness)) - (half_diag if apex_out else 0.0)
    return (min(value, -half_diag) if apex_out else value), crest


def as_scanned(points, angle_deg: float, opening: dict, *, iterations: int = 60) -> np.ndarray:
    """Points of the opened scan (m) back in the scan's frame as scanned: a preimage under the
    jaw-opening map (systems.fpsm.oral_mesh.opening_map). That map rotates x about the hinge by
    angle * w(s(x)); so x = Rot(p, -theta) where theta solves theta = angle * w(s(Rot(p, -theta)))
    on [0, angle], a scalar equation per point solved by bisection (vectorized; a root exists
    since the two sides cross at the interval's ends). The residual is checked."""
    from implantplan.systems.fpsm.oral_mesh import opening_map, rotate_about_axis

    p = np.asarray(points, dtype=float)
    if angle_deg <= 0:
        return p.copy()
    hinge = np.asarray(opening["hinge_point"], float)
    axis = np.asarray(opening["hinge_axis"], float)
    axis = axis / np.linalg.norm(axis)
    o_pt = np.asarray(opening["occlusal_point"], float)
    o_n = np.asarray(opening["occlusal_normal"], float)
    o_n = o_n / np.linalg.norm(o_n)
    blend = float(opening["blend"])
    angle = np.deg2rad(angle_deg)

    def back(theta):
        return rotate_about_axis(p, hinge, axis, -theta)

    def g(theta):  # angle * w(s(x(theta))) - theta: >= 0 at 0, <= 0 at angle
        s = (back(theta) - o_pt) @ o_n
        u = np.clip((0.5 * blend - s) / blend, 0.0, 1.0)
        return angle * u * u * (3.0 - 2.0 * u) - theta

    lo, hi = np.zeros(len(p)), np.full(len(p), angle)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        up = g(mid) > 0
        lo, hi = np.where(up, mid, lo), np.where(up, hi, mid)
    x = back(0.5 * (lo + hi))
    residual = np.max(np.abs(opening_map(x, angle_deg, hinge, axis, o_pt, o_n, blend)[0] - p))
    if residual > 1e-9:
        raise RuntimeError(f"the jaw-opening map did not invert (residual {residual:.3g} m)")
    return x
