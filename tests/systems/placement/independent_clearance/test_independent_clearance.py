"""Independent verification of implantplan.systems.placement.tool_clearance (the "sound" clearance).

Ground truth (groundtruth.py, verifier's own code): the FPSM curve re-implemented from DESIGN.md
Eq. 1-5, the free region F from the tool_clearance docstring, its boundary triangulated densely
(FCL BVH) with an explicit discretization bound eps, and *rigorous* collision certificates: an
exact axis point outside F, or an exact axis point and an exact boundary point closer than r.

A false-safe = the sound value > 0 while the certificate says the capsule touches/crosses dF.

Run (default size, < 60 s):      pytest tests/systems/placement/independent_clearance
Bigger samples:                  VERIFY12_N=2000 pytest
tests/systems/placement/independent_clearance
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from groundtruth import spline, verdict  # noqa: E402
from harness import MM, MODELS, evaluate, families, ratchet, region  # noqa: E402

from implantplan.systems.errors import InputError  # noqa: E402
from implantplan.systems.instrument import Instrument  # noqa: E402
from implantplan.systems.placement.tool_clearance import (  # noqa: E402
    ToolClearance,
    feed_clearance,
    rod_clearance,
    tool_clearance,
)

PY = sys.executable


@pytest.fixture(scope="session")
def n_rods(request):
    return int(os.environ.get("VERIFY12_N", 40))


@pytest.fixture(scope="session")
def models():
    out = {}
    for name, make in MODELS.items():
        f = make()
        out[name] = (f, region(f, 1024, 4))
    return out


# -- the ground truth itself ---------------------------------------------------------------------


def test_spline_from_definition_matches_radius_at(models):
    rng = np.random.default_rng(0)
    for f, G in models.values():
        th = rng.uniform(-10, 10, 5000)
        z = rng.uniform(*f.z_range, 5000)
        assert np.allclose(G.radius(th, z), f.radius_at(th, z), atol=1e-12, rtol=0)
        # knots reproduce the control radii (Eq. 1)
        k = np.arange(f.control_points)
        knots = 2 * np.pi * k / f.control_points
        for j in range(f.slices):
            assert np.allclose(spline(f.rho[j:j + 1], knots)[0], f.rho[j], atol=1e-15)


def test_ground_truth_cylinder_hand_values(models):
    f, G = models["cylinder"]
    R = 0.05
    for r in (0.0001, 0.006, 0.008):
        q = G.query(np.array([0, 0, 0.05]), np.array([0, 0, 1.0]))
        assert verdict(q, r, G.eps)[0] == "free"
        assert abs(q["upper"] - R) < 1e-9 and abs(q["d_fcl"] - R) <= G.eps
    q = G.query(np.array([0.041, 0, 0.05]), np.array([0.041, 0, 1.0]))
    assert abs(q["upper"] - 0.009) < 1e-6  # wall 50 - 41 mm
    q = G.query(np.array([0.0, 0, 0.05]), np.array([0.06, 0, 0.05]))
    assert q["axis_out"]  # leaves through the side
    q = G.query(np.array([0.0, 0, 0.01]), np.array([0.0, 0, -0.01]))
    assert q["axis_out"]  # leaves through the throat


def test_free_region_definition_consistent_with_d_safe(models):
    """tool_clearance's F (docstring) and Fpsm.d_safe (> 0 inside) agree point by point,
    including the edge cases z = z_0, z = z_top, the axis, above and below the range."""
    rng = np.random.default_rng(1)
    for f, G in models.values():
        z0, zt = f.z_range
        n = 20000
        th = rng.uniform(0, 2 * np.pi, n)
        z = np.concatenate([rng.uniform(z0 - 0.01, zt + 0.01, n - 400), np.full(100, z0),
                            np.full(100, zt), np.full(100, np.nextafter(zt, np.inf)),
                            np.full(100, np.nextafter(z0, -np.inf))])
        rr = G.radius(th, np.clip(z, z0, zt)) * rng.uniform(0, 1.3, n)
        rr[:50] = 0.0  # on the axis
        P = np.column_stack([rr * np.cos(th), rr * np.sin(th), z])
        mine = G.signed_radial(P) > 0
        theirs = f.d_safe(P) > 0
        assert np.array_equal(mine, theirs), np.flatnonzero(mine != theirs)[:10]


# -- rods against the exact FPSM -----------------------------------------------------------------


@pytest.mark.parametrize("name", list(MODELS))
def test_no_false_safe_rod_families(models, n_rods, name):
    f, G = models[name]
    bad = []
    for fam, (p0, p1, r) in families(f, G, n_rods, seed=101).items():
        res = evaluate(f, G, p0, p1, r, truth_all=False)
        fs = (res["sound"] > 0) & (res["kind"] == "collide")
        # the quantitative promise: the sound value never exceeds the true clearance
        over = (res["sound"] > 0) & (res["sound"] > res["upper"] + G.eps + 1e-9)
        for k in np.flatnonzero(fs | over):
            bad.append((fam, p0[k].tolist(), p1[k].tolist(), float(r[k]),
                        float(res["sound"][k]), float(res["upper"][k])))
    assert not bad, f"{len(bad)} false-safe / over-estimates on {name}, e.g. {bad[:3]}"


@pytest.mark.parametrize("name", list(MODELS))
def test_radius_ratchet(models, n_rods, name):
    """For each axis the largest radius still called safe never exceeds the axis's true
    distance to the boundary (an exact upper bound of it)."""
    f, G = models[name]
    fams = families(f, G, max(n_rods // 2, 10), seed=202)
    p0 = np.concatenate([v[0] for v in fams.values()])
    p1 = np.concatenate([v[1] for v in fams.values()])
    r_star, up, out, _ = ratchet(f, G, p0, p1, iters=18)
    ok = r_star >= 0
    assert not np.any(ok & out), "axis leaving F called safe at r = 0"
    gap = up[ok] - r_star[ok]
    assert np.all(gap >= -G.eps), (gap.min(), p0[ok][np.argmin(gap)], p1[ok][np.argmin(gap)])


def test_tool_and_feed_no_false_safe(models, n_rods):
    import toolcheck

    rng = np.random.default_rng(303)
    for name in ("default", "cylinder", "nonconvex"):
        f, G = models[name]
        X = toolcheck.random_poses(G, rng, max(n_rods, 20))
        for k in range(len(X)):
            tool = Instrument.paper(rod_radius=rng.uniform(0.5, 6) * MM,
                                implant_length=rng.uniform(5, 31) * MM,
                                rod_length=rng.uniform(20, 200) * MM,
                                implant_radius=rng.uniform(0, 2) * MM,
                                head_radius=rng.uniform(0.5, 7) * MM)
            v = tool_clearance(f, X[k], tool)[0]
            assert ToolClearance(f, tool).one(X[k]) == v
            if v > 0:
                assert toolcheck.truth_tool(G, X[k], tool) >= v - G.eps, (name, X[k], tool, v)
        Xf = toolcheck.random_poses_feed(G, rng, 3)
        tool = Instrument.paper(rod_radius=0.002, implant_length=0.008, rod_length=0.1)
        for k in range(len(Xf)):
            v = feed_clearance(f, Xf[k], tool)[0]
            if v <= 0:
                continue
            x = Xf[k][:3, 0]
            for s in np.arange(0, 0.08, 0.001):
                Y = Xf[k].copy()
                Y[:3, 3] += s * x
                if Y[2, 3] > G.ztop + 0.02:
                    break
                assert toolcheck.truth_tool(G, Y, tool) >= v - 0.001 / 2 - G.eps


# -- degenerate inputs ---------------------------------------------------------------------------


def test_degenerate_values(models):
    f, G = models["cylinder"]
    # p0 == p1 is a sphere: 50 - 41 - 6 = 3 mm at most
    c = rod_clearance(f, [0.041, 0, 0.05], [0.041, 0, 0.05], 0.006)[0]
    assert 0 < c <= 0.003
    # radius 0: the axis itself
    c = rod_clearance(f, [0.0, 0, 0.05], [0.0, 0, 0.06], 0.0)[0]
    assert 0 < c <= 0.05
    # leaving through the side / throat with radius 0 is a collision
    assert rod_clearance(f, [0, 0, 0.05], [0.06, 0, 0.05], 0.0)[0] <= 0
    assert rod_clearance(f, [0, 0, 0.01], [0, 0, -0.01], 0.0)[0] <= 0
    for bad in ([np.nan, 0, 0.05], [np.inf, 0, 0.05]):
        with pytest.raises(InputError):
            rod_clearance(f, bad, [0, 0, 0.06], 0.001)
    for r in (np.nan, -1e-3, np.inf):
        with pytest.raises(InputError):
            rod_clearance(f, [0, 0, 0.05], [0, 0, 0.06], r)


@pytest.mark.parametrize(
    "call",
    [
        "rod_clearance(f, [[0,0,0.05]]*3, [0,0,0.06], [1e-3, 2e-3])",  # radii count
        "rod_clearance(f, [[0,0,0.05]]*3, [[0,0,0.06]]*2, 1e-3)",  # p0/p1 count
        "rod_clearance(f, np.zeros((2,2,3)), np.zeros((2,2,3)), 1e-3)",  # 3-D batch
        "rod_clearance(f, [0,0,0.05], [0,0,0.06], 'x')",  # radius not a number
    ],
)
def test_bad_shapes_give_input_error(models, call):
    """DESIGN.md section 3: bad input -> a clear InputError naming the field."""
    f, _ = models["cylinder"]
    with pytest.raises(InputError):
        eval(call, {"rod_clearance": rod_clearance, "np": np, "f": f})


@pytest.mark.parametrize("x", [1e16, 1e20])
def test_huge_finite_coordinates_do_not_crash_or_pass(x):
    """Finite but huge coordinates must be rejected or called unsafe -- not crash the process
    (the grid index overflows int64 and is read out of bounds)."""
    code = (
        "from implantplan.systems.fpsm.model import Fpsm\n"
        "from implantplan.systems.placement.tool_clearance import rod_clearance\n"
        "from implantplan.systems.errors import InputError\n"
        "f = Fpsm.cylinder(0.05, 0.0, 0.1, 11)\n"
        "try:\n"
        f"    v = rod_clearance(f, [{x!r}, 0, 0.101], [{x!r}, 0, 0.101], 0.005)[0]\n"
        "    print('VALUE', v)\n"
        "except InputError:\n"
        "    print('INPUTERROR')\n"
    )
    p = subprocess.run([PY, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, f"process died with return code {p.returncode} (segfault = -11)"
    out = p.stdout.strip().split()
    assert out[0] == "INPUTERROR" or float(out[1]) <= 0


def test_non_rigid_pose_is_rejected_not_shrunk(models):
    """A pose whose rotation part is not a rotation shrinks the tool in the kernel: a colliding
    tool position must not come out as safe."""
    f, _ = models["cylinder"]
    tool = Instrument.paper(rod_radius=0.003, implant_length=0.031)
    X = np.eye(4)
    X[:3, :3] = np.column_stack([[0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    X[:3, 3] = [0.025, 0, 0.05]  # implant tip at x = 56 mm, the wall at 50 mm
    assert tool_clearance(f, X, tool)[0] <= 0
    Y = X.copy()
    Y[:3, :3] *= 0.5
    try:
        v = tool_clearance(f, Y, tool)[0]
    except InputError:
        return
    assert v <= 0, f"non-rigid pose accepted and called safe by {v * 1e3:.2f} mm"
