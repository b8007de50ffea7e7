"""Capability map core: reach / no reach, index range, roll handling, blocks, HDF5 round trip."""

import functools
from concurrent.futures import ThreadPoolExecutor

import h5py
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from implantplan.systems.actuator import actuator_map_frame
from implantplan.systems.capability import certificate as ce
from implantplan.systems.capability import maps as cm
from implantplan.systems.errors import InputError
from implantplan.systems.frames import rot_x, rot_z, transform
from implantplan.systems.robot.kinematics import fk, ik, jacobian_space, joint_limits


@pytest.fixture(scope="module")
def coarse():
    """A 15 cm / 30-direction map sampled at voxel centres (the query machinery; a certified map
    this coarse certifies almost nothing)."""
    return cm.build(cm.make_params(0.15, 30, cell="centre"), workers=1)


REGIONS = {  # name: (centre of a 12 cm ball in base_link, m): where the default suite checks
    "outer reach": cm.SHOULDER + np.array([0.62, -0.55, 0.58]),  # ~1.02 m from the shoulder
    "shoulder cylinder": np.array([0.05, 0.24, 0.45]),  # wrist centre near d4 of joint 1's axis
    "mid workspace": cm.SHOULDER + np.array([-0.35, 0.45, -0.2]),
}


ACTUATOR = actuator_map_frame()


def regional_map(centre, params=None, radius=0.12, **certify_options):
    """The certified 5 cm / 100-direction map over the voxels that meet a ball (built like the
    plan's capability check: only the voxels needed); ``certify_options`` go to the
    certificate (a term dropped)."""
    params = params or cm.make_params(0.05, 100)
    grid = cm.make_grid(params)
    ids = np.arange(grid.size)
    near = np.linalg.norm(grid.centres(ids) - centre, axis=1) <= radius + grid.voxel
    return cm.CapabilityMap(params, grid, *cm.build_block(params, ids[near],
                                                          certify_options=certify_options))


def actuator_params():
    return cm.make_params(0.05, 100, X_FT=ACTUATOR, tool="actuator")


@functools.cache
def region_poses(region, seed, n=3000):
    """n uniform poses in the 12 cm ball of ``region`` (SO(3) rotations) and n within 1e-7 of
    the actuator's exact reachability boundary (seeds not tuned); made once per test run (the
    tool map's test and the broken certificates' share them; the arrays are read-only)."""
    centre = REGIONS[region]
    X = np.concatenate([
        cm.random_poses(n, seed=seed, radius=0.12, center=centre),
        cm.boundary_poses(actuator_params(), n, seed=seed + 1, radius=0.12, center=centre),
    ])  # fmt: skip
    X.flags.writeable = False
    return X


@pytest.fixture(scope="module")
def regional():
    return {name: regional_map(c) for name, c in REGIONS.items()}


def test_golden_spiral_unit_and_spread():
    d = cm.golden_spiral(200)
    assert d.shape == (200, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    # near-uniform: the mean vector of a uniform point set is ~0, z spacing is 2/K
    assert np.linalg.norm(d.mean(axis=0)) < 0.02
    np.testing.assert_allclose(np.diff(d[:, 2]), -2.0 / 200, atol=1e-12)


@given(st.floats(-1, 1), st.floats(-np.pi, np.pi))
@settings(max_examples=100, deadline=None)
def test_nearest_direction_within_a_cell_of_the_true_nearest(z, phi):
    m = _tiny_map()
    s = np.sqrt(1 - z * z)
    v = np.array([s * np.cos(phi), s * np.sin(phi), z])
    chosen = m.directions[m.nearest_direction(v[None])[0]] @ v
    best = np.max(m.directions @ v)
    n_theta = m._table.shape[0]
    # the table's pick is at most one cell diameter worse than the true nearest (poles included)
    assert np.arccos(min(1.0, chosen)) <= np.arccos(min(1.0, best)) + 1.5 * np.pi / n_theta
    # the compiled query kernel and the numpy lookup agree
    cell = m.centres()[0]
    X = transform(cm.frames_from_z(v), cell)
    bit = m.query_points(X[None, :3, 3], X[None, :3, 2])[0][0]
    assert bit == m.reach_rows([0])[0, m.nearest_direction(v[None])[0]]


_TINY = []


def _tiny_map():
    if not _TINY:
        _TINY.append(cm.build(cm.make_params(0.3, 50), workers=1))
    return _TINY[0]


def test_obviously_reachable_and_unreachable(coarse):
    full = np.flatnonzero(coarse.index == 1.0)
    assert len(full) > 0
    c = coarse.centres()[full[0]]
    X = transform(rot_x(2.0), c)  # any direction in a voxel whose every direction is reachable
    reach, index = coarse.query(X[None])
    assert reach[0] == cm.exact_reachable(coarse.params, X[None])[0] and index[0] == 1.0
    assert coarse.verdict(X[None])[0] == cm.UNDECIDED  # a centre map certifies nothing
    # 3 m away from the base: beyond the 1.65 m reach, certified unreachable without IK
    far = transform(np.eye(3), [3.0, 0.0, 0.5])[None]
    reach, source, index = coarse.answer(far)
    assert not reach[0] and source[0] == cm.NO and index[0] == 0.0
    # a real arm pose: its voxel centre is 'reachable' in the map at the pose's direction
    q = np.array([0.3, 0.4, 1.2, 0.2, 1.0, 0.0])
    assert cm.reach_at(coarse.params, fk(q)[None, :3, 3], fk(q)[None, :3, 2])[0][0, 0]


def test_index_in_unit_interval_and_matches_bits(coarse):
    assert np.all((coarse.index > 0) & (coarse.index <= 1))
    rows = coarse.reach_rows()
    np.testing.assert_allclose(coarse.index, rows.mean(axis=1))
    # stored voxels all lie within the reach sphere about the shoulder
    assert np.all(np.linalg.norm(coarse.centres() - cm.SHOULDER, axis=1) <= cm.ARM_REACH + 0.15)


def test_voxel_index_seen_from_many_bases(coarse):
    rng = np.random.default_rng(6)
    pts = rng.uniform(-1.5, 1.5, (300, 3))
    X_BW = np.stack([transform(rot_x(a), [0.1 * a, 0.0, -0.2]) for a in (0.0, 0.5, 2.0)])
    got = coarse.voxel_index(pts, X_BW)
    for b in range(3):
        p_B = pts @ X_BW[b, :3, :3].T + X_BW[b, :3, 3]
        np.testing.assert_array_equal(got[b], coarse.query_points(p_B, np.ones_like(p_B))[1])
    assert got.max() > 0 and got.min() == 0.0


def test_roll_free_with_360_limits():
    p = cm.make_params(0.2, 20, limits="360")
    m = cm.build(p, workers=1)
    np.testing.assert_array_equal(m.reach_bits, m.all_roll_bits)


def test_roll_with_175_limits_matches_sampled_rolls():
    p = cm.make_params(0.2, 20, limits="175")
    rng = np.random.default_rng(3)
    centres = cm.SHOULDER + rng.uniform(-1.2, 1.2, (60, 3))
    dirs = cm.golden_spiral(20)
    some, every = cm.reach_at(p, centres, dirs)
    # brute force: 720 rolls (0.5 deg) with the true +-175 deg limits on every joint
    gam = np.deg2rad(np.arange(0, 360, 0.5))
    Rz = np.zeros((len(gam), 4, 4))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1] = (
        np.cos(gam),
        -np.sin(gam),
        np.sin(gam),
        np.cos(gam),
    )
    Rz[:, 2, 2] = Rz[:, 3, 3] = 1
    base = np.zeros((60, 20, 4, 4))
    base[..., :3, :3] = cm.frames_from_z(dirs)[None]
    base[..., :3, 3] = centres[:, None]
    base[..., 3, 3] = 1
    per_roll = ik(base[:, :, None] @ Rz, limits="175").valid.any(-1)  # (60, 20, 720)
    np.testing.assert_array_equal(some, per_roll.any(-1))
    np.testing.assert_array_equal(every, per_roll.all(-1))
    assert some.sum() > every.sum() > 0  # the 10 deg gap matters for single-branch pairs


def test_self_collision_option_removes_folded_branches():
    q = np.zeros((2, 6))
    q[1, 2] = np.radians(170)  # forearm folded back onto the upper arm
    np.testing.assert_array_equal(cm.self_collision_free(q), [True, False])
    free = cm.make_params(0.2, 20)
    checked = cm.make_params(0.2, 20, self_collision=True)
    assert free.key() != checked.key()
    rng = np.random.default_rng(8)
    centres = cm.SHOULDER + rng.uniform(-1.0, 1.0, (80, 3))
    dirs = cm.golden_spiral(20)
    a, _ = cm.reach_at(free, centres, dirs)
    b, _ = cm.reach_at(checked, centres, dirs)
    assert np.all(a | ~b)  # collision checking only removes pairs
    assert b.sum() < a.sum()


def test_tool_not_coaxial_samples_roll():
    X_FT = transform(rot_x(np.pi / 2), [0.0, 0.0, 0.1])  # tool axis perpendicular to the flange z
    p = cm.make_params(0.2, 10, X_FT=X_FT, tool="test")
    assert p.rolls == 12
    assert not cm.roll_is_free(X_FT)
    with pytest.raises(InputError, match="rolls"):
        cm.make_params(0.2, 10, rolls=4)


def test_blocks_through_any_executor_give_the_same_map(coarse):
    with ThreadPoolExecutor(2) as ex:
        m = cm.build(coarse.params, executor=ex, poses_per_block=5000)
    np.testing.assert_array_equal(m.voxel_ids, coarse.voxel_ids)
    np.testing.assert_array_equal(m.reach_bits, coarse.reach_bits)
    assert sum(len(b) for b in cm.blocks_of(coarse.params, 5000)) >= len(m.voxel_ids)


def test_hdf5_round_trip_and_parameter_check(coarse, tmp_path):
    path = tmp_path / "map.h5"
    coarse.save(path)
    m = cm.load(path, expect={"limits": "175", "directions": 30, "voxel": 0.15})
    assert m.params == coarse.params
    np.testing.assert_array_equal(m.reach_bits, coarse.reach_bits)
    X = cm.random_poses(2000, seed=5)
    np.testing.assert_array_equal(m.query(X)[0], coarse.query(X)[0])
    with pytest.raises(InputError, match="limits"):
        cm.load(path, expect={"limits": "360"})
    with h5py.File(path, "a") as f:
        f.attrs["schema_version"] = 99
    with pytest.raises(InputError, match="schema_version"):
        cm.load(path)
    with pytest.raises(InputError, match="does not exist"):
        cm.load(tmp_path / "missing.h5")


def test_accuracy_counts_add_up(coarse):
    X = cm.random_poses(5000, seed=2)
    paper = cm.accuracy(coarse, X, exact_roll=False)  # the centre bits, the paper's question
    assert paper["TP"] + paper["FP"] + paper["FN"] + paper["TN"] == pytest.approx(1.0)
    assert paper["correct"] > 0.85  # a 15 cm / 30-direction centre map is still mostly right
    assert paper["FP"] > 0 and paper["false_safe"] == round(paper["FP"] * 5000)
    assert paper["rejected_reachable"] == pytest.approx(
        paper["FN"] / (paper["TP"] + paper["FN"]))
    acc = cm.accuracy(coarse, X)  # the answers: undecided cells resolved by IK, always right
    assert acc["correct"] == 1.0 and acc["false_safe"] == 0 and acc["false_yes"] == 0
    assert acc["certified_yes"] == 0.0  # the reach ball: no pose is certified unreachable
    assert acc["certified_no"] == 0.0 and acc["resolved_by_ik"] == 1.0


def test_bad_params_are_input_errors():
    with pytest.raises(InputError, match="voxel"):
        cm.make_params(0.0, 10)
    with pytest.raises(InputError, match="directions"):
        cm.make_params(0.1, 0)
    with pytest.raises(InputError, match="limits"):
        cm.make_params(0.1, 10, limits="180")
    with pytest.raises(InputError, match="poses"):
        cm.build(cm.make_params(0.3, 4), workers=1).query(np.zeros((3, 3)))


def _hand_map():
    """A 4x4x4 grid of 0.1 m voxels at the origin with two stored voxels: (1, 1, 1) reaching 8
    of 8 directions (index 1) and (1, 1, 2) reaching 2 of 8 (index 0.25)."""
    params = cm.make_params(0.1, 8)
    grid = cm.Grid(origin=np.zeros(3), voxel=0.1, shape=(4, 4, 4))
    ids = np.ravel_multi_index(np.array([[1, 1], [1, 1], [1, 2]]), grid.shape)
    bits = np.array([[0xFF], [0b11000000]], dtype=np.uint8)
    return cm.CapabilityMap(params, grid, ids, bits, bits.copy())


def test_neighbourhood_ids_hand_derived():
    g = _hand_map().grid
    near = g.neighbourhood(np.array([[0.15, 0.15, 0.15], [0.05, 0.05, 0.05], [-1.0, 0.0, 0.0]]))
    assert near.shape == (3, 27)
    # interior voxel (1,1,1): all 27 inside, offsets in C order, the centre is entry 13
    expect = [np.ravel_multi_index((1 + i, 1 + j, 1 + k), g.shape)
              for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)]
    assert near[0].tolist() == expect and near[0, 13] == np.ravel_multi_index((1, 1, 1), g.shape)
    # corner voxel (0,0,0): only the 2x2x2 cells with non-negative indices are inside
    assert int(np.sum(near[1] >= 0)) == 8
    assert np.all(near[2] == -1)  # far outside


def test_neighbourhood_index_hand_derived():
    m = _hand_map()
    # around (1,1,1): both stored voxels are neighbours -> (1 + 0.25) / 27; around (1,1,3): only
    # (1,1,2) -> 0.25 / 27 (the cells with k = 4 are outside the grid and count 0)
    got = m.neighbourhood_index(np.array([[0.15, 0.15, 0.15], [0.15, 0.15, 0.35]]))
    np.testing.assert_allclose(got, [1.25 / 27, 0.25 / 27], rtol=1e-15)
    # batches keep their leading shape
    assert m.neighbourhood_index(np.zeros((2, 5, 3))).shape == (2, 5)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-0.1, 0.5), min_size=3, max_size=3))
def test_neighbourhood_index_is_the_mean_voxel_index_of_the_neighbour_centres(p):
    m = _hand_map()
    near = m.grid.neighbourhood(np.array(p))
    centres = m.grid.centres(np.maximum(near, 0))
    ref = np.where(near >= 0, m.voxel_index(centres), 0.0).mean()
    assert m.neighbourhood_index(np.array(p)) == pytest.approx(ref, abs=1e-15)


# -- the certified map: yes / no / undecided, undecided resolved by IK -------------------------


@pytest.mark.parametrize("seed, boundary", [
    (20261201, 400),
    pytest.param(4711, 1000, marks=pytest.mark.sweep),
    pytest.param(99, 1000, marks=pytest.mark.sweep)])  # fmt: skip
@pytest.mark.parametrize("region", list(REGIONS))
def test_certified_map_is_never_false_yes(regional, region, seed, boundary):
    """0 poses in certified-yes cells where exact IK at the pose fails: poses uniform in the
    region (position in the ball, SO(3) rotation) and poses within 1e-7 of the exact
    reachability boundary (seeds not tuned; one seed per region and 400 boundary poses by
    default, all three seeds and 1,000 in the sweep: in the mid workspace one pair of
    random neighbours in about 3,700 straddles the boundary, so each boundary pose costs some
    3,700 IK solutions); the answers (undecided cells by IK) are all right, and the certificate
    still covers a good share of the reachable poses."""
    m, c = regional[region], REGIONS[region]
    X = np.concatenate([
        cm.random_poses(2000, seed=seed, radius=0.12, center=c),
        cm.boundary_poses(m.params, boundary, seed=seed + 1, radius=0.12, center=c),
    ])  # fmt: skip
    acc = cm.accuracy(m, X)
    assert acc["false_yes"] == 0 and acc["false_no"] == 0
    assert acc["correct"] == 1.0 and acc["false_safe"] == 0
    assert acc["coverage"] > 0.15  # the shoulder cylinder's is the lowest (0.16-0.17)


@pytest.mark.parametrize("region", ["mid workspace", pytest.param("outer reach",
                                                                  marks=pytest.mark.sweep)])
def test_certified_tool_map_is_never_false_yes(region):
    """The actuator's tip (contra-angle: roll sampled, one certified bit per roll bin)."""
    params, c = actuator_params(), REGIONS[region]
    acc = cm.accuracy(regional_map(c, params), region_poses(region, seed=1))
    assert acc["false_yes"] == 0 and acc["correct"] == 1.0
    assert acc["coverage"] > 0.22  # outer reach 0.26: the elbow's reach bound


@pytest.mark.parametrize("region, drop", [
    ("mid workspace", {"rotation_term": False}),
    ("outer shell", {"position_term": False}),
    ("shoulder cylinder", {"shoulder_term": False}),
    ("outer shell", {"kappa": 1.0}),
])  # fmt: skip
def test_a_broken_certificate_is_caught(region, drop):
    """The same test sets (the region's poses and the broken map's own cell corners,
    cm.corner_poses) catch a certificate with a bound term dropped (or the safety factor on the
    first-order bound removed): exact IK contradicts some of its certified cells. The position
    term and the safety factor show at the actuator's outer reach (outer_shell_map), where the
    elbow's reach bound does not already hide them."""
    if region == "outer shell":
        broken = outer_shell_map(ACTUATOR, **drop)
        X = cm.corner_poses(broken, 50_000, seed=1)
    else:
        params, c = actuator_params(), REGIONS[region]
        broken = regional_map(c, params, **drop)
        X = np.concatenate([region_poses(region, seed=1),
                            cm.corner_poses(broken, 20_000, seed=1)])
    assert cm.accuracy(broken, X)["false_yes"] > 0


def outer_shell_map(tool_frame, **certify_options):
    """The certified 5 cm / 100-direction map of ``tool_frame`` over 60 voxels drawn (seed 0)
    from the shell where the tool meets the elbow's reach: 1.3-1.55 m from the shoulder for
    the actuator's tip, 1.05-1.3 m for the flange (no flange cell is certified beyond)."""
    params = cm.make_params(0.05, 100, X_FT=tool_frame,
                            tool="flange" if tool_frame is None else "actuator")
    lo, hi = (1.05, 1.3) if tool_frame is None else (1.3, 1.55)
    grid = cm.make_grid(params)
    ids = cm.candidate_voxels(params, grid)
    d = np.linalg.norm(grid.centres(ids) - cm.SHOULDER, axis=1)
    pick = np.random.default_rng(0).choice(ids[(d > lo) & (d < hi)], size=60, replace=False)
    return cm.CapabilityMap(params, grid, *cm.build_block(params, pick,
                                                          certify_options=certify_options))


@pytest.mark.parametrize("tool_frame", [ACTUATOR, None], ids=["actuator", "flange"])
def test_certified_cells_hold_at_their_corners(tool_frame):
    """At the far ends of the certified cells (voxel corners, the edge of the direction's
    region, the edge of the roll bin: cm.corner_poses) exact IK reaches every pose; the same
    poses catch the elbow bounded by q3's own room (the rule before the reach's cos q3)."""
    m = outer_shell_map(tool_frame)
    X = cm.corner_poses(m, 100_000, seed=1)
    acc = cm.accuracy(m, X)
    assert acc["certified_yes"] > 0.999  # the poses lie in certified cells
    assert acc["false_yes"] == 0 and acc["correct"] == 1.0
    if tool_frame is not None:
        old = outer_shell_map(tool_frame, elbow_reach=False)
        assert cm.accuracy(old, cm.corner_poses(old, 100_000, seed=1))["false_yes"] > 0


def test_corner_poses_lie_at_the_ends_of_certified_cells():
    m = outer_shell_map(ACTUATOR)
    X = cm.corner_poses(m, 2000, seed=3)
    np.testing.assert_array_equal(X, cm.corner_poses(m, 2000, seed=3))
    np.testing.assert_allclose(X[:, :3, :3] @ np.swapaxes(X[:, :3, :3], 1, 2),
                               np.broadcast_to(np.eye(3), (2000, 3, 3)), atol=1e-12)
    assert np.mean(m.verdict(X) == cm.YES) > 0.999
    # most positions at a corner of their voxel (within 1e-9 of half an edge on every axis)
    off = np.abs(X[:, :3, 3] - m.grid.centres(np.ravel_multi_index(
        m.grid.cells(X[:, :3, 3]).T, m.grid.shape)))
    assert 0.6 < np.mean(np.all(off > 0.025 - 1e-8, axis=1)) < 0.8
    # most z axes on the edge of their direction's region: the neighbour's a degree further
    d = m.nearest_direction(X[:, :3, 2])
    ang = np.arccos(np.clip(np.sum(X[:, :3, 2] * m.directions[d], axis=1), -1, 1))
    assert np.median(ang / cm.direction_radii(100)[d]) > 0.5
    assert cm.corner_poses(cm.empty_map(m.params), 5, seed=0).shape == (0, 4, 4)


def test_answers_are_exact_and_say_where_they_came_from(regional):
    m, c = regional["outer reach"], REGIONS["outer reach"]
    X = np.concatenate([cm.random_poses(1500, seed=8, radius=0.3, center=c),
                        cm.random_poses(50, seed=9, radius=0.2, center=[2.5, 0.0, 0.0])])
    reach, source, index = m.answer(X)
    np.testing.assert_array_equal(reach, cm.exact_reachable(m.params, X))
    assert set(np.unique(source)) == {cm.YES, cm.NO, cm.UNDECIDED}
    assert np.all(reach[source == cm.YES]) and not np.any(reach[source == cm.NO])
    np.testing.assert_array_equal(m.verdict(X), source)
    np.testing.assert_array_equal(m.query(X)[0], reach)
    np.testing.assert_array_equal(index, m.query_points(X[:, :3, 3], X[:, :3, 2])[1])
    assert {cm.SOURCES[int(v)] for v in np.unique(source)} == {
        "certified reachable", "certified unreachable", "resolved by IK"}


def test_certified_cells_lie_inside_the_centre_sampled_ones(regional):
    """A certified cell's centre sample is reachable, so its (voxel, direction) bit is set in
    the paper's map; the paper's map alone is false-safe near the boundary."""
    m = regional["outer reach"]
    k = m.params.directions
    yes = np.unpackbits(m.yes_bits, axis=1, count=k)
    assert np.all(m.reach_rows() | ~yes.astype(bool))
    X = cm.boundary_poses(m.params, 300, seed=5, radius=0.12, center=REGIONS["outer reach"])
    centre_bits, _ = m.query_points(X[:, :3, 3], X[:, :3, 2])
    assert np.sum(centre_bits & ~cm.exact_reachable(m.params, X)) > 0


def test_boundary_poses_straddle_the_exact_boundary():
    params = cm.make_params(0.15, 30)
    X = cm.boundary_poses(params, 400, seed=3)
    assert X.shape == (400, 4, 4)
    truth = cm.exact_reachable(params, X)
    assert np.array_equal(truth[0::2], ~truth[1::2])  # pairs: one reachable, one not
    gap = np.linalg.norm(X[0::2, :3, 3] - X[1::2, :3, 3], axis=1)
    assert gap.max() < 1e-5
    np.testing.assert_array_equal(X, cm.boundary_poses(params, 400, seed=3))


def test_jacobian_inverse_is_the_inverse_of_the_kinematics_jacobian():
    rng = np.random.default_rng(4)
    G = np.empty((6, 6))
    for X_FT in (np.eye(4), ACTUATOR):
        for q in rng.uniform(-3, 3, (20, 6)):
            assert ce.jacobian_inverse(q, X_FT, G)
            np.testing.assert_allclose(G @ jacobian_space(q, X_FT), np.eye(6), atol=1e-8)
    assert not ce.jacobian_inverse(np.zeros(6), np.eye(4), G)  # q5 = 0: the wrist is singular


def test_direction_radii_bound_every_query_direction():
    """Every z axis the query sends to direction d lies within alpha[d] of d."""
    m = cm.CapabilityMap(cm.make_params(0.3, 100), cm.make_grid(cm.make_params(0.3, 100)),
                         np.zeros(0, np.int64), np.zeros((0, 13), np.uint8),
                         np.zeros((0, 13), np.uint8))
    z = cm.random_poses(200_000, seed=3)[:, :3, 2]
    d = m.nearest_direction(z)
    ang = np.arccos(np.clip(np.sum(z * m.directions[d], axis=1), -1, 1))
    alpha = cm.direction_radii(100)
    assert np.all(ang <= alpha[d])
    assert alpha.max() < 0.35  # and tight: the Voronoi cells of 100 directions plus the table


def test_roll_bins_hand_derived():
    dirs = cm.golden_spiral(30)
    F = cm.frames_from_z(dirs)
    for r in range(12):
        g = 2 * np.pi * r / 12 + np.radians(14.0)  # inside bin r (half width 15 deg)
        Rz = rot_z(g)
        np.testing.assert_array_equal(cm.roll_bins(F @ Rz, dirs, 12), r)
    # the pose's z tilted off d: roll measured in F(d) carried along the tilt (Rodrigues)
    axis = np.cross(dirs[4], [0.0, 0.0, 1.0])
    axis /= np.linalg.norm(axis)
    tilt = Rotation.from_rotvec(0.2 * axis).as_matrix()
    R = tilt @ F[4] @ rot_z(np.radians(61.0))
    assert cm.roll_bins(R[None], dirs[4:5], 12)[0] == 2  # 61 deg is nearest 60 deg
    assert cm.roll_bins(R[None], dirs[4:5], 1)[0] == 0


def test_certificate_follows_its_definition():
    """The compiled kernel against a plain numpy reading of the rule on real cells (actuator,
    +-175 deg): a branch valid and not singular at the centre sample, G = J^-1 from
    kinematics.jacobian_space, dq_j = kappa (h sum|G[j, 3:]| + alpha |P g_j| + pi/R |g_j . z0|),
    every joint's room >= slack + dq_j, cos q3 kept inside [-1, 1] by |sin q3| dq_3 (the
    elbow's reach), q5 at least dq from 0 and pi, the wrist centre
    more than d4 + the rigorous bound from joint 1's axis; at most TRIES branches in order of
    their smallest room."""
    params = actuator_params()
    grid = cm.make_grid(params)
    ids = np.ravel_multi_index(grid.cells(REGIONS["mid workspace"] + np.array([[0, 0, 0],
                               [0.05, 0, 0], [0, 0.3, 0.1]])).T, grid.shape)
    dirs = cm.golden_spiral(100)
    R_s, res, valid = cm.centre_samples(params, grid.centres(ids), dirs)
    ok = valid & ~res.singular
    alpha = cm.direction_radii(100)
    got = ce.certify(res.q, ok, R_s, grid.centres(ids), alpha=alpha, voxel=0.05, X_FT=ACTUATOR,
                     limits=joint_limits("175"), slack=params.slack, rolls=12)
    lo, hi = joint_limits("175")
    c = ce.wrist_centre_offset(ACTUATOR)
    sroom = lambda x: np.minimum(np.abs(x), np.pi - np.abs(x))  # noqa: E731
    expect = np.zeros_like(got)
    for v in range(len(ids)):
        for d in range(100):
            for r in range(12):
                w = grid.centres(ids[v]) + R_s[d, r] @ c
                bound = 0.5 * np.sqrt(3) * 0.05 + np.linalg.norm(c) * (alpha[d] + np.pi / 12)
                if np.hypot(w[0], w[1]) - 0.2013 <= bound:
                    continue
                q = res.q[v, d, r]
                score = np.where(ok[v, d, r], np.minimum(
                    np.minimum(sroom(q[:, 2]), sroom(q[:, 4])),
                    np.min(np.minimum(q - lo, hi - q), axis=1)), -1.0)
                for b in np.argsort(-score, kind="stable")[:ce.TRIES]:
                    if score[b] <= params.slack:
                        break
                    G = np.linalg.inv(jacobian_space(q[b], ACTUATOR))
                    g, z0 = G[:, :3], R_s[d, r, :, 2]
                    gz = g @ z0
                    dq = ce.KAPPA * (0.025 * np.abs(G[:, 3:]).sum(1)
                                     + alpha[d] * np.linalg.norm(g - gz[:, None] * z0, axis=1)
                                     + np.pi / 12 * np.abs(gz))
                    if (np.all(dq <= ce.DQ_MAX) and np.all(q[b] - dq >= lo + params.slack)
                            and np.all(q[b] + dq <= hi - params.slack)
                            and abs(np.sin(q[b, 2])) * dq[2] <= 1 - abs(np.cos(q[b, 2]))
                            and sroom(q[b, 4]) >= dq[4]):
                        expect[v, d, r] = True
                        break
    assert np.mean(got == expect) > 0.999  # rounding at the thresholds only
    assert 0.1 < got.mean() < 0.95


@pytest.mark.parametrize("version", [1, 2])
def test_old_schema_maps_are_refused_naming_the_file(coarse, tmp_path, version):
    path = tmp_path / "old.h5"
    coarse.save(path)
    with h5py.File(path, "a") as f:
        f.attrs["schema_version"] = version
    with pytest.raises(InputError, match="old.h5.*rebuild"):
        cm.load(path)


def test_cell_and_slack_are_validated():
    with pytest.raises(InputError, match="cell"):
        cm.make_params(0.1, 10, cell="corner")
    with pytest.raises(InputError, match="slack"):
        cm.make_params(0.1, 10, cell="centre", slack=0.1)
    assert cm.make_params(0.1, 10).key() != cm.make_params(0.1, 10, cell="centre").key()
