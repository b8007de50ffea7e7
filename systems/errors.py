"""The two kinds of failure a user sees (DESIGN.md section 3, Errors).

``InputError``: the input is wrong (a field, a file, a shape); the CLI exits 2 with the message.
``PlanningFailure``: the input is fine but no plan exists (no collision-free placement, no
reachable base); the CLI exits 3 with the reason. Both carry a message that names the field or
the reason; neither is ever shown as a traceback.
"""

from __future__ import annotations

import contextlib


class InputError(ValueError):
    """Bad user input. ``field`` names what is wrong, the message says what was expected."""

    def __init__(self, field: str, message: str):
        self.field = field
        self.message = message
        super().__init__(f"{field}: {message}")


class PlanningFailure(RuntimeError):
    """A valid request that has no acceptable answer; ``reason`` says why."""

    def __init__(self, reason: str, *, result: dict | None = None):
        self.reason = reason
        self.result = result
        super().__init__(reason)


@contextlib.contextmanager
def fields_renamed(fields: dict[str, str], texts: dict[str, str] | None = None):
    """Re-raise an InputError raised inside the block with ``fields[field]`` for its field and
    each ``texts`` key replaced by its value in its message: a core's own names (``voxel``,
    ``z_range``) become what the user typed (``--voxel-mm``, ``fpsm.z_range_mm``)."""
    try:
        yield
    except InputError as exc:
        message = exc.message
        for old, new in (texts or {}).items():
            message = message.replace(old, new)
        raise InputError(fields.get(exc.field, exc.field), message) from None
