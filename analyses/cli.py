"""The ``implantplan`` command line.

Each capability module exposes ``register(subparsers)``, adding its subcommands with a ``func``
default that takes the parsed arguments and returns an exit code. Errors map to exit codes as
DESIGN.md section 3 says (:data:`EXIT_CODES`): ``InputError`` -> 2, ``PlanningFailure`` -> 3,
both with a one-line message and no traceback; any other exception is an internal error, exit 1,
with one line naming the log file the traceback was written to (:func:`log_folder`). ``SIGTERM``
is handled as Ctrl-C (a ``KeyboardInterrupt``, so every ``finally`` cleans up: the staging
folders of analyses.out_folder), exit 143 (130 for Ctrl-C).
"""

from __future__ import annotations

import argparse
import faulthandler
import importlib
import os
import signal
import sys
import tempfile
import time
import traceback
from pathlib import Path

from implantplan import __version__
from implantplan.analyses.progress import quiet_drake
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
        "a synthetic CBCT (DICOM CT series) of a mesh case",
    ),
    "batch": (
        "implantplan.analyses.batch",
        "plan many cases in parallel (Dask), one folder each, with a summary",
    ),
}


EXIT_CODES = """exit codes: 0 every check passes; 3 a planning failure or a failed check;
2 bad input (the message names the field); 1 an internal error (one line, the traceback in a
log file); 130 interrupted (Ctrl-C), 143 terminated (SIGTERM)"""


def log_folder() -> Path:
    """Where internal errors' tracebacks go: ``$IMPLANTPLAN_LOG_DIR``, else
    ``$XDG_STATE_HOME/implantplan/logs`` (``~/.local/state/...``), else a per-user folder in the
    temp folder when the home folder cannot be written."""
    if os.environ.get("IMPLANTPLAN_LOG_DIR"):
        return Path(os.environ["IMPLANTPLAN_LOG_DIR"])
    state = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local",
                                                             "state")
    folder = Path(state) / "implantplan" / "logs"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if os.access(folder, os.W_OK):
            return folder
    except OSError:
        pass
    return Path(tempfile.gettempdir()) / f"implantplan-{os.getuid()}" / "logs"


def _write_log(argv: list[str]) -> Path | None:
    """The current exception's traceback in a new log file; None when none can be written."""
    try:
        folder = log_folder()
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"error-{time.strftime('%Y%m%dT%H%M%S')}-{os.getpid()}.log"
        path.write_text(f"implantplan {__version__}\nargv: {argv}\n\n"
                        + traceback.format_exc(), encoding="utf-8")
        return path
    except OSError:
        return None


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where Ctrl-C would be (so the same cleanup runs)."""


STOP_RETRY_S = 0.01  # a SIGTERM or Ctrl-C swallowed by a finalizer is raised again this later
_STOPPING = {"caught": False, "pending": Terminated}


def _terminate(signum, frame):
    if not _STOPPING["caught"]:
        raise Terminated()


def _raise_pending(signum, frame):
    if not _STOPPING["caught"]:
        raise _STOPPING["pending"]()


def _unraisable_hook(previous):
    """A ``sys.unraisablehook`` for a command's run: Python ignores an exception raised in a
    finalizer (``__del__``, a weakref callback: "Exception ignored in ..."), so a SIGTERM or a
    Ctrl-C that lands there (llvmlite disposes of its objects so while numba compiles) would be
    lost and the command would run on. Such a Terminated or KeyboardInterrupt is raised again
    ``STOP_RETRY_S`` later from SIGALRM, until it reaches the command; every other one goes to
    ``previous``."""

    def hook(unraisable):
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            _STOPPING["pending"] = type(unraisable.exc_value)
            signal.setitimer(signal.ITIMER_REAL, STOP_RETRY_S)
            return
        previous(unraisable)

    return hook


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
        "surgery (AUBO-i10, Drake).", epilog=EXIT_CODES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
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


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # Drake logs through Python's logging; its INFO lines ("Meshcat listening ...") are noise in
    # a command's output: warnings and errors still show, a repeated one once with its count at
    # the end. A filter, because pydrake sets the logger's level when it is first imported.
    noise = quiet_drake()
    noise.reset()
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    previous = previous_alarm = previous_int = None
    previous_hook = sys.unraisablehook
    _STOPPING["caught"] = False
    try:
        previous = signal.signal(signal.SIGTERM, _terminate)
        # Ctrl-C is KeyboardInterrupt even when the command was started with SIGINT ignored (a
        # shell's background job, a pytest-xdist worker): Python leaves an inherited SIG_IGN in
        # place, and the studio, which quits on Ctrl-C, then served on
        previous_int = signal.signal(signal.SIGINT, signal.default_int_handler)
        previous_alarm = signal.signal(signal.SIGALRM, _raise_pending)
        sys.unraisablehook = _unraisable_hook(previous_hook)
        # `kill -USR1 PID`: every thread's Python stack on stderr, the command runs on (where a
        # long or stuck command is, without a debugger)
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    except ValueError:  # not the main thread (main() called from a worker thread)
        pass
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
    except Terminated:
        _STOPPING["caught"] = True  # a retry still armed (see _unraisable_hook) does nothing
        print("implantplan: terminated (SIGTERM)", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        _STOPPING["caught"] = True
        print("implantplan: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug: one line here, the traceback in the log
        log = _write_log(argv)
        where = f"traceback in {log}" if log else "no log file could be written"
        first = str(exc).splitlines()[0] if str(exc) else ""
        print(f"implantplan: internal error: {type(exc).__name__}: {first[:200]} ({where})",
              file=sys.stderr)
        return 1
    finally:
        if previous is not None:
            signal.setitimer(signal.ITIMER_REAL, 0.0)
            faulthandler.unregister(signal.SIGUSR1)
            signal.signal(signal.SIGTERM, previous)
            if previous_int is not None:  # None: a handler set outside Python, left as ours
                signal.signal(signal.SIGINT, previous_int)
            signal.signal(signal.SIGALRM, previous_alarm)
            sys.unraisablehook = previous_hook
        for line in noise.summary():
            print(f"implantplan: {line}", file=sys.stderr)
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
