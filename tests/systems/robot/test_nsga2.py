"""NSGA-II, the non-dominated sort and the hypervolume (systems.robot.nsga2)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from implantplan.systems.errors import InputError
from implantplan.systems.robot import nsga2


def test_hypervolume_by_hand():
    assert nsga2.hypervolume(np.zeros((1, 3)), np.ones(3)) == pytest.approx(1.0)
    # boxes 1 x .5 x .5 and .5 x 1 x 1 overlapping in .5^3: .25 + .5 - .125
    F = np.array([[0.0, 0.5, 0.5], [0.5, 0.0, 0.0]])
    assert nsga2.hypervolume(F, np.ones(3)) == pytest.approx(0.625)
    assert nsga2.hypervolume(np.array([[0.0, 0.5], [0.5, 0.0]]), np.ones(2)) == pytest.approx(0.75)
    # points beyond the reference add nothing, dominated points add nothing
    F2 = np.vstack([F, [[2.0, 0.0, 0.0], [0.6, 0.1, 0.1]]])
    assert nsga2.hypervolume(F2, np.ones(3)) == pytest.approx(0.625)


@settings(max_examples=30, deadline=None)
@given(arrays(np.float64, (12, 3), elements=st.floats(0, 1)))
def test_hypervolume_matches_inclusion_exclusion_on_a_grid(F):
    F = np.round(F * 4) / 4  # grid points: exact count of dominated 1/4-cells
    cells = (np.stack(np.meshgrid(*[np.arange(4) / 4] * 3, indexing="ij"), -1).reshape(-1, 3)
             + 0.125)
    dom = np.any(np.all(cells[:, None, :] >= F[None], axis=-1), axis=1)
    assert nsga2.hypervolume(F, np.ones(3)) == pytest.approx(dom.sum() / 64, abs=1e-12)


@settings(max_examples=40, deadline=None)
@given(arrays(np.float64, (30, 3), elements=st.sampled_from([0.0, 1.0, 2.0, 3.0])),
       arrays(np.float64, (30,), elements=st.sampled_from([0.0, 0.0, 0.5, 1.0])))
def test_compiled_sort_matches_the_domination_matrix(F, cv):
    D = nsga2.domination_matrix(F, cv)
    rank = nsga2.non_dominated_sort(F, cv)
    # rank 0 = dominated by nobody; each point of rank r > 0 is dominated by one of rank r - 1
    # and by none of rank >= r
    for j in range(F.shape[0]):
        dominators = rank[D[:, j]]
        if rank[j] == 0:
            assert dominators.size == 0
        else:
            assert dominators.max() == rank[j] - 1
        assert np.all(dominators < rank[j])


def test_nsga2_finds_a_known_front():
    """Schaffer's problem: f = (x^2, (x - 2)^2); the Pareto set is x in [0, 2]."""

    def evaluate(X, rng):
        x = X[:, 0]
        return np.stack([x**2, (x - 2) ** 2], axis=1), np.zeros(len(x))

    r = nsga2.nsga2(evaluate, [-10.0], [10.0], pop=40, gen=60, seed=3, patience=None)
    x = r.X[r.front, 0]
    assert x.size >= 30
    assert x.min() >= -1e-3 and x.max() <= 2 + 1e-3
    assert x.max() - x.min() > 1.8
    r2 = nsga2.nsga2(evaluate, [-10.0], [10.0], pop=40, gen=60, seed=3, patience=None)
    np.testing.assert_array_equal(r.X, r2.X)


def test_nsga2_rejects_bad_bounds():
    with pytest.raises(InputError):
        nsga2.nsga2(lambda X, rng: (X, np.zeros(len(X))), [1.0], [0.0], pop=8, gen=2, seed=0)
