"""systems.robot.scenario: the bundled scenarios read through the typed sections give exactly the
Scenario that the file says (every field, bit for bit), and the schema's own rules."""

import dataclasses

import numpy as np
import pytest
import yaml

from implantplan.systems import actuator as act
from implantplan.systems.errors import InputError
from implantplan.systems.frames import rpy_to_rotation, transform
from implantplan.systems.robot import moprp
from implantplan.systems.robot.scenario import Actuator, Obstacle, Scenario


def reference(raw: dict, name: str) -> Scenario:
    """The Scenario a bundled file describes, read straight from the YAML mapping (the file's
    documented meaning: m and deg as the keys say, defaults as the format gives them), with no
    validation: the oracle the typed reader must reproduce."""
    def pose(d):
        return transform(rpy_to_rotation(np.deg2rad(np.asarray(d.get("rpy_deg", [0, 0, 0]),
                                                                  dtype=float))),
                         np.asarray(d["xyz_m"], dtype=float))

    obstacles = []
    for k, ob in enumerate(raw.get("obstacles", [])):
        if ob["type"] == "capsule":
            obstacles.append(Obstacle(name=ob.get("name", f"obstacle{k}"), kind="capsule",
                                      p0=np.asarray(ob["p0_m"], dtype=float),
                                      p1=np.asarray(ob["p1_m"], dtype=float),
                                      radius=float(ob["radius_m"])))
        else:
            obstacles.append(Obstacle(
                name=ob.get("name", f"obstacle{k}"), kind="box",
                X_WB=transform(rpy_to_rotation(np.deg2rad(np.asarray(
                    ob.get("rpy_deg", [0, 0, 0]), dtype=float))),
                    np.asarray(ob["center_m"], dtype=float)),
                half_size=np.asarray(ob["size_m"], dtype=float) / 2))
    a = raw.get("actuator", {})
    actuator = Actuator(
        rod_length=float(a.get("rod_length_m", act.ROD_LENGTH)),
        rod_radius=float(a.get("rod_radius_m", act.ROD_RADIUS)),
        head_radius=float(a.get("head_radius_m", act.HEAD_RADIUS)),
        implant_length=float(a.get("implant_length_m", act.IMPLANT_LENGTH)),
        implant_radius=float(a.get("implant_radius_m", act.IMPLANT_RADIUS)),
        body_length=float(a.get("body_length_m", 0.0)),
        body_radius=float(a.get("body_radius_m", 0.0)))
    bounds = raw["base_bounds_m"]
    ga = raw.get("ga", {})
    box = raw["cabinet"]["box"]
    return Scenario(
        name=name, posture=raw["posture"], X_WO=pose(raw["oral"]),
        lower=np.array([bounds[k][0] for k in "xyz"], dtype=float),
        upper=np.array([bounds[k][1] for k in "xyz"], dtype=float),
        joint2_range=np.deg2rad(np.asarray(raw["cabinet"]["joint2_range_deg"], dtype=float)),
        X_BC=transform(np.eye(3), np.asarray(box["center_m"], dtype=float)),
        cabinet_half=np.asarray(box["size_m"], dtype=float) / 2,
        obstacles=tuple(obstacles), actuator=actuator, X_FT=act.X_FT(actuator.rod_length),
        eps=np.deg2rad(float(raw["joint_error_deg"])),
        feed_length=float(raw["feed_length_m"]), feed_samples=int(raw.get("feed_samples", 11)),
        clearance=float(raw.get("clearance_m", 0.005)),
        max_joint_step=np.deg2rad(float(raw.get("max_joint_step_deg", 20.0))),
        limits=str(raw.get("joint_limits_deg", "175")),
        joint_headroom=np.deg2rad(float(raw.get("joint_headroom_deg", 10.0))),
        head_translation=float(raw.get("head_motion", {}).get("translation_mm", 5.0)) * 1e-3,
        head_rotation=np.deg2rad(float(raw.get("head_motion", {}).get("rotation_deg", 1.0))),
        pop=int(ga.get("pop", 500)), gen=int(ga.get("gen", 500)), seed=int(raw.get("seed", 0)),
        patience=ga.get("patience", 20), hv_tol=float(ga.get("hv_tol", 1e-3)),
        percentile_samples=int(raw.get("percentile_samples", 2000)))


def assert_identical(a, b, where="scenario"):
    """Same type and value in every field, arrays bit for bit (dtype and shape too)."""
    assert type(a) is type(b), where
    if dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            assert_identical(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_identical(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b), where
    else:
        assert a == b, (where, a, b)


@pytest.mark.parametrize("name", moprp.BUNDLED)
def test_bundled_scenarios_read_to_exactly_what_the_file_says(name):
    raw = yaml.safe_load(moprp.scenario_path(name).read_text())
    sc = moprp.load_scenario(name)
    assert_identical(sc, reference(raw, name))
    assert len(sc.obstacles) >= 5 and {o.kind for o in sc.obstacles} == {"capsule", "box"}
    # X_FT given (the plant's TCP) replaces the actuator's, nothing else
    X_FT = act.X_FT()
    assert_identical(moprp.load_scenario(name, X_FT=X_FT),
                     dataclasses.replace(reference(raw, name), X_FT=X_FT))


def test_the_comparison_sees_a_difference():
    raw = yaml.safe_load(moprp.scenario_path("lying").read_text())
    raw["obstacles"][1]["radius_m"] += 1e-12
    with pytest.raises(AssertionError, match=r"obstacles\[1\]\.radius"):
        assert_identical(moprp.load_scenario("lying"), reference(raw, "lying"))


def _raw():
    return yaml.safe_load(moprp.scenario_path("lying").read_text())


def test_defaults_and_patience_off():
    d = _raw()
    for key in ("feed_samples", "clearance_m", "max_joint_step_deg", "joint_limits_deg",
                "percentile_samples", "seed", "actuator", "ga"):
        del d[key]
    d["name"] = None
    sc = moprp.scenario_from_dict(d, source="models/room.yaml")
    assert (sc.name, sc.feed_samples, sc.clearance, sc.limits, sc.pop, sc.gen, sc.patience,
            sc.hv_tol, sc.seed, sc.percentile_samples) == ("room", 11, 0.005, "175", 500, 500,
                                                           20, 1e-3, 0, 2000)
    assert sc.max_joint_step == np.deg2rad(20.0) and sc.actuator == Actuator()
    d["ga"] = {"patience": None}
    assert moprp.scenario_from_dict(d).patience is None  # null: no stagnation stop
    d["joint_limits_deg"] = 360  # YAML reads the bare number; it names the same variant
    assert moprp.scenario_from_dict(d).limits == "360"


@pytest.mark.parametrize(("edit", "field"), [
    ({"obstacles": [{"name": "x", "type": "cone"}]}, r"obstacles\[0\]\.type: expected capsule "
                                                     "or box, got 'cone'"),
    ({"obstacles": [{"type": "box", "center_m": [0, 0, 0], "size_m": [1, 0, 1]}]},
     r"obstacles\[0\]\.size_m: expected positive sizes"),
    ({"obstacles": [{"type": "capsule", "p0_m": [0, 0, 0], "p1_m": [0, 0, 1]}]},
     r"obstacles\[0\]\.radius_m: missing"),
    ({"feed_samples": 1}, "feed_samples: expected a number >= 2"),
    ({"joint_limits_deg": "180"}, "joint_limits_deg: expected one of 175, 360"),
    ({"oral": {"xyz": [0, 0, 1]}}, r"oral\.xyz: unknown key"),
    ({"cabinet": {"joint2_range_deg": [-90, 90]}}, r"cabinet\.box: missing"),
    ({"schema_version": 2}, "schema_version: expected 1, got 2"),
])
def test_schema_rules_name_the_field(edit, field):
    d = {**_raw(), **edit}
    with pytest.raises(InputError, match=field):
        moprp.scenario_from_dict(d)
