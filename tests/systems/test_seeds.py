"""Random streams below a root seed: numpy's spawn tree, reproducible and distinct."""

import numpy as np

from implantplan.systems import seeds


def test_a_path_is_numpys_spawned_child():
    child = np.random.SeedSequence(7).spawn(3)[2].spawn(2)[1]
    assert seeds.sequence(7, 2, 1).generate_state(4).tolist() == child.generate_state(4).tolist()
    assert seeds.rng(7, 2, 1).random() == np.random.default_rng(child).random()


def test_streams_are_reproducible_and_distinct():
    assert seeds.seed(3, seeds.PLACEMENT, 0) == seeds.seed(3, seeds.PLACEMENT, 0)
    values = {seeds.seed(r, s, k) for r in (0, 1) for s in range(len(seeds.STAGES))
              for k in range(4)}
    assert len(values) == 2 * len(seeds.STAGES) * 4
    # the old offsets collided: case seed 0's second site and case seed 1's first site
    assert seeds.seed(0, seeds.PLACEMENT, 1) != seeds.seed(1, seeds.PLACEMENT, 0)
    assert 0 <= seeds.seed(5) < 2**32
