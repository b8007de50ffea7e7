"""The case's instrument is the one the placement verifies: ``instrument: actuator`` on the
default case is refused with the reason (its head does not fit), ``paper`` plans; the key's
errors name it."""

import dataclasses

import pytest

from implantplan.analyses import pipeline
from implantplan.analyses.case import case_from_dict, default_case_path, load_case
from implantplan.systems.errors import InputError, PlanningFailure
from implantplan.systems.files import read_yaml


def _case(**changes):
    path = default_case_path()
    data = read_yaml(path)
    data.update(changes)
    return case_from_dict(data, source=path)


def test_the_instrument_key():
    assert load_case(default_case_path()).instrument.kind == "paper"
    case = _case(instrument="actuator")
    inst = case.instrument_at(case.sites[0])
    assert inst.name == "actuator" and inst.head == pytest.approx(0.008)
    with pytest.raises(InputError, match="instrument.kind"):
        _case(instrument="thin")
    with pytest.raises(InputError, match="instrument.urdf"):
        _case(instrument={"urdf": "no/such.urdf"})
    with pytest.raises(InputError, match="instrument.colour"):
        _case(instrument={"kind": "paper", "colour": "red"})
    urdf = "package://implantplan/tools/implanting_actuator.urdf"
    own = _case(instrument={"urdf": urdf})
    assert own.instrument_at(own.sites[0]).shapes == inst.shapes


@pytest.mark.sweep
def test_the_actuator_is_refused_on_the_default_case_with_its_reason():
    case = _case(instrument="actuator")
    fit = pipeline.fit_stage(case)
    with pytest.raises(PlanningFailure, match="tool's .*clearance"):
        pipeline.placement_stage(case, fit.fpsm, mesh=fit.opened)
    paper = dataclasses.replace(case, instrument=load_case(default_case_path()).instrument)
    assert all(p.valid for p in pipeline.placement_stage(paper, fit.fpsm, mesh=fit.opened))
