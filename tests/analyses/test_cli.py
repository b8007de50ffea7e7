"""The ``implantplan`` entry point: lazy command loading, help text on every option, OS errors."""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys

import pytest

from implantplan.analyses.cli import COMMANDS, build_parser, main


def _walk(parser: argparse.ArgumentParser, path: str):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from _walk(child, f"{path} {name}")
        else:
            yield path, action


def test_help_loads_no_command_module():
    code = (
        "import sys\n"
        "from implantplan.analyses.cli import main\n"
        "try:\n    main(['--help'])\nexcept SystemExit as e:\n    assert e.code == 0\n"
        "heavy = [m for m in ('pydrake', 'numba', 'matplotlib', 'trimesh', 'scipy') "
        "if m in sys.modules]\n"
        "print('HEAVY:' + ','.join(heavy))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "HEAVY:"


def test_help_lists_every_command_in_order(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    positions = [text.index(f"    {name}") for name in COMMANDS]
    assert positions == sorted(positions)


def test_the_lazy_table_matches_what_the_modules_register():
    full = build_parser()
    sub = next(a for a in full._actions if isinstance(a, argparse._SubParsersAction))
    assert list(sub.choices) == list(COMMANDS)
    helps = {a.dest: a.help for a in sub._choices_actions}
    assert helps == {name: h for name, (_, h) in COMMANDS.items()}


def test_an_unwritable_output_is_exit_2_with_the_path(capsys):
    code = main(["fpsm", "cylinder", "--radius-mm", "50", "--z-min-mm", "0", "--z-max-mm", "100",
                 "--slices", "3", "--out", "/proc/no-such-dir/cyl.json"])
    assert code == 2
    err = capsys.readouterr().err
    assert "error" in err and "/proc/no-such-dir" in err and "Traceback" not in err


def test_every_option_has_help_text():
    missing = [
        f"{path}: {action.option_strings or action.dest}"
        for path, action in _walk(build_parser(), "implantplan")
        if action.help in (None, "") and not isinstance(action, argparse._HelpAction)
    ]
    assert missing == []


def _parsers(parser: argparse.ArgumentParser, path: list[str]):
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from _parsers(child, [*path, name])


def test_every_command_prints_its_help(capsys):
    """``--help`` of every command and subcommand formats (a bare % in a help string breaks
    argparse's formatting with a traceback) and exits 0."""
    paths = [p for p, _ in _parsers(build_parser(), [])]
    assert len(paths) > len(COMMANDS)
    for path in paths:
        with pytest.raises(SystemExit) as e:
            main([*path, "--help"])
        assert e.value.code == 0, path
        assert "usage: implantplan" in capsys.readouterr().out, path


COMMAND_HEAD = """
import argparse, os, signal, sys, time
from implantplan.analyses import cli
"""
COMMAND_TAIL = """
def parser(argv=None):
    p = argparse.ArgumentParser()
    p.set_defaults(func=work)
    return p

cli.build_parser = parser
"""


def command_script(work: str, end: str = "sys.exit(cli.main([]))\n") -> str:
    """A Python script that runs ``cli.main`` on a command whose function is ``work`` (defined
    in the text ``work``), then ``end``."""
    return COMMAND_HEAD + work + COMMAND_TAIL + end


SIGNAL_IN_A_FINALIZER = command_script("""
class Finalizer:
    def __del__(self):  # the signal's handler runs in here, where Python ignores exceptions
        os.kill(os.getpid(), getattr(signal, sys.argv[1]))
        time.sleep(0.001)

def work(args):
    Finalizer()
    start = time.monotonic()
    while time.monotonic() - start < 5.0:
        pass
    print("ran on")
    return 0
""", """t = time.monotonic()
code = cli.main([])
print(f"seconds {time.monotonic() - t:.3f}")
sys.exit(code)
""")


@pytest.mark.parametrize("name, code, line", [
    ("SIGTERM", 143, "implantplan: terminated (SIGTERM)"),
    ("SIGINT", 130, "implantplan: interrupted")])
def test_a_stop_landing_in_a_finalizer_still_stops_the_command(name, code, line):
    """A SIGTERM or Ctrl-C whose handler runs inside a finalizer (as in llvmlite's while numba
    compiles: Python prints "Exception ignored in ..." and goes on) is raised again until it
    reaches the command: its exit code at once, the one line, no traceback, the work not run to
    its end."""
    proc = subprocess.run([sys.executable, "-c", SIGNAL_IN_A_FINALIZER, name],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == code, (proc.stdout, proc.stderr)
    assert "ran on" not in proc.stdout
    assert proc.stderr.strip() == line, proc.stderr
    assert float(proc.stdout.split()[-1]) < 1.0, proc.stdout


STACKS_ON_USR1 = command_script("""
def somewhere_in_the_work():
    os.kill(os.getpid(), signal.SIGUSR1)
    time.sleep(0.2)
    return 0

def work(args):
    return somewhere_in_the_work()
""")


def test_usr1_prints_where_the_command_is_and_it_runs_on():
    """``kill -USR1`` on a command prints every thread's stack on stderr (the function it is
    in named) and the command goes on to its own exit code."""
    proc = subprocess.run([sys.executable, "-c", STACKS_ON_USR1], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "Current thread" in proc.stderr and "somewhere_in_the_work" in proc.stderr


WORKS_FIVE_SECONDS = command_script("""
def work(args):
    print("working", flush=True)
    start = time.monotonic()
    while time.monotonic() - start < 5.0:
        time.sleep(0.01)
    print("ran on")
    return 0
""")


def test_ctrl_c_stops_a_command_started_with_sigint_ignored():
    """A command started with SIGINT ignored (a shell's background job, a pytest-xdist worker's
    child: Python keeps the inherited SIG_IGN) still stops on Ctrl-C, exit 130: the studio, which
    quits on Ctrl-C, served on in that case."""
    proc = subprocess.Popen([sys.executable, "-c", WORKS_FIVE_SECONDS], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    assert proc.stdout.readline().strip() == "working"
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, (out, err)
    assert "ran on" not in out and err.strip() == "implantplan: interrupted", err
