"""Progress lines on the terminal for long runs: stage, step, elapsed time.

Written to stderr so that stdout stays machine-readable. ``quiet=True`` silences it (tests).
"""

from __future__ import annotations

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
