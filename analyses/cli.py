"""The ``implantplan`` command line.

Each capability module exposes ``register(subparsers)``, adding its subcommands with a ``func``
default that takes the parsed arguments and returns an exit code. Errors map to exit codes as
DESIGN.md section 3 says: ``InputError`` -> 2, ``PlanningFailure`` -> 3, both with a one-line
message and no traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from implantplan.systems.errors import InputError, PlanningFailure

# Modules that add subcommands, in the order they appear in --help.
COMMAND_MODULES: tuple[str, ...] = (
    "implantplan.analyses.plan",
    "implantplan.analyses.fpsm_commands",
    "implantplan.analyses.instrument",
    "implantplan.analyses.capmap",
    "implantplan.analyses.robot_place",
    "implantplan.analyses.simulate",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="implantplan",
        description="Planning and teleoperation simulation for robot-assisted dental implant "
        "surgery (AUBO-i10, Drake).",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        code = args.func(args)
    except InputError as exc:
        print(f"implantplan: error: {exc}", file=sys.stderr)
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
