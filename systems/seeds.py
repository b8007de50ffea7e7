"""Random streams: one ``numpy.random.SeedSequence`` per run, spawned per stage and site; and
the rounding that makes a search take the same path on every machine (:func:`rounded`).

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


# bits kept of a search's objective values (a relative step of 2^-27 = 7.5e-9)
OBJECTIVE_BITS = 27


def rounded(values, bits: int = OBJECTIVE_BITS) -> np.ndarray:
    """``values`` rounded to ``bits`` bits of mantissa (inf, nan and 0 unchanged).

    Objective values that come through BLAS and LAPACK differ in their last bits between
    machines (and between batch sizes on one machine): values equal in exact arithmetic (MOPRP's
    wrist-flip branches, a base evaluated in two generations) or a PSO's last, rounding-sized
    "improvements" would then be decided by those bits, and a search with the same seed would
    end elsewhere on another machine. Rounded, they compare the same everywhere (unless a value
    falls within ~1e-15 of a rounding step)."""
    m, e = np.frexp(np.asarray(values, dtype=float))
    return np.ldexp(np.round(m * 2.0**bits) / 2.0**bits, e)
