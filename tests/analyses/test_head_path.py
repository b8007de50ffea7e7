"""The head study's path deviation: exact distance to the still run's polyline."""

import numpy as np

from implantplan.analyses.studies.head_motion import path_distance


def test_path_distance_is_the_distance_to_the_polyline():
    rng = np.random.default_rng(3)
    path = np.cumsum(rng.normal(size=(40, 3)), axis=0)
    p = rng.normal(size=(120, 3)) * 5 + path.mean(axis=0)
    got = path_distance(p, path, chunk=64)
    # reference: dense samples of every segment (the distance can only be overestimated)
    u = np.linspace(0.0, 1.0, 2001)
    dense = (path[:-1, None] + u[None, :, None] * np.diff(path, axis=0)[:, None]).reshape(-1, 3)
    ref = np.linalg.norm(p[:, None] - dense[None], axis=2).min(axis=1)
    assert np.all(got <= ref + 1e-12)
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1).max()
    assert np.all(ref - got <= seg / 2000)
    # points on the path are at 0; a time shift along the path is not a deviation
    assert np.allclose(path_distance(path[5:], path), 0.0, atol=1e-12)
    assert np.allclose(path_distance(path[:1], path[:1]), 0.0)
