"""The memory a plan will need, estimated before any work, against a budget (DESIGN.md section 3,
"Bounded work").

Every count of a case has an upper bound checked when the case is read (analyses.case,
systems.safety, docs/formats.md "Bounds"); within the bounds a combination can still need more
memory than the machine has (the dense FPSM check of 200 slices x 2,000 samples alone holds ~25
million rays). :func:`estimate` adds up, per stage, the largest arrays the stage allocates, with
per-element sizes measured on this code (peak RSS of ``plan --no-figures`` on the small test case:
459 MB; with ``fpsm`` 60 slices x 1,000 samples x 30 control points: 924 MB, of which the estimate
below gives 536 MB to the fit, measured 465 MB), rounded up:

- the process with Drake, numba and the libraries loaded: 500 MB;
- the scan: 2 KB per triangle (the scanned, opened and closed copies, the FCL tree, the ray
  scene), the triangles bounded from the file's size (at least 16 bytes per triangle in any
  format: binary STL has 50, binary PLY about 19); a CBCT: 40 bytes per voxel (2 bytes each in
  the files, or the voxels its headers give where more: a compressed file) and 6 x
  voxels^(2/3) triangles;
- the FPSM fit: 128 bytes per ray of the dense check ((8 slices x 8 samples) per slice and sample)
  and 256 per ray of the conservative cast ((slices - 1) x 3 + 1 heights x samples);
- the registration Monte Carlo: 512 bytes per sample and feed pose (51 poses: a feed of at most
  200 mm every 4 mm);
- the robot search: 4 KB per individual, site and IK branch (8) in a generation of
  2 x population;
- the capability check: 64 bytes per direction, voxel (27 around a target), site and branch;
- the feeding simulations: 20 MB per run and site (the logged trajectories).

:func:`check` refuses a plan whose estimate exceeds the budget (default: half the machine's
memory; ``--memory-budget-mb`` or ``$IMPLANTPLAN_MEMORY_BUDGET_MB``) with exit 2 and the estimate
per stage.
"""

from __future__ import annotations

import os
from pathlib import Path

from implantplan.systems.anatomy.cbct import is_volume_path, scan_files, volume_voxels
from implantplan.systems.errors import InputError

MB = 1e6
BASE = 500 * MB
PER_FACE = 2048
BYTES_PER_FACE_MIN = 16
BYTES_PER_VOXEL = 2  # a CT slice's 16-bit pixels (uncompressed DICOM; a .nii.gz underestimates)
PER_VOXEL = 40  # HU volume, masks, labels, marching cubes' field, for the air and bone surfaces
FACES_PER_VOXEL_AREA = 6  # the air surface: 430,881 triangles of 23.2 M voxels (0.4 mm phantom)
PER_DENSE_RAY, PER_CAST_RAY, CHECK_FACTOR, SLAB_LEVELS = 128, 256, 8, 3
PER_REGISTRATION_POSE, FEED_POSES = 512, 51
PER_INDIVIDUAL_BRANCH, BRANCHES = 4096, 8
PER_CAPABILITY_ENTRY, NEIGHBOURHOOD = 64, 27
PER_RUN = 20 * MB
ENV = "IMPLANTPLAN_MEMORY_BUDGET_MB"


def machine_memory() -> float:
    """The machine's physical memory (bytes)."""
    return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def default_budget() -> float:
    """``$IMPLANTPLAN_MEMORY_BUDGET_MB`` (MB) if set, else half the machine's memory (bytes)."""
    text = os.environ.get(ENV)
    if text:
        try:
            value = float(text)
        except ValueError:
            value = float("nan")
        if not value > 0 or value == float("inf"):
            raise InputError(ENV, f"expected a positive number of MB, got {text!r}")
        return value * MB
    return machine_memory() / 2


def estimate(case, *, runs: int | None = None) -> dict[str, float]:
    """Bytes per stage for planning ``case`` (an analyses.case.Case) with ``runs`` feeds per
    site (None: the case's ``simulation.runs``); the module docstring gives each term."""
    n_sites = len(case.sites)
    fp = case.fpsm
    cbct = 0.0
    if is_volume_path(case.mesh.path):  # a CBCT: voxels from its headers, or the files' size
        voxels = max(volume_voxels(case.mesh.path) or 0,
                     sum(p.stat().st_size for p in scan_files(case.mesh.path)) / BYTES_PER_VOXEL)
        cbct = PER_VOXEL * voxels
        faces = FACES_PER_VOXEL_AREA * voxels ** (2 / 3)
    else:
        try:
            size = Path(case.mesh.path).stat().st_size
        except OSError:
            size = 0
        faces = size / BYTES_PER_FACE_MIN
    dense = (fp.slices * CHECK_FACTOR) * (fp.samples * CHECK_FACTOR)
    cast = ((fp.slices - 1) * SLAB_LEVELS + 1) * fp.samples
    runs = case.simulation.runs if runs is None else runs
    return {
        "process": BASE,
        "scan": PER_FACE * faces + cbct,
        "fpsm": PER_DENSE_RAY * dense + PER_CAST_RAY * cast,
        "registration": PER_REGISTRATION_POSE * FEED_POSES * case.safety.registration_samples,
        "robot": PER_INDIVIDUAL_BRANCH * 2 * case.robot.pop * n_sites * BRANCHES,
        "capability": PER_CAPABILITY_ENTRY * case.capability.directions * NEIGHBOURHOOD
                      * n_sites * BRANCHES,
        "simulation": PER_RUN * runs * n_sites,
    }


def check(case, *, runs: int | None = None, budget: float | None = None) -> float:
    """The total estimate (bytes); over ``budget`` (bytes; None: :func:`default_budget`) an
    InputError naming the largest stage's settings and the estimate per stage."""
    budget = default_budget() if budget is None else float(budget)
    parts = estimate(case, runs=runs)
    total = sum(parts.values())
    if total > budget:
        worst = max(parts, key=parts.get)
        field = {"scan": "mesh.path", "fpsm": "fpsm.slices/samples",
                 "registration": "safety.registration_samples", "robot": "robot.pop",
                 "capability": "capability.directions", "simulation": "simulation.runs",
                 "process": "memory"}[worst]
        shown = ", ".join(f"{k} {v / MB:,.0f}" for k, v in parts.items() if v >= MB)
        raise InputError(field, f"the plan would need about {total / MB:,.0f} MB ({shown} MB), "
                         f"over the memory budget of {budget / MB:,.0f} MB (--memory-budget-mb "
                         f"or ${ENV}; default half the machine's memory)")
    return total
