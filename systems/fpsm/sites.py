"""Implant sites against the scan: on the tissue surface, axis into the free space.

DESIGN.md section 3: the Hole frame's origin is the site on the jaw surface (within a tolerance,
default 1 mm, of the scan) and its z axis points from the bone into the cavity. A site typed in
the wrong unit, copied from another patient or with its axis reversed would otherwise plan "safely"
in open air: nothing downstream (FPSM, placement) knows where the tissue is.

Two tests per site, vectorized over the sites:

- **on the surface**: the distance from the site to the scan's triangles (trimesh's exact
  closest-point query) is at most ``tolerance``;
- **axis into the cavity**: the point ``step`` along +axis (``step = tolerance + 1 mm`` by
  default, so a site up to ``tolerance`` inside the tissue still steps out of it) lies in the
  cavity, i.e. inside the closed scan surface (the scan is the surface of the oral cavity's air
  space, seen from the inside; open cuts are closed as the FPSM fit closes them).

When a test fails, :func:`site_problems` also says which unit slip would explain the value
(a position in m typed into an ``_mm`` field, or mm read as m: the site scaled by 1000 or
1/1000 about the Center origin lands on the tissue) and whether the reversed axis would pass.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from implantplan.systems.fpsm.oral_mesh import close_open_cuts
from implantplan.systems.frames import apply

DEFAULT_TOLERANCE = 1e-3  # m, DESIGN.md section 3
STEP_BEYOND_TOLERANCE = 1e-3  # m past the tolerance along the axis for the "into air" test


@dataclass(frozen=True)
class SiteCheck:
    """Per site (arrays of shape (n,)): distance to the scan (m), and whether the point ``step``
    along +axis / -axis lies in the cavity."""

    distance: np.ndarray
    axis_into_cavity: np.ndarray
    reversed_into_cavity: np.ndarray
    tolerance: float
    step: float

    @property
    def on_surface(self) -> np.ndarray:
        return self.distance <= self.tolerance

    @property
    def ok(self) -> np.ndarray:
        return self.on_surface & self.axis_into_cavity


def _closed(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    return mesh if mesh.is_watertight else close_open_cuts(mesh)[0]


def distance_to_surface(mesh: trimesh.Trimesh, points_W: np.ndarray) -> np.ndarray:
    """(n, 3) points in the mesh frame -> (n,) exact distance to the nearest triangle (m)."""
    _, dist, _ = trimesh.proximity.closest_point(mesh, np.asarray(points_W, dtype=float))
    return np.asarray(dist, dtype=float)


def check_sites(
    mesh: trimesh.Trimesh,
    X_WC: np.ndarray,
    positions_C: np.ndarray,
    axes_C: np.ndarray,
    *,
    tolerance: float = DEFAULT_TOLERANCE,
) -> SiteCheck:
    """Check sites given in the Center frame against the scan (in its own frame W).

    Args:
        mesh: the scan as planned (opened, not necessarily closed), metres.
        X_WC: (4, 4) pose of Center in the mesh frame.
        positions_C: (n, 3) site positions in Center (m).
        axes_C: (n, 3) unit implant axes in Center (from the bone into the cavity).
        tolerance: largest distance from the site to the scan (m).
    """
    p_C = np.atleast_2d(np.asarray(positions_C, dtype=float))
    u_C = np.atleast_2d(np.asarray(axes_C, dtype=float))
    u_C = u_C / np.linalg.norm(u_C, axis=1, keepdims=True)
    step = tolerance + STEP_BEYOND_TOLERANCE
    p_W = apply(X_WC, p_C)
    u_W = u_C @ np.asarray(X_WC)[:3, :3].T
    closed = _closed(mesh)
    inside = closed.contains(np.vstack([p_W + step * u_W, p_W - step * u_W]))
    n = len(p_C)
    return SiteCheck(
        distance=distance_to_surface(mesh, p_W),
        axis_into_cavity=inside[:n],
        reversed_into_cavity=inside[n:],
        tolerance=float(tolerance),
        step=float(step),
    )


def site_problems(
    check: SiteCheck,
    mesh: trimesh.Trimesh,
    X_WC: np.ndarray,
    positions_C: np.ndarray,
) -> list[str | None]:
    """One message per site (None when it passes): what was found, what was expected, and the
    unit slip or reversed axis that would explain it when one does."""
    p_C = np.atleast_2d(np.asarray(positions_C, dtype=float))
    scaled = {
        "the position looks like metres typed into an _mm field (x1000 lands on the tissue)":
            p_C * 1000.0,
        "the position looks like mm read as metres (/1000 lands on the tissue)": p_C / 1000.0,
    }
    slip_dist = {k: distance_to_surface(mesh, apply(X_WC, v)) for k, v in scaled.items()}
    out: list[str | None] = []
    for i in range(len(p_C)):
        if check.ok[i]:
            out.append(None)
            continue
        parts = []
        if not check.on_surface[i]:
            parts.append(
                f"lies {check.distance[i] * 1e3:.2f} mm from the scanned tissue, expected at most "
                f"{check.tolerance * 1e3:g} mm (the site must be on the jaw surface)"
            )
            hints = [k for k, d in slip_dist.items() if d[i] <= check.tolerance]
            parts.extend(hints)
        if not check.axis_into_cavity[i]:
            msg = (
                f"its axis does not point into the mouth: {check.step * 1e3:g} mm along +axis is "
                "inside the tissue or outside the scan, expected the cavity's free space (the "
                "axis runs from the bone into the cavity)"
            )
            if check.reversed_into_cavity[i]:
                msg += "; the reversed axis would point into the cavity (sign typed the wrong way?)"
            parts.append(msg)
        out.append("; ".join(parts))
    return out


def project_to_tissue(
    mesh: trimesh.Trimesh, X_WC: np.ndarray, positions_C: np.ndarray, axes_C: np.ndarray
) -> np.ndarray:
    """Move each site along its -axis (into the jaw) to the first scanned tissue it meets.

    Sites proposed on the FPSM's wall lie in the air (the model is conservative: inside the free
    space), up to a few mm from the tissue; this is where the implant axis meets the jaw.

    Returns:
        (n, 3) positions in Center (m); NaN rows where the ray meets no tissue.
    """
    p_C = np.atleast_2d(np.asarray(positions_C, dtype=float))
    u_C = np.atleast_2d(np.asarray(axes_C, dtype=float))
    u_C = u_C / np.linalg.norm(u_C, axis=1, keepdims=True)
    p_W = apply(X_WC, p_C)
    u_W = u_C @ np.asarray(X_WC)[:3, :3].T
    locations, ray_ids, _ = mesh.ray.intersects_location(p_W, -u_W, multiple_hits=True)
    out = np.full_like(p_C, np.nan)
    if len(ray_ids):
        depth = np.einsum("ij,ij->i", locations - p_W[ray_ids], -u_W[ray_ids])
        order = np.lexsort((depth, ray_ids))
        first = order[np.r_[True, ray_ids[order][1:] != ray_ids[order][:-1]]]
        X_CW = np.linalg.inv(np.asarray(X_WC, dtype=float))
        out[ray_ids[first]] = apply(X_CW, locations[first])
    return out
