"""RASSCMAP: arc radius, surface points, Algorithms 1-2, YAML inputs, cost, search, store."""

from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from implantplan.systems.capability import maps as cm
from implantplan.systems.capability import rasscmap as rm
from implantplan.systems.capability import rasscmap_inputs as rin
from implantplan.systems.capability import setup_search as ss
from implantplan.systems.capability import store as ms
from implantplan.systems.errors import InputError, PlanningFailure
from implantplan.systems.frames import rot_x, transform

CASES = str(Path(__file__).resolve().parents[3] / "models" / "capmap_cases")


@pytest.fixture(scope="module")
def cmap():
    return cm.build(cm.make_params(0.10, 40), workers=1)


def test_arc_radius_half_circle_by_hand():
    # a half circle of radius 0.2: a = pi * 0.2, c = 0.4, theta = pi
    r, theta = rm.arc_radius(np.pi * 0.2, 0.4)
    assert r == pytest.approx(0.2, abs=1e-12)
    assert theta == pytest.approx(np.pi, abs=1e-12)


def test_arc_radius_quarter_circle_by_hand():
    # theta = pi/2, r = 1: a = pi/2, c = 2 sin(pi/4) = sqrt(2)
    r, theta = rm.arc_radius(np.pi / 2, np.sqrt(2.0))
    assert r == pytest.approx(1.0, abs=1e-12)
    assert theta == pytest.approx(np.pi / 2, abs=1e-12)


@given(st.floats(0.05, 1.0), st.floats(0.05, 6.2))
@settings(max_examples=80, deadline=None)
def test_arc_radius_round_trip(r, theta):
    a, c = r * theta, 2 * r * np.sin(theta / 2)
    r2, t2 = rm.arc_radius(a, c)
    assert r2 == pytest.approx(r, rel=1e-7)
    assert t2 == pytest.approx(theta, rel=1e-7)


def test_arc_radius_rejects_chord_longer_than_arc():
    with pytest.raises(InputError, match="chord"):
        rm.arc_radius(0.3, 0.4)


def test_surface_points_lie_on_the_layers():
    a, c, length, v = np.pi * 0.2, 0.4, 0.3, 0.05
    p = rm.surface_points(a, c, length, d_r=np.radians(10), d_t=0.1, voxel=v, depth=0.1)
    # half circle: centre on the chord (y0 = 0); 19 rotations x 4 z steps x 3 layers
    assert len(p) == 19 * 4 * 3
    radii = np.hypot(p[:, 0], p[:, 1])
    np.testing.assert_allclose(np.unique(radii.round(9)), [0.2, 0.25, 0.3])
    assert p[:, 1].min() == pytest.approx(0.0, abs=1e-12)  # chord ends at y = 0
    np.testing.assert_allclose(np.unique(p[:, 2]), [0.0, 0.1, 0.2, 0.3], atol=1e-12)


def test_algorithm2_geometry_law_of_sines(cmap):
    """Joint J lies on the shaft line through the trocar, |J - tip| = l_i, bend = delta."""
    X_WA = transform(rot_x(np.pi), [0.6, 0.0, 0.4])
    tip = np.array([0.65, 0.03, 0.22])
    p_A = X_WA[:3, 3]
    D = np.linalg.norm(tip - p_A)
    u = (tip - p_A) / D
    l_i, delta = 0.03, np.radians(60)
    phi = np.arcsin(l_i * np.sin(delta) / D)
    w = np.cross(u, [0, 0, 1.0])
    w /= np.linalg.norm(w)
    z_s = np.cos(phi) * u - np.sin(phi) * w
    z_i = np.cos(delta - phi) * u + np.sin(delta - phi) * w
    AJ = D * np.sin(delta - phi) / np.sin(delta)
    J = p_A + AJ * z_s
    assert np.linalg.norm(tip - J) == pytest.approx(l_i, abs=1e-12)
    np.testing.assert_allclose((tip - J) / l_i, z_i, atol=1e-12)
    assert np.degrees(np.arccos(z_s @ z_i)) == pytest.approx(60.0, abs=1e-9)


def _algorithm2_reference(cmap, X_WB, X_WA, centres, trocar, ins, d_rot):
    """Slow numpy Algorithm 2: the same geometry written with arcsin / explicit angles."""
    out = np.zeros((len(centres), cmap.params.directions), bool)
    delta, psi = rm.bend_samples(d_rot, ins.joint_limit)
    X_BW = np.linalg.inv(X_WB)
    p_A, z_A = X_WA[:3, 3], X_WA[:3, 2]
    for m, c in enumerate(centres):
        D = np.linalg.norm(c - p_A)
        u = (c - p_A) / D
        hint = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = hint - (hint @ u) * u  # the bend-plane azimuth psi is measured from this e1
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(u, e1)
        for d, ps in zip(delta, psi, strict=True):
            if D <= ins.instrument_length or ins.instrument_length * np.sin(d) / D > 1:
                continue
            phi = np.arcsin(ins.instrument_length * np.sin(d) / D)
            AJ = D * np.sin(d - phi) / np.sin(d) if d > 0 else D - ins.instrument_length
            if d > 0 and AJ < trocar.cannula_length:
                continue
            w = np.cos(ps) * e1 + np.sin(ps) * e2
            z_s = np.cos(phi) * u - np.sin(phi) * w
            if z_s @ z_A < -1e-12:
                continue
            p_ee = p_A + (AJ - ins.shaft_length) * z_s
            ok = cmap.query_points(
                (X_BW[:3, :3] @ p_ee + X_BW[:3, 3])[None], (X_BW[:3, :3] @ z_s)[None]
            )
            if ok[0][0]:
                z_i = np.cos(d - phi) * u + np.sin(d - phi) * w
                out[m, cmap.nearest_direction(z_i[None])[0]] = True
    return out


def test_algorithm2_kernel_matches_reference(cmap):
    X_WA = transform(rot_x(np.pi), [0.5, -0.3, 0.5])
    trocar = rm.Trocar(cannula_length=0.03, depth=0.10)
    ins = rm.Instrument(shaft_length=0.3, instrument_length=0.03)
    X_WB = transform(rot_x(0.0), [0.05, 0.02, 0.0])
    rng = np.random.default_rng(5)
    centres = X_WA[:3, 3] + rng.uniform([-0.1, -0.1, -0.13], [0.1, 0.1, -0.04], (12, 3))
    d_rot = np.radians(15)
    fast = rm.add_orientations(cmap, X_WB, X_WA, centres, trocar, ins, d_rot)
    slow = _algorithm2_reference(cmap, X_WB, X_WA, centres, trocar, ins, d_rot)
    assert slow.sum() > 20
    np.testing.assert_array_equal(fast, slow)


def test_constrained_map_hemisphere_and_index(cmap):
    X_WA = transform(rot_x(np.pi), [0.5, -0.3, 0.5])  # z points down into the "patient"
    X_WB = np.eye(4)
    trocar = rm.Trocar(cannula_length=0.04, depth=0.12)
    ins = rm.Instrument(shaft_length=0.3, instrument_length=0.02)
    r = rm.constrained_map(cmap, X_WB, X_WA, trocar, ins, voxel=0.04, d_rot=np.radians(15))
    assert len(r.centres) > 0
    # every voxel is on the patient's side of the trocar plane, within cannula + depth (+ voxel)
    d = r.centres - X_WA[:3, 3]
    assert np.all(d @ X_WA[:3, 2] >= -0.04)
    assert np.all(np.linalg.norm(d, axis=1) <= 0.04 + 0.12 + 0.04 * np.sqrt(3))
    assert np.all((r.index >= 0) & (r.index <= 1))
    assert 0 < r.c_s < 0.6  # instrument directions span at most ~a hemisphere
    # the straight instrument direction from the trocar is reachable at a pivot voxel
    pv = np.flatnonzero(r.index > 0)[0]
    u = (r.centres[pv] - X_WA[:3, 3]) / np.linalg.norm(r.centres[pv] - X_WA[:3, 3])
    reach, idx = r.query(transform(cm.frames_from_z(u), r.centres[pv])[None], cmap.directions)
    assert reach[0] and idx[0] == r.index[pv]
    # a robot placed 5 m away reaches nothing
    far = rm.constrained_map(
        cmap, transform(np.eye(3), [5.0, 0, 0]), X_WA, trocar, ins, voxel=0.04, d_rot=np.radians(15)
    )
    assert far.c_s == 0.0


def test_setup_cost_formula():
    reach = np.array([[True, True], [True, False]])
    c_t = np.array([[0.6, 0.8], [1.0, 1.0]])
    c_s = np.array([0.5, 0.9])
    np.testing.assert_allclose(ss.setup_cost(reach, c_t, c_s), [0.5 * (0.7 + 0.5), 0.0])


def _write(tmp_path, name, data):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data))
    return p


def test_yaml_errors_name_the_field(tmp_path):
    bad = {"patient": {"id": "X", "access": "unconstrained", "pose": {"xyz": [0, 0, 0]},
                       "voxel_size": 0.05, "map_depth": 0.1,
                       "body": {"arc_length": 0.3, "chord": 0.4, "length": 0.2}}}  # fmt: skip
    with pytest.raises(InputError, match="patient.body.chord"):
        rin.load_patient(_write(tmp_path, "p.yaml", bad))
    bad["patient"]["body"]["chord"] = 0.2
    bad["patient"]["voxel_size"] = -1
    with pytest.raises(InputError, match="patient.voxel_size"):
        rin.load_patient(_write(tmp_path, "p.yaml", bad))
    bad["patient"]["voxel_size"] = 0.05
    bad["patient"]["pose"] = {"xyz": [0, 0]}
    with pytest.raises(InputError, match="patient.pose.xyz"):
        rin.load_patient(_write(tmp_path, "p.yaml", bad))
    with pytest.raises(InputError, match="task.poses"):
        rin.load_task(_write(tmp_path, "t.yaml", {"task": {"id": "T", "poses": []}}))
    robot = {"robot": {"name": "aubo_i10", "map": "m.h5",
                       "base_ranges": [{"x": [1.0, 0.0], "y": 0.0}]}}  # fmt: skip
    with pytest.raises(InputError, match=r"robot.base_ranges\[0\].x"):
        rin.load_robot(_write(tmp_path, "r.yaml", robot))
    with pytest.raises(InputError, match="patient.access_points"):
        rin.load_patient(
            _write(
                tmp_path,
                "c.yaml",
                {
                    "patient": {
                        **bad["patient"],
                        "pose": {"xyz": [0, 0, 0]},
                        "access": "constrained",
                    }
                },
            )  # fmt: skip
        )


def test_bundled_cases_parse():
    p = rin.load_patient(f"{CASES}/laparoscopy_patient.yaml")
    assert p.access == "constrained" and len(p.access_points) == 5
    assert len(rin.load_task(f"{CASES}/laparoscopy_task.yaml").poses) == 200
    rail = rin.load_robot(f"{CASES}/laparoscopy_robot_rail.yaml")
    assert len(rin.base_candidates(rail.ranges)[0]) == 25  # 1.2 m rail at 5 cm
    ped = rin.load_robot(f"{CASES}/pedicle_robot.yaml")
    assert len(rin.base_candidates(ped.ranges)[0]) == 800  # as in the paper's use case
    assert rin.load_patient(f"{CASES}/dental_patient.yaml").access == "unconstrained"
    assert len(rin.load_task(f"{CASES}/dental_task.yaml").poses) == 6
    assert len(rin.load_robot(f"{CASES}/dental_robot.yaml").ranges) == 2


def _unconstrained_problem(cmap, tmp_path, base_y):
    pat = _write(tmp_path, "p.yaml", {"patient": {
        "id": "P", "access": "unconstrained",
        "pose": {"xyz": [0.6, -0.1, 0.3], "rpy_deg": [90, 0, 90]},
        "voxel_size": 0.1, "map_depth": 0.1, "rotation_step_deg": 15, "translation_step": 0.1,
        "body": {"arc_length": 0.5, "chord": 0.36, "length": 0.3}}})  # fmt: skip
    task = _write(tmp_path, "t.yaml", {"task": {"id": "T", "poses": [
        {"xyz": [0.7, 0.0, 0.55], "rpy_deg": [180, 0, 0]},
        {"xyz": [0.8, 0.0, 0.55], "rpy_deg": [180, 0, 0]}]}})  # fmt: skip
    robot = _write(tmp_path, "r.yaml", {"robot": {
        "name": "aubo_i10", "map": "unused.h5", "translation_step": 0.1, "rotation_step_deg": 30,
        "base_ranges": [{"x": [-0.3, 0.3], "y": base_y, "z": 0.0, "yaw_deg": [0, 330]},
                        {"x": [3.0, 3.2], "y": 0.0, "z": 0.0, "yaw_deg": 0}]}})  # fmt: skip
    return ss.SetupProblem(cmap, rin.load_patient(pat), rin.load_task(task), rin.load_robot(robot))


def test_exhaustive_and_ga_agree_and_far_bases_score_zero(cmap, tmp_path):
    prob = _unconstrained_problem(cmap, tmp_path, [-0.3, 0.3])
    ex = ss.optimize(prob, method="exhaustive")
    assert prob.n == 7 * 7 * 12 + 3
    # the bases 3 m away (last range) reach nothing: cost 0, the worst
    assert np.all(prob.cost[-3:] == 0.0) and ex.worst_cost == 0.0
    assert ex.cost == pytest.approx(prob.cost.max())
    ga_prob = _unconstrained_problem(cmap, tmp_path, [-0.3, 0.3])
    ga = ss.genetic_search(ga_prob, seed=1, population=30, generations=40)
    assert ga.cost <= ex.cost + 1e-12
    assert ga.cost >= 0.95 * ex.cost  # a small problem: the GA gets (close to) the optimum
    ga2 = ss.genetic_search(_unconstrained_problem(cmap, tmp_path, [-0.3, 0.3]), seed=1,
                            population=30, generations=40)  # fmt: skip
    assert (ga2.best, ga2.cost) == (ga.best, ga.cost)  # same seed, same result


def test_tie_break_takes_the_deepest_of_the_tied_best(cmap, tmp_path):
    prob = _unconstrained_problem(cmap, tmp_path, [-0.3, 0.3])
    res = ss.exhaustive_search(prob)
    ids = np.arange(prob.n)
    top = (prob.cost == prob.cost[res.best]) & (prob.margin == prob.margin[res.best])
    assert prob.cost[res.best] == prob.cost.max()
    assert prob.margin[res.best] == prob.margin[prob.cost == prob.cost.max()].max()
    if top.sum() > 1:
        depth = ss.setup_distance(prob, ids[top], ids[~top]).min(axis=1)
        assert depth[np.flatnonzero(ids[top] == res.best)[0]] == depth.max()
    # distance: a 30 deg yaw step at the same position = YAW_LENGTH * pi / 6
    same_pos = np.flatnonzero(np.all(prob.base_coords[:, :4] == prob.base_coords[0, :4], axis=1))
    d = ss.setup_distance(prob, np.array([0]), same_pos)[0]
    np.testing.assert_allclose(np.sort(d)[:2], [0.0, ss.YAW_LENGTH * np.pi / 6], atol=1e-12)


def test_no_reachable_base_is_a_planning_failure(cmap, tmp_path):
    prob = _unconstrained_problem(cmap, tmp_path, [4.0, 4.2])
    with pytest.raises(PlanningFailure, match="reaches all 2 task poses"):
        ss.optimize(prob)


def test_store_reuses_constrained_maps(cmap, tmp_path):
    pat = rin.load_patient(f"{CASES}/laparoscopy_patient.yaml")
    pat.access_points = pat.access_points[:2]
    pat.voxel, pat.d_rot = 0.05, np.radians(15)
    task = rin.Task("T", rin.load_task(f"{CASES}/laparoscopy_task.yaml").poses[::20])
    robot = rin.load_robot(f"{CASES}/laparoscopy_robot_fixed.yaml")
    store = ms.RasscmapStore(tmp_path / "store")
    p1 = ss.SetupProblem(cmap, pat, task, robot, store=store)
    p1.evaluate(np.arange(p1.n))
    assert (store.hits, store.misses) == (0, 2)
    p2 = ss.SetupProblem(cmap, pat, task, robot, store=store)
    p2.evaluate(np.arange(p2.n))
    assert store.hits == 2
    np.testing.assert_array_equal(p1.cost, p2.cost)
    assert len(list((tmp_path / "store").rglob("*.h5"))) == 2
