"""The ``implantplan`` command line.

Each capability module exposes ``register(subparsers)``, adding its subcommands with a ``func``
default that takes the parsed arguments and returns an exit code. Errors map to exit codes as
DESIGN.md section 3 says: ``InputError`` -> 2, ``PlanningFailure`` -> 3, both with a one-line
message and no traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from implantplan import __version__
from implantplan.systems.errors import InputError, PlanningFailure

# Each top-level command, the module that registers it (``register(subparsers)``) and its help
# line, in the order they appear in --help. Only the module of the command being run is imported,
# so ``implantplan --help`` does not load Drake, numba kernels or matplotlib.
COMMANDS: dict[str, tuple[str, str]] = {
    "plan": (
        "implantplan.analyses.plan",
        "plan a case: FPSM, placements + VF, robot base, capability, feeding sim",
    ),
    "demo": (
        "implantplan.analyses.plan",
        "plan the bundled default case (real oral mesh, two implants, lying)",
    ),
    "fpsm": (
        "implantplan.analyses.fpsm",
        "finite-parameter surrogate model of the oral cavity",
    ),
    "instrument": ("implantplan.analyses.instrument", "instrument placement (feeding target + VF)"),
    "capmap": ("implantplan.analyses.capmap", "capability maps and RASSCMAP setup planning"),
    "robot": ("implantplan.analyses.robot", "robot base placement (MOPRP, seed 001)"),
    "simulate": ("implantplan.analyses.simulate", "teleoperated-feeding simulations (seed 001)"),
    "analyze": ("implantplan.analyses.simulate", "offline analyses of layouts"),
    "studio": (
        "implantplan.analyses.studio",
        "the planning studio: live setup planning and teleoperation in the browser (Meshcat)",
    ),
    "phantom": (
        "implantplan.analyses.phantom",
        "a synthetic CBCT (DICOM CT series) of a mesh case, to plan from",
    ),
    "batch": (
        "implantplan.analyses.batch",
        "plan many cases in parallel (Dask), one folder each, with a summary",
    ),
}


def _requested_command(argv: list[str]) -> str | None:
    """The first argument that names a command (options come before it only as -h/--version)."""
    for arg in argv:
        if not arg.startswith("-"):
            return arg if arg in COMMANDS else None
    return None


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; with ``argv`` only the requested command's module is imported (the other
    commands get a help-only entry), without it every module is (complete parser, for tests)."""
    parser = argparse.ArgumentParser(
        prog="implantplan",
        description="Planning and teleoperation simulation for robot-assisted dental implant "
        "surgery (AUBO-i10, Drake).",
    )
    parser.add_argument("--version", action="version", version=f"implantplan {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    names = list(COMMANDS) if argv is None else [_requested_command(argv)]
    wanted = {COMMANDS[name][0] for name in names if name in COMMANDS}
    for name, (module, help_text) in COMMANDS.items():
        if name in sub.choices:  # registered with an earlier command of the same module
            continue
        if module in wanted:
            importlib.import_module(module).register(sub)
        else:
            sub.add_parser(name, help=help_text, add_help=False)
    return parser


def _warnings_and_up(record: logging.LogRecord) -> bool:
    return record.levelno >= logging.WARNING


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # Drake logs through Python's logging; its INFO lines ("Meshcat listening ...") are noise in
    # a command's output: warnings and errors still show. A filter, because pydrake sets the
    # logger's level when it is first imported.
    logging.getLogger("drake").addFilter(_warnings_and_up)
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    try:
        code = args.func(args)
    except InputError as exc:
        print(f"implantplan: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # an unreadable input or an unwritable output: a user error
        where = f" {exc.filename!r}" if exc.filename else ""
        print(f"implantplan: error: cannot access{where}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except PlanningFailure as exc:
        print(f"implantplan: planning failed: {exc.reason}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print("implantplan: interrupted", file=sys.stderr)
        return 130
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
