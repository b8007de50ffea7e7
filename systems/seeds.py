"""Random streams: one ``numpy.random.SeedSequence`` per run, spawned per stage and site.

A run's root seed (the case's ``seed``, a scenario's ``seed`` or a study's ``--seed``) is the only
number a user gives. Every random stream below it is the child of ``SeedSequence(root)`` at a
fixed path of spawn keys (``SeedSequence(root).spawn(n)[i].spawn(m)[j]`` for the path (i, j)),
so streams never overlap the way ``seed + k`` offsets of neighbouring runs do, and each stream
is reproducible on its own whichever others ran.
"""

from __future__ import annotations

import numpy as np

# The plan's stages in the order of its progress lines: the first spawn key below a case's root.
STAGES = ("fpsm", "placement", "robot", "capability", "feeding")
FPSM, PLACEMENT, ROBOT, CAPABILITY, FEEDING = range(len(STAGES))


def sequence(root: int, *path: int) -> np.random.SeedSequence:
    """The stream at ``path`` below ``root`` (no path: the root itself)."""
    return np.random.SeedSequence(int(root), spawn_key=tuple(int(k) for k in path))


def seed(root: int, *path: int) -> int:
    """The stream at ``path`` as a 32-bit integer seed, for cores that take an int."""
    return int(sequence(root, *path).generate_state(1)[0])


def rng(root: int, *path: int) -> np.random.Generator:
    """A generator on the stream at ``path``."""
    return np.random.default_rng(sequence(root, *path))
