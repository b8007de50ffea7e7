"""Progress lines on the terminal for long runs: stage, step, elapsed time.

Written to stderr so that stdout stays machine-readable. ``quiet=True`` silences it (tests).
"""

from __future__ import annotations

import logging
import re
import sys
import time


class Progress:
    """Prints ``[  12.3 s] stage: message`` lines; ``step(i, n)`` throttles to ~2 lines/s."""

    def __init__(self, stage: str, *, quiet: bool = False, stream=None):
        self.stage = stage
        self.quiet = quiet
        self.stream = stream if stream is not None else sys.stderr
        self.t0 = time.perf_counter()
        self._last = -1.0

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def say(self, message: str) -> None:
        if not self.quiet:
            print(f"[{self.elapsed:7.1f} s] {self.stage}: {message}", file=self.stream, flush=True)

    def step(self, i: int, n: int, message: str = "") -> None:
        now = self.elapsed
        if i + 1 >= n or now - self._last >= 0.5:
            self._last = now
            self.say(f"{i + 1}/{n} {message}".rstrip())


class DrakeNoise(logging.Filter):
    """A filter on Drake's logger (``logging.getLogger("drake")``) for a command's terminal:
    INFO lines (``Meshcat listening for connections at ...``) are dropped, and a warning that
    repeats (the same text once its numbers are taken out, as Differential IK's "stuck" warnings
    in a long study) shows once; :meth:`summary` counts the repeats it held back.

    :func:`quiet_drake` installs one per process (the CLI's, and each batch worker's)."""

    def __init__(self):
        super().__init__("drake-noise")
        self.counts: dict[str, int] = {}
        self.first: dict[str, str] = {}

    def reset(self) -> None:
        """Forget the warnings seen (a new command in the same process)."""
        self.counts.clear()
        self.first.clear()

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING:
            return False
        text = record.getMessage()
        key = re.sub(r"[-+]?\d[\d.eE+-]*", "#", text)
        self.counts[key] = self.counts.get(key, 0) + 1
        self.first.setdefault(key, text)
        return self.counts[key] == 1

    def summary(self) -> list[str]:
        """One line per warning that repeated: its first text and how often it came."""
        return [f"drake warning repeated {n} times in all (shown once): {self.first[k][:120]}"
                for k, n in self.counts.items() if n > 1]


def quiet_drake() -> DrakeNoise:
    """The process's :class:`DrakeNoise` on Drake's logger (installed on the first call)."""
    logger = logging.getLogger("drake")
    for f in logger.filters:
        if isinstance(f, DrakeNoise):
            return f
    noise = DrakeNoise()
    logger.addFilter(noise)
    return noise
