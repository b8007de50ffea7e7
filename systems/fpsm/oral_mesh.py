"""Oral meshes in: loading, validation, the Center frame, closing open cuts, a procedural cavity.

The FPSM (seed 000, Wang et al. 2023, Sec. 3) is fitted to a triangle mesh of the oral cavity's
surface, seen from the inside. This module turns any mesh file trimesh reads (STL, OBJ including
quads, PLY, OFF, GLB) into a clean :class:`trimesh.Trimesh` in metres, gives the Center frame
(origin and Z axis out of the mouth, paper Fig. 4) as a 4x4 pose ``X_WC`` in the mesh's frame,
and closes open cuts of scanned meshes so rays cast from the axis always meet a wall.

Closing open cuts (:func:`close_open_cuts`): every boundary loop (a cycle of edges used by one
face only) is closed by a fan of triangles around the loop's centroid (the mean of its edge
midpoints weighted by edge length), oriented so the cap continues the surface's orientation.
For a planar convex loop that is the flat cap; for a bent loop (the default mesh's single loop
runs along its floor and up its back) it is a cone towards the centroid, which lies inside the
loop's convex hull: it cuts the free space short there, i.e. errs on the safe side.

Opening the mouth (:func:`open_mouth`): scans of a closed mouth (the default mesh) leave no room
for the instrument; the lower jaw's tissue is rotated about the temporomandibular hinge, blended
smoothly across the occlusal plane (see the function).

The procedural oral cavity (:func:`procedural_oral_cavity`) is a closed tube around the Center
Z axis whose wall radius R(theta, z) is a known analytic function (arch, palate dome, tongue
floor, teeth ridges, mouth opening), so tests know the wall distances the fit must find.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from implantplan import models
from implantplan.systems.errors import InputError
from implantplan.systems.files import MAX_MESH_BYTES, input_file
from implantplan.systems.frames import frame_from_z, unit

UNITS = {"mm": 1e-3, "m": 1.0}
MAX_FACES = 2_000_000  # triangles of a scan (docs/formats.md, Bounds; the bundled one has 24,598)

_MODELS = models.MODELS_DIR / "oral"

# The default case: models/oral/oralCavityMesh.obj (ArtiSynth jaw-tongue model, mm; see
# models/oral/ATTRIBUTION.txt). Mesh axes: x front -> back (lips near x = 53.8 mm), y left-right,
# z up; the mesh is cut open along its floor (z = 54.1 mm) and at its back (x = 153.1 mm).
# Center frame: Z out of the mouth = mesh -x; Y up = mesh +z (so the lower jaw, where implant
# holes are drilled, is at Center -Y as in the paper's cylinder check); X = Y x Z = mesh -y.
# Origin on the mid-sagittal plane (y = 0) at the height of the lips' most forward point
# (z = 100 mm, where the front wall reaches x = 53.8 mm) and at x = 140 mm, where that line meets
# the back of the cavity once its open cuts are closed (close_open_cuts: the cap reaches
# x = 140.3 mm there). Center z then runs from the back (z ~ -0.3 mm) to the lips (z ~ 85.4 mm).
# The mesh is open along the floor and at the back, so fitting it needs close_open_cuts (or a
# cap radius and an explicit z range).
# These constants describe the mesh AS SCANNED (mouth closed: the paper's tool has no safe
# placement in it). The bundled surgical case, models/cases/default.yaml, opens the mouth first
# (open_mouth, 25 deg about the TMJ hinge) and uses its own Center frame and z range there.
DEFAULT_CAVITY = {
    "path": _MODELS / "oralCavityMesh.obj",
    "units": "mm",
    "center_origin_mm": (140.0, 0.0, 100.0),
    "center_z": (-1.0, 0.0, 0.0),
    "center_x_hint": (0.0, -1.0, 0.0),
}


def load_oral_mesh(path, *, units: str = "mm", field: str = "mesh") -> trimesh.Trimesh:
    """Load a scanner's mesh file and return it repaired, validated and in metres.

    Every format loads to the same mesh: STL (binary or ASCII) stores each triangle with its own
    three corners, so coincident vertices are merged (within trimesh's merge tolerance, 1e-8 m);
    then zero-area and duplicate faces are dropped, unreferenced vertices removed, and the
    winding made consistent across shared edges (the orientation of the first face wins, so a
    cavity seen from the inside stays seen from the inside).

    Args:
        path: any file trimesh loads (STL, OBJ incl. quads, PLY, OFF, GLB; scenes are merged).
        units: ``"mm"`` or ``"m"``: the unit of the file's coordinates.
        field: name used in error messages.

    Returns:
        A :class:`trimesh.Trimesh` in metres; ``mesh.metadata["implantplan"]`` records the source,
        the input units and the repairs (``repairs``: merged vertices, dropped zero-area and
        duplicate faces, removed unreferenced vertices, flipped faces).
    """
    if units not in UNITS:
        raise InputError("units", f"expected one of {sorted(UNITS)}, got {units!r}")
    path = input_file(path, field, max_bytes=MAX_MESH_BYTES)
    try:
        with open(path, "rb") as stream:
            stream.read(1)
    except OSError as exc:
        raise InputError(field, f"cannot read {str(path)!r}: {exc.strerror or exc}") from None
    try:
        loaded = trimesh.load(path, process=False, force="mesh")
    except ImportError:  # trimesh's text fallback wants an optional decoder for garbage bytes
        raise InputError(
            field, f"could not read {path} as a mesh: the file is corrupt or not a mesh format"
        ) from None
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise InputError(field, f"could not read {path} as a mesh ({exc})") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(getattr(loaded, "faces", ())) == 0:
        raise InputError(field, f"{path} holds no triangle mesh")
    if len(loaded.faces) > MAX_FACES:
        raise InputError(field, f"{path} has {len(loaded.faces)} faces; expected at most "
                         f"{MAX_FACES} (decimate the scan)")
    mesh = trimesh.Trimesh(
        vertices=np.asarray(loaded.vertices, dtype=float) * UNITS[units],
        faces=np.asarray(loaded.faces),
        process=False,
    )
    mesh = repair_mesh(validate_mesh(mesh, field=field))
    mesh.metadata["implantplan"] = {
        **mesh.metadata.get("implantplan", {}),
        "source": str(path),
        "units_in": units,
    }
    return mesh


def repair_mesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Merge coincident vertices, drop duplicate faces and unused vertices, make the winding
    consistent; the counts go to ``metadata["implantplan"]["repairs"]`` (with the zero-area faces
    :func:`validate_mesh` removed). Returns a new mesh."""
    out = mesh.copy()
    meta = dict(mesh.metadata.get("implantplan", {}))
    n_vertices = len(out.vertices)
    out.merge_vertices()
    merged = n_vertices - len(out.vertices)
    # after merging, faces that collapsed to an edge or a point have zero area
    tri = out.vertices[out.faces]
    degenerate = ~(
        (out.faces[:, 0] != out.faces[:, 1])
        & (out.faces[:, 1] != out.faces[:, 2])
        & (out.faces[:, 0] != out.faces[:, 2])
    ) | (np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) == 0)
    unique = np.zeros(len(out.faces), dtype=bool)
    unique[out.unique_faces()] = True
    keep = unique & ~degenerate
    n_unreferenced = len(out.vertices)
    out.update_faces(keep)
    out.remove_unreferenced_vertices()
    n_unreferenced -= len(out.vertices)
    before = out.faces.copy()
    trimesh.repair.fix_winding(out)
    flipped = int(np.count_nonzero(np.any(out.faces != before, axis=1)))
    meta["repairs"] = {
        "merged_vertices": int(merged),
        "removed_zero_area_faces": int(meta.get("removed_zero_area_faces", 0))
        + int(np.count_nonzero(degenerate)),
        "removed_duplicate_faces": int(np.count_nonzero(~unique & ~degenerate)),
        "removed_unreferenced_vertices": int(n_unreferenced),
        "flipped_faces": flipped,
    }
    out.metadata["implantplan"] = meta
    return out


def validate_mesh(mesh: trimesh.Trimesh, *, field: str = "mesh") -> trimesh.Trimesh:
    """Check a mesh is usable and remove its zero-area faces (counted in the metadata).

    Errors: no faces, non-finite vertex coordinates, faces indexing missing vertices.
    Returns a new mesh (the input is not modified).
    """
    V = np.asarray(mesh.vertices, dtype=float)
    F = np.asarray(mesh.faces)
    if F.ndim != 2 or F.shape[0] == 0 or V.shape[0] == 0:
        raise InputError(field, "the mesh is empty (no triangles)")
    if not np.all(np.isfinite(V)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(V), axis=1)))
        raise InputError(field, f"{bad} vertices have NaN or infinite coordinates")
    if F.min() < 0 or F.max() >= V.shape[0]:
        raise InputError(field, "faces index vertices that do not exist")
    tri = V[F]
    doubled_area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    scale = float(np.ptp(V, axis=0).max())
    keep = doubled_area > 1e-12 * scale * scale
    if not np.any(keep):
        raise InputError(field, "every triangle has zero area")
    out = trimesh.Trimesh(vertices=V.copy(), faces=F[keep].copy(), process=False)
    out.metadata["implantplan"] = {
        **dict(mesh.metadata.get("implantplan", {})),
        "removed_zero_area_faces": int(np.count_nonzero(~keep)),
    }
    return out


def center_frame(origin, z_axis, *, x_hint=None) -> np.ndarray:
    """X_WC: the Center frame in the mesh frame from its origin, Z axis (out of the mouth) and an
    optional x hint (made orthogonal to Z; default mesh x, or y when Z is along x)."""
    origin = np.asarray(origin, dtype=float)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise InputError("center_origin", "expected 3 finite coordinates")
    return frame_from_z(origin, unit(z_axis, field="center_z"), x_hint=x_hint, field="center_z")


def default_center_frame() -> np.ndarray:
    """X_WC (m) of the default case (see DEFAULT_CAVITY)."""
    return center_frame(
        np.asarray(DEFAULT_CAVITY["center_origin_mm"]) * 1e-3,
        DEFAULT_CAVITY["center_z"],
        x_hint=DEFAULT_CAVITY["center_x_hint"],
    )


def load_default_cavity() -> tuple[trimesh.Trimesh, np.ndarray]:
    """The default oral cavity mesh (m) and its Center frame X_WC."""
    mesh = load_oral_mesh(DEFAULT_CAVITY["path"], units=DEFAULT_CAVITY["units"])
    return mesh, default_center_frame()


def boundary_loops(mesh: trimesh.Trimesh) -> list[np.ndarray]:
    """Open boundary loops as arrays of vertex indices, in the direction of their faces' edges.

    A boundary edge is a directed face edge (a, b) whose reverse (b, a) is in no face. Loops are
    followed from each unvisited edge to the edge starting where it ends.
    """
    F = np.asarray(mesh.faces)
    directed = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    n = int(len(mesh.vertices))
    key = directed[:, 0].astype(np.int64) * n + directed[:, 1]
    reverse = directed[:, 1].astype(np.int64) * n + directed[:, 0]
    # undirected count 1 <=> neither a second copy nor the reverse exists
    undirected = np.sort(directed, axis=1)
    ukey = undirected[:, 0].astype(np.int64) * n + undirected[:, 1]
    _, inverse, counts = np.unique(ukey, return_inverse=True, return_counts=True)
    open_edges = directed[(counts[inverse] == 1) & ~np.isin(key, reverse)]
    if len(open_edges) == 0:
        return []
    nxt: dict[int, list[int]] = {}
    for i, (a, _b) in enumerate(open_edges):
        nxt.setdefault(int(a), []).append(i)
    used = np.zeros(len(open_edges), dtype=bool)
    loops = []
    for start in range(len(open_edges)):
        if used[start]:
            continue
        loop = []
        e = start
        while not used[e]:
            used[e] = True
            a, b = open_edges[e]
            loop.append(int(a))
            candidates = [c for c in nxt.get(int(b), []) if not used[c]]
            if not candidates:
                break
            e = candidates[0]
        if len(loop) >= 3:
            loops.append(np.asarray(loop, dtype=np.int64))
    return loops


def close_open_cuts(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, dict]:
    """Close every open boundary loop by a fan of triangles around its centroid.

    The centroid is the edge-length-weighted mean of the loop's edge midpoints. For a boundary
    edge a -> b (as it runs in its face) the cap triangle is (b, a, c), so the cap's orientation
    continues the surface's. See the module docstring for what this does to bent loops.

    Returns:
        ``(closed_mesh, info)`` with ``info = {"loops": k, "loop_edges": [...],
        "cap_triangles": t}``.
    """
    loops = boundary_loops(mesh)
    V = np.asarray(mesh.vertices, dtype=float)
    F = np.asarray(mesh.faces)
    new_vertices = [V]
    new_faces = [F]
    n = len(V)
    for loop in loops:
        a = loop
        b = np.roll(loop, -1)
        mid = 0.5 * (V[a] + V[b])
        length = np.linalg.norm(V[b] - V[a], axis=1)
        centroid = (mid * length[:, None]).sum(axis=0) / max(length.sum(), 1e-300)
        new_vertices.append(centroid[None, :])
        new_faces.append(np.stack([b, a, np.full_like(a, n)], axis=1))
        n += 1
    closed = trimesh.Trimesh(
        vertices=np.concatenate(new_vertices), faces=np.concatenate(new_faces), process=False
    )
    closed.metadata["implantplan"] = dict(mesh.metadata.get("implantplan", {}))
    info = {
        "loops": len(loops),
        "loop_edges": [int(len(loop)) for loop in loops],
        "cap_triangles": int(sum(len(loop) for loop in loops)),
    }
    closed.metadata["implantplan"]["closed_open_cuts"] = info
    return closed, info


@dataclass
class ProceduralCavity:
    """A procedural oral cavity: the mesh (m, in the Center frame: X_WC = identity) and its
    analytic wall radius ``radius(theta, z)`` (m) about the Center Z axis for z in [0, length].

    Attributes:
        mesh: closed, watertight triangle mesh, normals pointing out of the cavity's air space.
        length: cavity length along Z (m); the +Z end is the mouth opening.
        params: the generator's parameters (for the record).
    """

    mesh: trimesh.Trimesh
    length: float
    params: dict = field(default_factory=dict)

    def radius(self, theta, z) -> np.ndarray:
        """Wall distance (m) from the Z axis at angle ``theta`` (rad) and height ``z`` (m)."""
        return _cavity_radius(np.asarray(theta, float), np.asarray(z, float), self.params)


def _cavity_radius(theta: np.ndarray, z: np.ndarray, p: dict) -> np.ndarray:
    # Center frame: Y up (palate), -Y the tongue floor, +-X the cheeks (dental arch).
    s = np.clip(z / p["length"], 0.0, 1.0)
    c, sn = np.cos(theta), np.sin(theta)
    # arch: elliptic section, wider at the back (s = 0) than at the front
    a = p["half_width"] * (1.0 - p["arch_taper"] * s)  # half width along X
    b_up = p["dome_height"] * (1.0 - p["dome_taper"] * s)  # palate dome height along +Y
    b_down = p["floor_depth"]  # tongue floor along -Y
    b = np.where(sn >= 0, b_up, b_down)
    r = 1.0 / np.sqrt((c / a) ** 2 + (sn / b) ** 2)
    # tongue floor: a bulge pushing the lower wall up near the middle of the cavity
    r = r - np.where(sn < 0, p["tongue_bulge"] * (sn**2) * np.sin(np.pi * s) ** 2, 0.0)
    # teeth ridges: bumps on the sides (|cos| large) repeating along z
    r = r - p["ridge_height"] * (c**4) * (0.5 + 0.5 * np.cos(2 * np.pi * p["ridges"] * s))
    # mouth opening: the section narrows towards the lips over the last `lip_fraction`
    t = np.clip((s - (1.0 - p["lip_fraction"])) / p["lip_fraction"], 0.0, 1.0)
    r = r * (1.0 - (1.0 - p["opening_ratio"]) * (3 * t**2 - 2 * t**3))
    # seeded small irregularity (smooth in theta and z)
    k = np.arange(1, p["noise_terms"] + 1)
    phase = np.asarray(p["noise_phase"])
    if k.size:
        wave = np.sin(np.multiply.outer(theta, k) + phase[: k.size]) * np.cos(
            np.multiply.outer(np.pi * s, k) + phase[k.size :]
        )
        r = r * (1.0 + p["noise"] * wave.sum(axis=-1) / k.size)
    return r


def procedural_oral_cavity(
    *,
    length: float = 0.08,
    half_width: float = 0.025,
    dome_height: float = 0.02,
    floor_depth: float = 0.015,
    arch_taper: float = 0.35,
    dome_taper: float = 0.25,
    tongue_bulge: float = 0.005,
    ridge_height: float = 0.002,
    ridges: int = 4,
    lip_fraction: float = 0.2,
    opening_ratio: float = 0.5,
    noise: float = 0.0,
    noise_terms: int = 3,
    seed: int = 0,
    angular_resolution: int = 128,
    axial_resolution: int = 64,
) -> ProceduralCavity:
    """A watertight procedural oral cavity around the Z axis, z in [0, ``length``] (m).

    The wall radius (see :meth:`ProceduralCavity.radius`) is an arch-shaped section (elliptic,
    narrowing by ``arch_taper`` in width and ``dome_taper`` in height from back to front), a
    palate dome above (+Y), a tongue floor below (-Y) with a bulge, teeth
    ridges on the sides repeating ``ridges`` times along z, and a smooth narrowing to
    ``opening_ratio`` over the last ``lip_fraction`` of the length (the mouth opening, +Z end).
    Both ends are closed by flat fan caps. ``noise`` (relative) adds a smooth seeded irregularity;
    the same seed gives the same mesh bit for bit. All geometric features can be set to zero,
    which leaves an elliptic (or, with equal axes, circular) cylinder.
    """
    for name, value in {
        "length": length,
        "half_width": half_width,
        "dome_height": dome_height,
        "floor_depth": floor_depth,
    }.items():
        if not np.isfinite(value) or value <= 0:
            raise InputError(name, f"expected a positive length in m, got {value}")
    for name, value in {"arch_taper": arch_taper, "dome_taper": dome_taper}.items():
        if not 0 <= value < 1:
            raise InputError(name, f"expected a fraction in [0, 1), got {value}")
    if not 0 < opening_ratio <= 1:
        raise InputError("opening_ratio", f"expected a ratio in (0, 1], got {opening_ratio}")
    if not 0 < lip_fraction <= 1:
        raise InputError("lip_fraction", f"expected a fraction in (0, 1], got {lip_fraction}")
    if angular_resolution < 8 or axial_resolution < 2:
        raise InputError("resolution", "expected angular >= 8 and axial >= 2 vertices")
    rng = np.random.default_rng(seed)
    params = {
        "length": float(length),
        "half_width": float(half_width),
        "dome_height": float(dome_height),
        "floor_depth": float(floor_depth),
        "arch_taper": float(arch_taper),
        "dome_taper": float(dome_taper),
        "tongue_bulge": float(tongue_bulge),
        "ridge_height": float(ridge_height),
        "ridges": int(ridges),
        "lip_fraction": float(lip_fraction),
        "opening_ratio": float(opening_ratio),
        "noise": float(noise),
        "noise_terms": int(noise_terms),
        "noise_phase": rng.uniform(0, 2 * np.pi, 2 * int(noise_terms)).tolist(),
        "seed": int(seed),
    }
    nt, nz = int(angular_resolution), int(axial_resolution)
    theta = np.arange(nt) * (2 * np.pi / nt)
    z = np.linspace(0.0, length, nz)
    T, Zg = np.meshgrid(theta, z)  # (nz, nt)
    R = _cavity_radius(T, Zg, params)
    if np.any(R <= 0):
        raise InputError("procedural_oral_cavity", "features leave no free space somewhere")
    ring = np.stack([R * np.cos(T), R * np.sin(T), Zg], axis=-1).reshape(-1, 3)
    vertices = np.concatenate([ring, [[0.0, 0.0, 0.0], [0.0, 0.0, length]]])
    bottom, top = nz * nt, nz * nt + 1
    i = np.arange(nz - 1)[:, None] * nt
    j = np.arange(nt)[None, :]
    a = (i + j).ravel()
    b = (i + (j + 1) % nt).ravel()
    c = a + nt
    d = b + nt
    # outward normals (away from the axis): (a, b, d) and (a, d, c) with theta increasing
    side = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    jj = np.arange(nt)
    cap0 = np.stack([np.full(nt, bottom), (jj + 1) % nt, jj], 1)  # normal -Z
    last = (nz - 1) * nt
    cap1 = np.stack([np.full(nt, top), last + jj, last + (jj + 1) % nt], 1)  # normal +Z
    mesh = trimesh.Trimesh(
        vertices=vertices, faces=np.concatenate([side, cap0, cap1]), process=False
    )
    return ProceduralCavity(mesh=mesh, length=float(length), params=params)


def rotate_about_axis(points: np.ndarray, point: np.ndarray, axis: np.ndarray, angle):
    """Rotate each of ``points`` (K, 3) about the line through ``point`` along the unit ``axis``
    by its own ``angle`` (K,) rad (right-hand rule; Rodrigues' formula)."""
    v = points - point
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    kxv = np.cross(axis, v)
    kdv = v @ axis
    return point + v * c + kxv * s + np.outer(kdv, axis) * (1.0 - c)


def _vector3(value, name: str, *, nonzero: bool = False) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(name, f"expected 3 numbers, got {value!r}") from None
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise InputError(name, f"expected 3 finite numbers, got {value!r}")
    if nonzero:
        n = float(np.linalg.norm(v))
        if n < 1e-12:
            raise InputError(name, "expected a non-zero direction")
        v = v / n
    return v


def open_mouth(
    mesh: trimesh.Trimesh,
    angle_deg: float,
    *,
    hinge_point,
    hinge_axis,
    occlusal_point,
    occlusal_normal,
    blend: float = 0.02,
) -> trimesh.Trimesh:
    """Open the mouth of a closed-mouth oral mesh by rotating the lower jaw's tissue.

    A kinematic jaw-opening model (pure rotation about the temporomandibular hinge, the first
    20-25 mm of a real opening): every vertex ``p`` is rotated about the hinge line (through
    ``hinge_point`` along ``hinge_axis``, right-hand rule) by ``w(s) * angle``, where ``s`` is
    its signed height above the occlusal plane (through ``occlusal_point``, normal
    ``occlusal_normal`` pointing to the upper jaw) and ``w`` is a smoothstep weight: 1 for
    ``s <= -blend/2`` (lower jaw, tongue floor and lower lip rotate rigidly), 0 for
    ``s >= blend/2`` (upper jaw and palate stay), ``3u^2 - 2u^3`` in between
    (``u = (blend/2 - s) / blend``). The map is smooth, so the mesh stays connected: the cheeks
    and the corners of the lips stretch across the blend band. Connectivity is unchanged
    (same faces, same vertex order). Departure from anatomy: no condylar translation, no
    tissue volume preservation; the opening at the incisors is then ``2 L sin(angle / 2)``
    for an incisor at distance L from the hinge.

    Args:
        mesh: oral mesh (m).
        angle_deg: opening angle in degrees, in [0, 45]; 0 returns an unchanged copy.
        hinge_point: (3,) a point of the hinge axis (m, mesh frame).
        hinge_axis: (3,) hinge direction; a positive angle rotates the lower jaw by the
            right-hand rule about it (so choose the sign that moves the chin down).
        occlusal_point: (3,) a point of the occlusal plane (m, mesh frame).
        occlusal_normal: (3,) occlusal plane normal, towards the upper jaw.
        blend: width (m) of the band across the occlusal plane where the weight goes from 1
            to 0; > 0.

    Returns:
        A new :class:`trimesh.Trimesh`; ``metadata["implantplan"]["open_mouth"]`` records the
        parameters, how many vertices moved and how many faces turned over (normal against
        the rotated original) or became degenerate.
    """
    try:
        angle = float(angle_deg)
    except (TypeError, ValueError):
        raise InputError("mouth_opening_deg", f"expected a number, got {angle_deg!r}") from None
    if not np.isfinite(angle) or not 0.0 <= angle <= 45.0:
        raise InputError("mouth_opening_deg", f"expected an angle in [0, 45] deg, got {angle}")
    hinge_point = _vector3(hinge_point, "hinge_point")
    hinge_axis = _vector3(hinge_axis, "hinge_axis", nonzero=True)
    occlusal_point = _vector3(occlusal_point, "occlusal_point")
    occlusal_normal = _vector3(occlusal_normal, "occlusal_normal", nonzero=True)
    try:
        blend = float(blend)
    except (TypeError, ValueError):
        raise InputError("blend", f"expected a width in m, got {blend!r}") from None
    if not np.isfinite(blend) or blend <= 0:
        raise InputError("blend", f"expected a positive width in m, got {blend}")
    V = np.asarray(mesh.vertices, dtype=float)
    F = np.asarray(mesh.faces)
    V2, a = opening_map(V, angle, hinge_point, hinge_axis, occlusal_point, occlusal_normal,
                        blend)
    moved = a != 0
    out = trimesh.Trimesh(vertices=V2, faces=F.copy(), process=False)
    inverted, degenerate = face_flips(mesh, out, hinge_axis, a)
    out.metadata["implantplan"] = {
        **dict(mesh.metadata.get("implantplan", {})),
        "open_mouth": {
            "angle_deg": angle,
            "hinge_point": hinge_point.tolist(),
            "hinge_axis": hinge_axis.tolist(),
            "occlusal_point": occlusal_point.tolist(),
            "occlusal_normal": occlusal_normal.tolist(),
            "blend": blend,
            "moved_vertices": int(np.count_nonzero(moved)),
            "inverted_faces": inverted,
            "degenerate_faces": degenerate,
        },
    }
    return out


def opening_map(points, angle_deg, hinge_point, hinge_axis, occlusal_point, occlusal_normal,
                blend) -> tuple[np.ndarray, np.ndarray]:
    """The jaw-opening model's point map (see :func:`open_mouth`; arguments as there, already
    validated): the moved points (n, 3) and each point's rotation angle (rad). Used for the
    mesh's vertices and for anatomy in the scanned frame (systems.anatomy)."""
    V = np.asarray(points, dtype=float)
    s = (V - occlusal_point) @ occlusal_normal
    u = np.clip((0.5 * blend - s) / blend, 0.0, 1.0)
    w = u * u * (3.0 - 2.0 * u)  # smoothstep: 1 below the band, 0 above
    a = np.deg2rad(angle_deg) * w
    moved = a != 0  # an angle of 0 returns the points bit for bit
    V2 = V.copy()
    V2[moved] = rotate_about_axis(V[moved], hinge_point, hinge_axis, a[moved])
    return V2, a


def face_flips(before: trimesh.Trimesh, after: trimesh.Trimesh, axis, vertex_angle) -> tuple:
    """(inverted, degenerate) face counts of a deformation with per-vertex rotation angles.

    A face is inverted when its new normal points against its old normal rotated by the mean
    angle of its vertices about ``axis`` (what a rigid motion would give), and degenerate when
    its area falls below 1e-12 of the bounding box's squared size.
    """
    F = np.asarray(before.faces)

    def normals(V):
        t = V[F]
        return np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])

    n0 = normals(np.asarray(before.vertices, float))
    n1 = normals(np.asarray(after.vertices, float))
    ang = np.asarray(vertex_angle, float)[F].mean(axis=1)
    n0r = rotate_about_axis(n0, np.zeros(3), unit(axis), ang)
    scale = float(np.ptp(np.asarray(after.vertices), axis=0).max())
    area = np.linalg.norm(n1, axis=1)
    degenerate = area <= 1e-12 * scale * scale
    inverted = (np.einsum("ij,ij->i", n0r, n1) <= 0) & ~degenerate
    return int(np.count_nonzero(inverted)), int(np.count_nonzero(degenerate))
