import numpy as np
import pytest
from pydrake.systems.framework import DiagramBuilder

from implantplan.systems.errors import InputError
from implantplan.systems.frames import rotation_angle, rotations
from implantplan.systems.teleop.head_motion import HeadMotion, HeadMotionSource

T = np.linspace(0.0, 6.0, 6001)
PIVOT = np.array([0.3, -0.1, 0.8])


def _u(m, t=T):
    return m.D(t)[:, :3, 3] - (PIVOT - m.D(t)[:, :3, :3] @ PIVOT)


@pytest.mark.parametrize("profile", ["breathing", "swallow", "startle", "drift"])
def test_profiles_are_seeded_and_start_at_rest(profile):
    a, b = HeadMotion.make(profile, seed=3, pivot=PIVOT), HeadMotion.make(profile, seed=3,
                                                                           pivot=PIVOT)
    c = HeadMotion.make(profile, seed=4, pivot=PIVOT)
    np.testing.assert_array_equal(a.D(T), b.D(T))
    assert not np.allclose(a.D(T), c.D(T))
    np.testing.assert_allclose(a.D(0.0)[0], np.eye(4), atol=1e-15)


@pytest.mark.parametrize("seed", range(8))
def test_amplitudes_and_timing_match_the_issue(seed):
    br = HeadMotion.make("breathing", seed=seed, pivot=PIVOT)
    ptp = np.linalg.norm(_u(br), axis=1).max()
    assert 0.001 - 1e-9 <= ptp <= 0.002 + 1e-9
    assert 0.2 <= br.params["frequency_hz"] <= 0.3
    sw = HeadMotion.make("swallow", seed=seed, pivot=PIVOT)
    on = sw.params["onset_s"]
    d = np.linalg.norm(_u(sw), axis=1)
    assert 0.003 - 1e-9 <= d.max() <= 0.005 + 1e-9
    assert T[np.argmax(d)] == pytest.approx(on + 0.5, abs=2e-3)  # up within 0.5 s
    assert d[T > on + 1.0].max() < 1e-9 and d[T < on].max() == 0.0  # and back
    st = HeadMotion.make("startle", seed=seed, pivot=PIVOT)
    on = st.params["onset_s"]
    X = st.D(np.array([on, on + 0.2, on + 1.0]))
    jump = np.linalg.norm(_u(st, np.array([on + 0.2]))[0])
    assert 0.005 - 1e-9 <= jump <= 0.010 + 1e-9
    angle = np.rad2deg(rotation_angle(X[1, :3, :3]))
    assert 2.0 - 1e-6 <= angle <= 4.0 + 1e-6
    np.testing.assert_allclose(X[1], X[2], atol=1e-12)  # stays where it went
    dr = HeadMotion.make("drift", seed=seed, pivot=PIVOT)
    per_min = np.linalg.norm(_u(dr, np.array([60.0]))[0])
    assert 0.002 - 1e-9 <= per_min <= 0.005 + 1e-9


@pytest.mark.parametrize("profile", ["breathing", "swallow", "startle"])
def test_velocity_is_the_derivative_of_the_pose(profile):
    m = HeadMotion.make(profile, seed=1, pivot=PIVOT)
    point = PIVOT + np.array([0.02, 0.05, -0.03])
    t = np.linspace(0.5, 4.0, 3501)
    X = m.D(t)
    p = X[:, :3, :3] @ point + X[:, :3, 3]
    v_fd = np.gradient(p, t, axis=0)
    V = m.velocity(t, point)
    np.testing.assert_allclose(V[1:-1, 3:], v_fd[1:-1], atol=2e-4)


def test_csv_round_trip_and_errors(tmp_path):
    m = HeadMotion.make("startle", seed=2, pivot=PIVOT)
    t = np.linspace(0.0, 5.0, 501)
    path = m.save_csv(tmp_path / "head.csv", t)
    r = HeadMotion.make(str(path), pivot=PIVOT)
    assert r.profile == "csv"
    np.testing.assert_allclose(r.D(t), m.D(t), atol=1e-8)
    (tmp_path / "bad.csv").write_text("t_s,x_m\n0,1\n1,2\n")
    with pytest.raises(InputError, match="7 columns"):
        HeadMotion.make(str(tmp_path / "bad.csv"))
    (tmp_path / "back.csv").write_text("h\n1,0,0,0,0,0,0\n0,0,0,0,0,0,0\n")
    with pytest.raises(InputError, match="increasing"):
        HeadMotion.from_csv(tmp_path / "back.csv")
    with pytest.raises(InputError, match="--head-motion"):
        HeadMotion.make("sneeze")


def test_source_outputs_the_moved_head_frame():
    m = HeadMotion.make("startle", seed=5, pivot=PIVOT)
    X0 = np.eye(4)
    X0[:3, 3] = PIVOT + [0.0, 0.01, 0.02]
    builder = DiagramBuilder()
    src = builder.AddSystem(HeadMotionSource(m, X0))
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    t = m.params["onset_s"] + 0.1
    ctx.SetTime(t)
    sc = src.GetMyContextFromRoot(ctx)
    X = src.GetOutputPort("X_WHead").Eval(sc).GetAsMatrix4()
    np.testing.assert_allclose(X, m.D(t)[0] @ X0, atol=1e-12)
    V = src.GetOutputPort("V_WHead").Eval(sc)
    np.testing.assert_allclose(V, m.velocity(t, X0[:3, 3])[0], atol=1e-12)


def test_the_motion_is_a_parameter_of_the_context():
    """One source replays another motion in a context (set_motion): the outputs are the other
    motion's, the default context keeps the built one, and a non-motion is refused."""
    built, other = (HeadMotion.make("swallow", seed=s, pivot=PIVOT) for s in (1, 2))
    src = HeadMotionSource(built, np.eye(4))
    ctx, default = src.CreateDefaultContext(), src.CreateDefaultContext()
    src.set_motion(ctx, other)
    assert src.motion_in(ctx).seed == 2 and src.motion_in(default).seed == 1
    t = other.params["onset_s"] + 0.3
    for c in (ctx, default):
        c.SetTime(t)
    np.testing.assert_array_equal(src.GetOutputPort("X_WHead").Eval(ctx).GetAsMatrix4(),
                                  other.D(t)[0])
    np.testing.assert_array_equal(src.GetOutputPort("D_W").Eval(default).GetAsMatrix4(),
                                  built.D(t)[0])
    assert not np.allclose(other.D(t), built.D(t))
    with pytest.raises(InputError, match="head_motion"):
        src.set_motion(ctx, "swallow")


def test_a_turn_is_about_the_neck_at_its_drawn_rate():
    """The turn profile: points on the neck's axis stay put, the head turns by its drawn angle
    about that axis (either way over seeds), the peak angular rate is the drawn one."""
    from implantplan.systems.teleop.head_motion import NECK_BEHIND_CENTER, neck_of

    X_WC = np.eye(4)
    X_WC[:3, :3] = rotations(np.array([[0.3, -0.2, 1.1]]))[0]
    X_WC[:3, 3] = [0.4, -0.1, 0.9]
    point, axis = neck_of(X_WC)
    assert np.allclose(point, X_WC[:3, 3] - NECK_BEHIND_CENTER * X_WC[:3, 2])
    signs = set()
    for seed in range(12):
        hm = HeadMotion.make("turn", seed=seed, pivot=X_WC[:3, 3], neck=(point, axis))
        p = hm.params
        assert np.deg2rad(10) <= p["angle_rad"] <= np.deg2rad(15)
        assert np.deg2rad(30) <= p["peak_rate_rad_s"] <= np.deg2rad(60)
        signs.add(float(np.sign(p["axis"] @ axis)))
        t = np.linspace(0.0, 5.0, 5001)
        D = hm.D(t)
        on_axis = np.array([point, point + 0.05 * axis, point - 0.1 * axis])
        moved = np.einsum("nij,kj->nki", D[:, :3, :3], on_axis) + D[:, None, :3, 3]
        assert np.abs(moved - on_axis).max() < 1e-12
        end = D[-1, :3, :3]
        assert np.rad2deg(np.arccos((np.trace(end) - 1) / 2)) == pytest.approx(
            np.rad2deg(p["angle_rad"]), abs=1e-9)
        rate = np.linalg.norm(hm.velocity(t)[:, :3], axis=1)
        assert rate.max() == pytest.approx(p["peak_rate_rad_s"], rel=1e-4)
        assert np.all(rate[t < p["onset_s"]] < 1e-9)
        # the mouth (Center's origin) moves at the lever arm's speed
        v = np.linalg.norm(hm.velocity(t, point=X_WC[:3, 3])[:, 3:], axis=1)
        assert v.max() == pytest.approx(p["peak_rate_rad_s"] * NECK_BEHIND_CENTER, rel=1e-3)
    assert signs == {-1.0, 1.0}


def test_a_turn_with_given_parameters_is_the_drawn_turn():
    """HeadMotion.turn (the sweep's deterministic turn) with a drawn turn's parameters is that
    turn, pose for pose; bad parameters are refused naming them."""
    X_WC = np.eye(4)
    X_WC[:3, 3] = [0.4, -0.1, 0.9]
    from implantplan.systems.teleop.head_motion import neck_of

    neck = neck_of(X_WC)
    for seed in range(4):
        drawn = HeadMotion.make("turn", seed=seed, pivot=X_WC[:3, 3], neck=neck)
        p = drawn.params
        sign = float(np.sign(p["axis"] @ neck[1]))
        given = HeadMotion.turn(angle=p["angle_rad"], peak_rate=p["peak_rate_rad_s"], sign=sign,
                                onset=p["onset_s"], pivot=X_WC[:3, 3], neck=neck)
        t = np.linspace(0.0, 5.0, 501)
        np.testing.assert_allclose(given.D(t), drawn.D(t), atol=1e-15)
    for kw, name in (({"angle": 0.0}, "turn.angle"), ({"peak_rate": np.nan}, "turn.peak_rate"),
                     ({"onset": -1.0}, "turn.onset"), ({"sign": 0.5}, "turn.sign")):
        args = {"angle": 0.2, "peak_rate": 1.0, "sign": 1.0, "onset": 1.0, **kw}
        with pytest.raises(InputError, match=name):
            HeadMotion.turn(**args)


@pytest.mark.parametrize("profile", ["breathing", "swallow", "startle", "drift", "turn"])
def test_speed_bounds_bound_the_motion_and_are_tight(profile):
    """speed_bounds() (the swept clearance under a moving head rests on it) is at or above the
    angular speed and the pivot image's speed at 20,001 times, and within 0.1% of their peak for
    the closed forms that reach it (the drift is constant)."""
    X_WC = np.eye(4)
    X_WC[:3, 3] = PIVOT
    from implantplan.systems.teleop.head_motion import neck_of

    for seed in range(3):
        hm = HeadMotion.make(profile, seed=seed, pivot=PIVOT, neck=neck_of(X_WC))
        w_max, v_max = hm.speed_bounds()
        t = np.linspace(0.0, 6.0, 20001)
        V = hm.velocity(t)  # [omega; velocity of the pivot's image]
        w, v = np.linalg.norm(V[:, :3], axis=1), np.linalg.norm(V[:, 3:], axis=1)
        assert w.max() <= w_max * (1 + 1e-6) + 1e-12
        assert v.max() <= v_max * (1 + 1e-6) + 1e-12
        if profile != "turn":  # the turn's pivot image moves slower than w |neck - pivot|
            assert v.max() >= v_max * (1 - 1e-3)
        assert w.max() >= w_max * (1 - 1e-3)


def test_speed_bounds_of_a_recording(tmp_path):
    """A CSV's bounds are its largest slopes (linear interpolation between the rows)."""
    path = tmp_path / "head.csv"
    path.write_text("t_s,x_m,y_m,z_m,rx_rad,ry_rad,rz_rad\n0,0,0,0,0,0,0\n"
                    "0.5,0.001,0,0,0,0,0.01\n1.0,0.001,0.003,0,0,0,0.01\n")
    w_max, v_max = HeadMotion.from_csv(path).speed_bounds()
    assert w_max == pytest.approx(0.02) and v_max == pytest.approx(0.006)
