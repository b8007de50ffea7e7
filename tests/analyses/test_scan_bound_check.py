"""The independent check of the scan bound (analyses.studies.scan_bound_check) against FCL, and
the defect it found: the bound does not return for a capsule or sphere thicker than
res / RELATIVE (2 mm) whose axis passes 2.5-4 mm from the wall (it splits pieces forever)."""

import subprocess
import sys
import textwrap

import pytest

HANG = textwrap.dedent("""
    import numpy as np, trimesh
    from implantplan.systems.instrument import Instrument, Shape
    from implantplan.systems.placement.distance_grid import build_grid
    from implantplan.systems.placement.scan_clearance import ScanClearance
    m = trimesh.creation.cylinder(radius=0.03, height=0.08, sections=96)
    m.apply_translation([0, 0, 0.04])
    keep = ~np.all(np.isclose(m.vertices[m.faces][..., 2], 0.08), axis=1)
    m = trimesh.Trimesh(m.vertices, m.faces[keep], process=False)
    ball = Instrument("ball", (Shape("head", "sphere", [0, 0, 0], [0, 0, 0], {r}),),
                      rod_radius={r}, implant_length=0.01)
    scan = ScanClearance(m, ball, grid=build_grid(m, spacing=1e-3))
    X = np.eye(4)
    X[:3, 3] = [0.03 * np.cos(np.pi / 96) - {d}, 0.0, 0.04]  # the centre {d} m from the wall
    print(int(scan.fast_verdict(X, 1e-3)[0]))
""")


def _verdict_in(seconds: float, *, d: float, r: float = 0.006):
    """The fast verdict of a sphere of radius r centred d from a cylinder cavity's wall, run in a
    child process; None if it does not return within ``seconds``."""
    try:
        out = subprocess.run([sys.executable, "-c", HANG.format(d=d, r=r)], capture_output=True,
                             text=True, timeout=seconds, check=True)
    except subprocess.TimeoutExpired:
        return None
    return int(out.stdout.split()[-1])


def test_the_bound_returns_near_and_far_from_the_wall():
    # the control of the reproducer below: centre 1.5 mm from the wall (penetrating 4.5 mm, an
    # exact node proves it) and 5 mm (penetrating 1 mm: undecided) return at once
    assert _verdict_in(60, d=0.0015) == -1
    assert _verdict_in(60, d=0.005) == 0


@pytest.mark.xfail(strict=True, reason="scan_clearance._segment_bound splits a piece while "
                   "h > res + RELATIVE * lb, never true once lb < -res / RELATIVE = -2 mm: a "
                   "capsule or sphere of radius > 2 mm whose axis lies 2.5-4 mm from the wall "
                   "(no exact node within the grid's band to prove the touch) never returns")
def test_the_bound_returns_for_a_sphere_penetrating_2_to_4_mm():
    assert _verdict_in(20, d=0.0035) == -1
