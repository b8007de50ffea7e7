"""Stage 1 of seed 000 (Wang et al. 2023, Sec. 3.2-3.3): fit the FPSM's slices to an oral mesh.

Wall distances. Slice j lies in the plane z = z_j of the Center frame. For a sample angle phi the
wall distance R(phi, z) is the distance from the axis point (0, 0, z) along the ray
(cos phi, sin phi, 0) to the first mesh hit. Rays are cast with trimesh's ray engine, which is
Embree's (package ``embreex``) when installed, else trimesh's pure-numpy engine.

Pre-assignment (paper Sec. 3.3): the triangles are bucketed by slab, the stretch [z_j, z_j+1]
between neighbouring slices; a ray cast at a height inside a slab is then tested only against
that slab's triangles (those whose z-extent overlaps it), one small scene per slab. Embree's
BVH already skips far triangles, so with Embree this pays only when many rays share each slab
scene: it is used for the dense check, not for the fit's few thousand rays (see
:func:`cast_walls`); with trimesh's numpy engine always. Both give the same distances (tested).

Conservative between slices: the FPSM's radius is linear in z between slices (Eq. 11), so if
both rho_j(phi) and rho_j+1(phi) stay below the nearest wall over the slab between them, so does
every interpolated radius at that angle. Each slice is therefore constrained by
R_j(phi) = min of R(phi, z) over ``slab_levels`` heights per slab in [z_j-1, z_j+1].
Between sample angles nothing is guaranteed; the dense check measures it.

Methods (both kept, compared in analyses/bench_fpsm.py):

- ``exact`` (default): the constraints rho(phi_i) = B(phi_i) rho <= R_j(phi_i) - margin are
  linear in rho. The area S = 1/2 rho^T Q rho (Eq. 6) is convex in rho, so its maximum over the
  constraint polytope is at a vertex; we start from the LP maximizing the mean radius (HiGHS),
  then solve successive LPs on the linearized area, max (Q rho_k)^T rho, each of which can only
  increase S (convexity: S(x) >= S(rho_k) + (Q rho_k)^T (x - rho_k)), until it stalls.
  Departure from DESIGN.md's "polish with SLSQP": an SLSQP polish from that point under the same
  constraints gained nothing on the default mesh (15 x 15 x 150) and took 5x longer, so it is
  not done. The constraints include rho(phi_i) >= 0: without them SLSQP "gains" area by
  negative radii (a negative rho counts as area on the opposite side). Zero penetration at the
  sample angles holds by construction: after the solve the curve is lowered by its largest
  residual violation (the basis weights sum to one, so subtracting c from every control radius
  lowers the whole curve by exactly c).
- ``paper``: F_aim = -S + lambda f_pene^2 (Eq. 7), f_pene = share of the Z sample points beyond
  the wall; normalized gradient descent (Eq. 8) with central differences (Eq. 9); Sec. 5.1
  settings: lambda 30000, alpha 0.1 mm, at most 1000 iterations (S in mm^2, as the paper).
  The paper does not say how it starts nor its Delta rho: we start from the largest circle that
  meets no wall at the samples and use Delta rho = alpha. Penetration is tested against the same
  conservative wall distances as ``exact`` (a point beyond the first wall hit along its ray), so
  the two methods differ only in the optimizer. All slices descend in lock step (vectorized);
  the best iterate seen is kept.

Diagnostics per slice: coverage = curve area / area of the polygon of wall hits at the slice's
own sample rays (the free region seen along the rays); coverage_of_allowed = the same against
the polygon of the constraints actually imposed (slab minimum minus margin), which isolates the
optimizer from the conservatism of the slabs and compares with the paper's Table 1, where the
boundary is one 2D curve; penetration at the sample angles; the
penetration rate on the dense check (``check_factor`` times the angles and the slab heights);
rays that met no real wall (capped by ``cap_radius``). Lengths in metres throughout, except the
``paper`` optimizer's internal mm.
"""

from __future__ import annotations

import time

import numpy as np
import trimesh
from scipy.optimize import linprog

from implantplan.systems import validate
from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.model import TWO_PI, area, area_matrix, basis_matrix
from implantplan.systems.frames import apply

METHODS = ("exact", "paper")
PRE_ASSIGN_RAYS = 100_000  # with Embree, pre-assign by slab from this many rays on
PAPER_SETTINGS = {"lambda_pene": 30000.0, "alpha_mm": 0.1, "max_iterations": 1000}


# -- ray casting ---------------------------------------------------------------------------------


def ray_engine(mesh: trimesh.Trimesh, engine: str = "auto"):
    """The ray intersector for ``mesh``: ``"auto"`` = trimesh's choice (Embree when the
    ``embreex`` package is installed), ``"embree"`` (error when missing), ``"numpy"``."""
    if engine == "numpy":
        from trimesh.ray.ray_triangle import RayMeshIntersector

        return RayMeshIntersector(mesh)
    if engine == "embree":
        from trimesh.ray import has_embree

        if not has_embree:
            raise InputError("engine", "Embree ray casting needs the embreex package")
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        return RayMeshIntersector(mesh)
    if engine == "auto":
        return mesh.ray
    raise InputError("engine", f"expected auto, embree or numpy, got {engine!r}")


def first_hits(intersector, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Distance along each (unit) ray to its first hit, inf where it hits nothing."""
    dist = np.full(len(origins), np.inf)
    if len(origins) == 0:
        return dist
    loc, index_ray, _ = intersector.intersects_location(origins, directions, multiple_hits=False)
    if len(index_ray):
        d = np.einsum("ij,ij->i", loc - origins[index_ray], directions[index_ray])
        np.minimum.at(dist, index_ray, np.maximum(d, 0.0))
    return dist


def slab_levels(slice_z: np.ndarray, per_gap: int) -> tuple[np.ndarray, np.ndarray]:
    """Heights ``per_gap`` per slab (starting at each slice) plus the top slice.

    Returns ``(levels (L,), gap (L,))`` with ``gap[l]`` the slab index (0..M-2) a level lies in;
    the top slice's level belongs to the last slab. Level ``j * per_gap`` is slice j.
    """
    z = np.asarray(slice_z, float)
    if z.size == 1:
        return z.copy(), np.zeros(1, dtype=np.int64)
    t = np.arange(per_gap) / per_gap
    levels = (z[:-1, None] + t[None, :] * np.diff(z)[:, None]).ravel()
    gap = np.repeat(np.arange(z.size - 1), per_gap)
    return np.append(levels, z[-1]), np.append(gap, z.size - 2)


def _uses_embree(engine: str) -> bool:
    from trimesh.ray import has_embree

    return engine == "embree" or (engine == "auto" and has_embree)


def cast_walls(
    mesh: trimesh.Trimesh,
    X_WC: np.ndarray,
    slice_z: np.ndarray,
    angles: np.ndarray,
    *,
    per_gap: int,
    engine: str = "auto",
    pre_assign: bool | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Wall distances R(phi, z) at ``per_gap`` heights per slab.

    Args:
        mesh: the oral mesh (m), in the frame X_WC refers to.
        X_WC: pose of the Center frame in the mesh frame.
        slice_z: (M,) increasing slice heights (m).
        angles: (Z,) ray angles phi (rad) in the Center XY plane.
        per_gap: heights per slab (>= 1).
        engine: see :func:`ray_engine`.
        pre_assign: bucket triangles by slab and cast each slab's rays against its own triangles
            (paper Sec. 3.3). ``None`` (default): always with the numpy engine; with Embree only
            for at least PRE_ASSIGN_RAYS rays (measured in analyses/bench_fpsm.py on the
            default mesh: for the fit's 6,450 rays one whole-mesh scene is faster, for the
            dense check's 404,400 rays the slab scenes are about 2x faster).

    Returns:
        ``(levels (L,), R (L, Z), info)``; ``R`` is inf where a ray hits nothing; info holds ray
        count, casting seconds and the triangles per slab (when pre-assigned).
    """
    levels, gap = slab_levels(slice_z, per_gap)
    angles = np.asarray(angles, float)
    if pre_assign is None:
        pre_assign = not _uses_embree(engine) or levels.size * angles.size >= PRE_ASSIGN_RAYS
    dirs_C = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=1)
    dirs_W = dirs_C @ X_WC[:3, :3].T

    def cast(intersector, rows):
        origins_C = np.zeros((rows.size, angles.size, 3))
        origins_C[..., 2] = levels[rows, None]
        origins = apply(X_WC, origins_C.reshape(-1, 3))
        dirs = np.broadcast_to(dirs_W, (rows.size,) + dirs_W.shape).reshape(-1, 3)
        d = first_hits(intersector, origins, np.ascontiguousarray(dirs))
        return d.reshape(rows.size, angles.size)

    R = np.full((levels.size, angles.size), np.inf)
    triangles = None
    t0 = time.perf_counter()
    if not pre_assign:
        R[:] = cast(ray_engine(mesh, engine), np.arange(levels.size))
    else:
        # Pre-assignment: each triangle's extent along Center z, bucketed by slab.
        zv = (np.asarray(mesh.vertices) - X_WC[:3, 3]) @ X_WC[:3, 2]
        zf = zv[np.asarray(mesh.faces)]
        f_lo, f_hi = zf.min(axis=1), zf.max(axis=1)
        order = np.argsort(f_lo)
        f_lo_sorted = f_lo[order]
        z = np.asarray(slice_z, float)
        bounds = np.stack([z[:-1], z[1:]], 1) if z.size > 1 else np.array([[z[0], z[0]]])
        triangles = []
        for g, (lo, hi) in enumerate(bounds):
            cand = order[: np.searchsorted(f_lo_sorted, hi, side="right")]
            faces = cand[f_hi[cand] >= lo]
            triangles.append(int(faces.size))
            rows = np.nonzero(gap == g)[0]
            if faces.size == 0:
                continue
            used, local = np.unique(np.asarray(mesh.faces)[faces], return_inverse=True)
            sub = trimesh.Trimesh(
                np.asarray(mesh.vertices)[used], local.reshape(-1, 3), process=False
            )  # only the slab's own vertices: the scene build is proportional to them
            R[rows] = cast(ray_engine(sub, engine), rows)
    info = {
        "rays": int(R.size),
        "seconds": time.perf_counter() - t0,
        "pre_assigned": bool(pre_assign),
        "triangles_per_slab": triangles,
        "triangles_total": int(len(mesh.faces)),
    }
    return levels, R, info


def axis_extent(
    mesh: trimesh.Trimesh, X_WC: np.ndarray, engine: str = "auto"
) -> tuple[float, float]:
    """The stretch (z_in, z_out) of the Center Z axis inside the cavity: the first wall hits
    from the Center origin along -Z and +Z (the origin must lie inside the cavity)."""
    o = np.repeat(X_WC[None, :3, 3], 2, axis=0)
    d = np.stack([-X_WC[:3, 2], X_WC[:3, 2]])
    dist = first_hits(ray_engine(mesh, engine), o, d)
    if not np.all(np.isfinite(dist)):
        side = " and ".join(
            s for s, hit in zip(("-Z", "+Z"), np.isfinite(dist), strict=True) if not hit
        )
        raise InputError(
            "z_range",
            f"the Center Z axis leaves the mesh along {side} without meeting a wall; put the "
            "origin inside the cavity or give the range (--z-range-mm)",
        )
    return -float(dist[0]), float(dist[1])


# -- the two optimizers --------------------------------------------------------------------------


def _lp(c: np.ndarray, A: np.ndarray, b: np.ndarray, bounds) -> np.ndarray | None:
    res = linprog(-c, A_ub=A, b_ub=b, bounds=bounds, method="highs")
    return res.x if res.status == 0 else None


def fit_slice_exact(
    B: np.ndarray, wall: np.ndarray, *, max_rounds: int = 30
) -> tuple[np.ndarray, dict]:
    """Max area with rho(phi_i) <= wall_i at the sample angles (``exact`` method, one slice).

    Args:
        B: (Z, N) basis at the sample angles.
        wall: (Z,) allowed radius per sample (wall distance minus margin), > 0, any unit.

    Returns:
        ``(rho (N,), info)``; rho(phi_i) <= wall_i exactly (see the module docstring).
    """
    Z, N = B.shape
    Q = area_matrix(N)
    # rho(phi) >= 0 at the samples too, and a box that keeps every LP bounded
    A = np.vstack([B, -B])
    b = np.concatenate([wall, np.zeros(Z)])
    top = 3.0 * float(wall.max())
    bounds = [(1e-9 * top, top)] * N
    rho = _lp(np.ones(N), A, b, bounds)
    rounds = 0
    if rho is None:  # numerically infeasible LP (should not happen with wall > 0): circle
        rho = np.full(N, float(wall.min()))
    else:
        s = 0.5 * rho @ Q @ rho
        while rounds < max_rounds:
            rounds += 1
            new = _lp(Q @ rho, A, b, bounds)
            if new is None:
                break
            s_new = 0.5 * new @ Q @ new
            if s_new <= s * (1.0 + 1e-9):
                if s_new > s:
                    rho, s = new, s_new
                break
            rho, s = new, s_new
    # partition of unity: subtracting c from every control radius lowers the curve by c (up to
    # rounding, hence the loop, which adds an ulp-sized step when rounding leaves a residue)
    lowered = 0.0
    tiny = 4 * np.finfo(float).eps * float(np.abs(wall).max())
    for _ in range(8):
        excess = float(np.max(B @ rho - wall))
        if excess <= 0:
            break
        rho = rho - (excess + tiny)
        lowered += excess + tiny
    return rho, {"lp_rounds": rounds, "lowered_by": lowered}


def fit_slices_paper(
    B: np.ndarray,
    wall: np.ndarray,
    *,
    lambda_pene: float = PAPER_SETTINGS["lambda_pene"],
    alpha: float = PAPER_SETTINGS["alpha_mm"],
    max_iterations: int = PAPER_SETTINGS["max_iterations"],
    delta: float | None = None,
) -> tuple[np.ndarray, dict]:
    """Eq. 7-9 for all slices at once (``paper`` method); lengths in mm as the paper.

    Args:
        B: (Z, N) basis at the sample angles.
        wall: (M, Z) wall distances (mm) at the samples.
        lambda_pene, alpha, max_iterations: Sec. 5.1 settings; ``delta`` (Eq. 9's Delta rho)
            defaults to ``alpha``.

    Returns:
        ``(rho (M, N) mm, info)`` with the iterations each slice ran.
    """
    M, Z = wall.shape
    N = B.shape[1]
    delta = alpha if delta is None else float(delta)
    Q = area_matrix(N)
    Qd = np.diag(Q)

    def penalty(samples: np.ndarray, w: np.ndarray) -> np.ndarray:
        f = np.count_nonzero(samples > w, axis=-1) / Z
        return lambda_pene * f * f

    rho = np.repeat(wall.min(axis=1, keepdims=True), N, axis=1)  # largest circle, our choice
    s = 0.5 * np.einsum("mi,ij,mj->m", rho, Q, rho)
    F = -s + penalty(rho @ B.T, wall)
    best, best_F = rho.copy(), F.copy()
    active = np.ones(M, dtype=bool)
    iterations = np.zeros(M, dtype=np.int64)
    for _ in range(max_iterations):
        if not active.any():
            break
        r = rho[active]
        w = wall[active][:, None, :]
        base = r @ B.T  # (m, Z)
        Qr = r @ Q  # (m, N); S(rho +- d e_i) = S +- d (Q rho)_i + d^2 Q_ii / 2 (exact)
        s_plus = -(0.5 * np.einsum("mi,mi->m", r, Qr)[:, None] + delta * Qr + 0.5 * delta**2 * Qd)
        s_minus = -(0.5 * np.einsum("mi,mi->m", r, Qr)[:, None] - delta * Qr + 0.5 * delta**2 * Qd)
        shifted = delta * B.T[None, :, :]  # (1, N, Z)
        F_plus = s_plus + penalty(base[:, None, :] + shifted, w)
        F_minus = s_minus + penalty(base[:, None, :] - shifted, w)
        grad = (F_plus - F_minus) / (2 * delta)  # Eq. 9
        norm = np.linalg.norm(grad, axis=1)
        moving = norm > 0
        step = np.zeros_like(r)
        step[moving] = alpha * grad[moving] / norm[moving, None]  # Eq. 8
        r = r - step
        idx = np.nonzero(active)[0]
        rho[idx] = r
        iterations[idx] += 1
        F_new = -0.5 * np.einsum("mi,ij,mj->m", r, Q, r) + penalty(r @ B.T, wall[idx])
        better = F_new < best_F[idx]
        best[idx[better]] = r[better]
        best_F[idx[better]] = F_new[better]
        active[idx[~moving]] = False
    return best, {"iterations": iterations.tolist(), "F_aim_mm2": best_F.tolist()}


# -- the fit -------------------------------------------------------------------------------------


def _check_int(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or int(value) != value or int(value) < minimum:
        raise InputError(name, f"expected an integer >= {minimum}, got {value!r}")
    return int(value)


def _polygon_area(R: np.ndarray) -> np.ndarray:
    """Area of the polygon through the points (R_i, phi_i), phi evenly spaced, per row."""
    Z = R.shape[-1]
    return 0.5 * np.sin(TWO_PI / Z) * np.sum(R * np.roll(R, -1, axis=-1), axis=-1)


def _ranges_deg(flags: np.ndarray, angles: np.ndarray) -> str:
    """Compact text for the angles (deg) where ``flags`` is set, e.g. '200-340'."""
    idx = np.nonzero(flags)[0]
    if idx.size == 0:
        return ""
    runs = np.split(idx, np.nonzero(np.diff(idx) > 1)[0] + 1)
    deg = np.degrees(angles)
    return ", ".join(
        f"{deg[r[0]]:.0f}" if r.size == 1 else f"{deg[r[0]]:.0f}-{deg[r[-1]]:.0f}" for r in runs
    )


def fit_fpsm(
    mesh: trimesh.Trimesh,
    X_WC: np.ndarray,
    *,
    slices: int,
    control_points: int,
    samples: int,
    z_range=None,
    method: str = "exact",
    margin: float = 0.0,
    cap_radius: float | None = None,
    close_open_cuts: bool = False,
    slab_levels_per_gap: int = 3,
    check_factor: int = 8,
    engine: str = "auto",
    pre_assign: bool | None = None,
    progress=None,
):
    """Fit the FPSM (stage 1) to an oral mesh.

    Args:
        mesh: oral cavity surface (m), e.g. from :func:`systems.fpsm.oral_mesh.load_oral_mesh`.
        X_WC: (4, 4) pose of the Center frame in the mesh frame (Z out of the mouth).
        slices: M >= 2 slices, evenly spaced over ``z_range``.
        control_points: N >= 3 control radii per slice.
        samples: Z >= N sample angles per slice (the constraint / penalty rays).
        z_range: (z_min, z_max) in Center (m) where the end slices go. Default: the stretch of
            the Z axis inside the cavity (:func:`axis_extent`), inset by half a slice spacing at
            each end (at the walls themselves the section shrinks to nothing).
        method: ``"exact"`` (default) or ``"paper"``, see the module docstring.
        margin: clearance (m) kept from the walls at the sample angles (``exact``; ``paper``
            fits to the walls moved in by it too).
        cap_radius: where a ray meets no wall (open scan), use this distance (m) instead of
            failing.
        close_open_cuts: close the mesh's open boundary loops first
            (:func:`systems.fpsm.oral_mesh.close_open_cuts`).
        slab_levels_per_gap: heights per slab at which walls are cast (conservative slabs).
        check_factor: the dense check's factor on angles and heights (0 = no check).
        engine: ray engine, see :func:`ray_engine`.
        pre_assign: bucket triangles by slab (see :func:`cast_walls`; default: only without
            Embree).
        progress: optional :class:`analyses.progress.Progress`-like object with ``say``.

    Returns:
        :class:`systems.fpsm.model.Fpsm` with settings and per-slice diagnostics.
    """
    from implantplan.systems.fpsm.model import Fpsm
    from implantplan.systems.fpsm.oral_mesh import close_open_cuts as _close

    t_start = time.perf_counter()
    say = progress.say if progress is not None else (lambda message: None)
    M = _check_int("slices", slices, 2)
    N = _check_int("control_points", control_points, 3)
    Z = _check_int("samples", samples, N)
    per_gap = _check_int("slab_levels_per_gap", slab_levels_per_gap, 1)
    check_factor = _check_int("check_factor", check_factor, 0)
    if method not in METHODS:
        raise InputError("method", f"expected one of {METHODS}, got {method!r}")
    margin = float(margin)
    if not np.isfinite(margin) or margin < 0:
        raise InputError("margin", f"expected a finite margin >= 0 m, got {margin}")
    if cap_radius is not None:
        cap_radius = float(cap_radius)
        if not np.isfinite(cap_radius) or cap_radius <= margin:
            raise InputError(
                "cap_radius", f"expected a finite radius > margin (m), got {cap_radius}"
            )
    X_WC = validate.pose(X_WC, "X_WC")
    if len(mesh.faces) == 0:
        raise InputError("mesh", "the mesh is empty (no triangles)")

    closed_info = None
    if close_open_cuts:
        mesh, closed_info = _close(mesh)
        say(f"closed {closed_info['loops']} open boundary loop(s)")

    found_range = None
    if z_range is None:
        z_in, z_out = axis_extent(mesh, X_WC, engine)
        found_range = (z_in, z_out)
        h = (z_out - z_in) / M
        z_lo, z_hi = z_in + h / 2, z_out - h / 2
    else:
        z_lo, z_hi = (float(v) for v in z_range)
        if not (np.isfinite(z_lo) and np.isfinite(z_hi)) or z_hi <= z_lo:
            raise InputError("z_range", f"expected z_min < z_max (m), got {z_lo}, {z_hi}")
    slice_z = np.linspace(z_lo, z_hi, M)
    angles = np.arange(Z) * (TWO_PI / Z)

    # Wall distances, conservative over the slabs
    say(f"casting {((M - 1) * per_gap + 1) * Z} rays ({M} slices x {Z} angles x slabs)")
    levels, R_levels, cast_info = cast_walls(
        mesh, X_WC, slice_z, angles, per_gap=per_gap, engine=engine, pre_assign=pre_assign
    )
    no_hit = ~np.isfinite(R_levels)
    if no_hit.any():
        if cap_radius is None:
            slice_of_level = np.rint((levels - z_lo) / ((z_hi - z_lo) / (M - 1))).astype(int)
            bad = sorted(set(slice_of_level[no_hit.any(axis=1)].tolist()))
            per = "; ".join(
                f"slice {j}: {_ranges_deg(no_hit[slice_of_level == j].any(axis=0), angles)} deg"
                for j in bad[:6]
            )
            more = f" (and {len(bad) - 6} more slices)" if len(bad) > 6 else ""
            raise InputError(
                "mesh",
                f"{int(no_hit.sum())} rays from the Center axis meet no wall (the mesh is open "
                f"there): {per}{more}. Pass --cap-radius-mm to cap those rays or "
                "--close-open-cuts to close the mesh's open boundary loops",
            )
        R_levels = np.where(no_hit, cap_radius, R_levels)
    # slice j: nearest wall over [z_j-1, z_j+1]
    own = np.arange(M) * per_gap
    R_fit = np.empty((M, Z))
    for j in range(M):
        lo = max(own[j] - per_gap, 0)
        hi = min(own[j] + per_gap, levels.size - 1)
        R_fit[j] = R_levels[lo : hi + 1].min(axis=0)
    R_own = R_levels[own]
    wall = R_fit - margin
    if np.any(wall <= 0):
        bad = np.nonzero((wall <= 0).any(axis=1))[0].tolist()
        raise InputError(
            "center_origin",
            f"the Center Z axis is within the margin of a wall (or outside the cavity) near "
            f"slices {bad}: move the axis or shrink the z range",
        )
    t_cast = time.perf_counter() - t_start

    # Solve
    B = basis_matrix(angles, N)
    slice_seconds = np.zeros(M)
    t0 = time.perf_counter()
    if method == "exact":
        say(f"exact: {M} slices, LP + linearized-area LPs")
        scale = 1e3  # solve in mm for the LP tolerances

        def one(j):
            ts = time.perf_counter()
            r, info = fit_slice_exact(B, wall[j] * scale)
            return r / scale, info, time.perf_counter() - ts

        # one slice at a time: two HiGHS solves in two threads of one process can abort it
        # (HiGHS's scheduler is shared by its instances; a fatal abort was seen in the test
        # run of 2026-12-07), and threads saved about 0.1 s of a 0.8 s fit
        results = [one(j) for j in range(M)]
        rho = np.stack([r for r, _, _ in results])
        slice_seconds[:] = [s for _, _, s in results]
        solver_info = {"lp_rounds": [i["lp_rounds"] for _, i, _ in results]}
    else:
        say(f"paper: {M} slices, Eq. 7-9 gradient descent (lambda 30000, alpha 0.1 mm)")
        rho_mm, solver_info = fit_slices_paper(B, wall * 1e3)
        rho = rho_mm / 1e3
        slice_seconds[:] = (time.perf_counter() - t0) / M  # lock-step: the time is shared
    t_solve = time.perf_counter() - t0
    floor = 1e-6 * float(R_fit.max())
    rho = np.maximum(rho, floor)  # Fpsm needs positive control radii

    # Diagnostics
    curve = rho @ B.T  # (M, Z)
    diagnostics = {
        "method": method,
        "coverage": (area(rho) / _polygon_area(R_own)).tolist(),
        "coverage_of_allowed": (area(rho) / _polygon_area(wall)).tolist(),
        "penetrating_samples": np.count_nonzero(curve > R_fit + 1e-12, axis=1).tolist(),
        "max_penetration_samples_m": np.maximum((curve - R_fit).max(axis=1), 0.0).tolist(),
        "rays_without_wall": int(no_hit.sum()),
        "rays_cast": int(R_levels.size),
        "slice_seconds": slice_seconds.tolist(),
        "seconds": {"cast": t_cast, "solve": t_solve},
        "axis_extent_m": list(found_range) if found_range is not None else None,
        "closed_open_cuts": closed_info,
        "pre_assigned": cast_info["pre_assigned"],
        "triangles_per_slab": cast_info["triangles_per_slab"],
        **{f"solver_{k}": v for k, v in solver_info.items()},
    }
    if check_factor > 0:
        say(f"dense check: {check_factor}x angles and heights")
        diagnostics.update(
            dense_check(
                mesh,
                X_WC,
                slice_z,
                rho,
                Z * check_factor,
                per_gap * check_factor,
                cap_radius=cap_radius,
                engine=engine,
                pre_assign=pre_assign,
            )
        )
    diagnostics["seconds"]["total"] = time.perf_counter() - t_start
    settings = {
        "method": method,
        "slices": M,
        "control_points": N,
        "samples": Z,
        "z_range_m": [z_lo, z_hi],
        "margin_m": margin,
        "cap_radius_m": cap_radius,
        "close_open_cuts": bool(close_open_cuts),
        "slab_levels_per_gap": per_gap,
        "check_factor": check_factor,
        "units": "m",
        "mesh": dict(mesh.metadata.get("implantplan", {})).get("source"),
        **({"paper": dict(PAPER_SETTINGS)} if method == "paper" else {}),
    }
    return Fpsm(slice_z=slice_z, rho=rho, X_WC=X_WC, settings=settings, diagnostics=diagnostics)


def dense_check(
    mesh, X_WC, slice_z, rho, samples, per_gap, *, cap_radius=None, engine="auto", pre_assign=None
) -> dict:
    """Penetration of the FPSM (radius linear in z, Eq. 11) into the walls on a dense grid.

    Returns per-slice penetration rates over the heights nearest each slice, the overall rate,
    the largest depth (m) and the number of dense rays that met no wall (capped rays count as a
    wall at ``cap_radius``; uncapped ones as no wall).
    """
    t0 = time.perf_counter()
    angles = np.arange(samples) * (TWO_PI / samples)
    levels, R, _ = cast_walls(
        mesh, X_WC, slice_z, angles, per_gap=per_gap, engine=engine, pre_assign=pre_assign
    )
    no_hit = ~np.isfinite(R)
    if cap_radius is not None:
        R = np.where(no_hit, cap_radius, R)
    z = np.asarray(slice_z)
    j = np.clip(np.searchsorted(z, levels, side="right") - 1, 0, z.size - 2)
    w = (levels - z[j]) / (z[j + 1] - z[j])
    on_slices = rho @ basis_matrix(angles, rho.shape[1]).T  # (M, samples)
    lo, hi = on_slices[j], on_slices[j + 1]
    curve = lo + w[:, None] * (hi - lo)  # Eq. 11
    depth = curve - R
    pen = depth > 1e-12
    nearest = np.argmin(np.abs(levels[:, None] - z[None, :]), axis=1)
    rate = np.array(
        [pen[nearest == k].mean() if np.any(nearest == k) else 0.0 for k in range(z.size)]
    )
    finite_depth = np.where(np.isfinite(depth), depth, -np.inf)
    return {
        "dense_penetration_rate": rate.tolist(),
        "dense_penetration_rate_total": float(pen.mean()),
        "dense_max_depth_m": float(max(finite_depth.max(), 0.0)),
        "dense_rays": int(R.size),
        "dense_rays_without_wall": int(no_hit.sum()),
        "dense_seconds": time.perf_counter() - t0,
    }
