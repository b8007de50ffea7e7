"""The README and docs/ tell the truth.

- The README is a short front door (under 200 lines) and its demo transcript is what the demo
  prints today (made by ``python -m implantplan.analyses.readme_transcript``, never typed).
- Every command in a fenced ``bash`` block of README.md or docs/*.md parses with the real
  parser (``implantplan ...``) or names a module that exists (``python -m ...``).
- Every such command that writes under ``out/`` runs, in a fresh folder holding a copy of
  ``models/``, after the earlier commands that write the ``out/`` files it reads, and exits 0
  (or the code its line documents, ``# exits N: why``) leaving the files it names. Commands of
  seconds run by default (grouped into chains of commands that need each other's files);
  commands of minutes are marked ``sweep`` and the paper-scale runs ``slow`` (:data:`SWEEP`,
  :data:`SLOW`); a studio command serves until it prints its address and is then interrupted;
  the cluster block starts its own Dask scheduler and workers on 127.0.0.1. ``implantplan
  demo`` is run once per session by ``demo_run`` (the transcript test).
- docs/commands.md lists every command and exactly its options (compared with the parser),
  every repository path and module the docs name exists, every link and anchor resolves, and no
  text cites an issue number.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import importlib.util
import io
import queue
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from implantplan.analyses.cli import build_parser, main
from implantplan.analyses.readme_transcript import normalized, transcript_in

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
DOCS = [README, *sorted((ROOT / "docs").glob("*.md"))]
OUTPUT_FLAGS = ("--out", "--png", "--html", "--plots", "--meshcat-html")
BIN = Path(sys.executable).parent

# Commands of minutes (marked sweep) and paper-scale runs (marked slow), by a piece of their text.
SWEEP = {
    "implantplan plan models/cases/default.yaml --out out/default": "the whole default case",
    "implantplan batch --cohort out/cohort/cohort.yaml": "plans two cases",
    "implantplan phantom --out out/phantom --voxel-mm 0.4": "a 34 M-voxel CT series, 45 s",
    "implantplan plan out/phantom/case.yaml": "plans the phantom's CBCT, 2-3 min",
    "implantplan analyze head-motion --runs 2": "plans the default case, then the startles",
    "implantplan analyze accuracy --runs 2": "plans the default case, then about 60 runs",
    "implantplan analyze moprp-fidelity --scenario lying": "25 draws of 20 random layouts",
    "implantplan simulate feeding --scenario lying --runs 10": "ten feeds",
    "--head-motion startle --out out/feed-head": "two feeds with the tracker and guard",
    "implantplan simulate circle": "two circles with joint error",
    "implantplan analyze layouts": "feeds and circles on every layout",
    "--out out/cap-pedicle": "builds the robot file's 5 cm map first",
    "implantplan studio models/cases/default.yaml": "plans the default case, then serves",
    "--scheduler tcp://HOST:8786": "a Dask cluster of its own",
}
SLOW = {
    "implantplan analyze head-motion --runs 50": "50 runs per profile and site: 5-20 min",
    "implantplan analyze accuracy --runs 200": "200 runs per row and site: 20-40 min",
    "implantplan analyze moprp-fidelity --scenario sitting": "the lying study's code, 1.5-2 min",
    "implantplan analyze head-motion --turn-sweep": "72 head turns: 15-30 min (the sweep test "
    "test_head_turn runs the same grid)",
}
# Commands that write under out/ but are not run here, and why.
NOT_RUN = {
    "--csv out/implantplan-demo/recordings/": "replays a recording a person makes in the studio; "
    "tests/analyses/test_studio.py records one and replays it with the same command",
}


@dataclass(frozen=True)
class Command:
    doc: str  # path relative to the repository
    line: int
    block: int  # index of its fenced block in the doc
    argv: tuple[str, ...]
    exit: int = 0  # the exit code its line documents ("# exits N: why"), else 0

    @property
    def text(self) -> str:
        return shlex.join((Path(self.argv[0]).name, *self.argv[1:]))

    @property
    def program(self) -> str:
        return Path(self.argv[0]).name

    @property
    def where(self) -> str:
        return f"{self.doc}:{self.line}: {self.text}"

    @property
    def outputs(self) -> list[str]:
        if self.program == "python" and self.argv[1:2] == ("-c",):
            return re.findall(r"'(out/[^']+)'", self.argv[2])
        return [value for flag, value in zip(self.argv, self.argv[1:], strict=False)
                if flag in OUTPUT_FLAGS and value.startswith("out/")]

    @property
    def inputs(self) -> list[str]:
        """The out/ paths it reads (given to any flag but an output flag, or positionally)."""
        outs = set(self.outputs)
        return [a for a in self.argv[1:] if a.startswith("out/") and a not in outs]

    def key(self, table: dict) -> str | None:
        hits = [k for k in table if k in self.text]
        assert len(hits) <= 1, f"{self.where} matches {hits}"
        return hits[0] if hits else None


def fenced_commands(path: Path) -> list[Command]:
    """The commands of a Markdown file's ``bash`` blocks (continuations joined, comments and
    ``&&`` chains split)."""
    text = path.read_text(encoding="utf-8")
    out = []
    for block, match in enumerate(re.finditer(r"^```bash\n(.*?)^```", text, flags=re.S | re.M)):
        first = text.count("\n", 0, match.start(1)) + 1
        lines = match.group(1).split("\n")
        i = 0
        while i < len(lines):
            start, joined = i, lines[i]
            while joined.endswith("\\"):
                i += 1
                joined = joined[:-1] + " " + lines[i]
            i += 1
            words = shlex.split(joined, comments=True)
            documented = re.search(r"#\s*exits (\d):", joined)
            while words:
                cut = words.index("&&") if "&&" in words else len(words)
                out.append(Command(str(path.relative_to(ROOT)), first + start, block,
                                   tuple(words[:cut]),
                                   int(documented.group(1)) if documented else 0))
                words = words[cut + 1:]
    return out


def all_commands() -> list[Command]:
    """Every fenced command, README first, then docs/ by name; repeats dropped."""
    seen, out = set(), []
    for doc in DOCS:
        for c in fenced_commands(doc):
            if c.text not in seen:
                seen.add(c.text)
                out.append(c)
    return out


COMMANDS = all_commands()


def _cluster_blocks() -> dict[tuple[str, int], list[Command]]:
    """Blocks that start a Dask scheduler: run as one (HOST = 127.0.0.1, a free port)."""
    blocks: dict[tuple[str, int], list[Command]] = {}
    for doc in DOCS:
        cmds = fenced_commands(doc)
        for c in cmds:
            if c.argv[:2] == ("dask", "scheduler"):
                blocks[(c.doc, c.block)] = [d for d in cmds if d.block == c.block]
    return blocks


CLUSTERS = _cluster_blocks()
IN_CLUSTER = {c.text for cmds in CLUSTERS.values() for c in cmds}


def runnable(c: Command) -> bool:
    return (c.program in ("implantplan", "python") and bool(c.outputs)
            and c.key(NOT_RUN) is None and c.text not in IN_CLUSTER)


def serves(c: Command) -> bool:
    return c.program == "implantplan" and c.argv[1:2] == ("studio",)


def mark(c: Command) -> str | None:
    return "slow" if c.key(SLOW) else "sweep" if c.key(SWEEP) else None


RUNNABLE = [c for c in COMMANDS if runnable(c)]
QUICK = [c for c in RUNNABLE if mark(c) is None and not serves(c)]
LONG = [c for c in RUNNABLE if c not in QUICK]


def producer(path: str, before: Command) -> Command | None:
    """The last runnable command before ``before`` that writes ``path`` (or a folder of it)."""
    found = None
    for c in RUNNABLE:
        if c == before:
            break
        if any(path == o or path.startswith(o.rstrip("/") + "/") for o in c.outputs):
            found = c
    return found


def prerequisites(c: Command) -> list[Command]:
    """The commands ``c`` needs run first, in document order."""
    need: set[Command] = set()
    todo = [c]
    while todo:
        for path in todo.pop().inputs:
            p = producer(path, c)
            if p is not None and p not in need:
                need.add(p)
                todo.append(p)
    return [d for d in RUNNABLE if d in need]


def chains() -> list[list[Command]]:
    """The default-run commands in groups that need each other's files, in document order."""
    group = {c: i for i, c in enumerate(QUICK)}
    for c in QUICK:
        for p in prerequisites(c):
            old, new = group[p], group[c]
            group = {d: new if g == old else g for d, g in group.items()}
    return [[c for c in QUICK if group[c] == g] for g in dict.fromkeys(group[c] for c in QUICK)]


# -- the README --------------------------------------------------------------------------------

def test_the_readme_is_a_short_front_door():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) < 200, f"README.md has {len(lines)} lines: move detail into docs/"


def test_the_readme_transcript_is_what_the_demo_prints(demo_run):
    _, printed = demo_run
    readme = transcript_in(README.read_text(encoding="utf-8"))
    assert normalized(readme) == normalized(printed), (
        "README transcript is stale: run python -m implantplan.analyses.readme_transcript")


# -- every command parses and the marks are right ------------------------------------------------

def test_every_fenced_implantplan_command_parses():
    parser = build_parser()
    bad = []
    for c in COMMANDS:
        if c.program != "implantplan":
            continue
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err):
                parser.parse_args(list(c.argv[1:]))
        except SystemExit:
            bad.append(f"{c.where}\n    {err.getvalue().strip()}")
    assert bad == []


def test_every_fenced_python_module_exists():
    modules = [(c, c.argv[c.argv.index("-m") + 1]) for c in COMMANDS
               if c.program == "python" and "-m" in c.argv]
    assert modules
    missing = [c.where for c, m in modules
               if not (m.startswith("tests.") and (ROOT / (m.replace(".", "/") + ".py")).is_file())
               and importlib.util.find_spec(m) is None]
    assert missing == []


def test_commands_write_only_under_out():
    bad = [c.where for c in COMMANDS if c.program == "implantplan"
           for flag, value in zip(c.argv, c.argv[1:], strict=False)
           if flag in OUTPUT_FLAGS and not value.startswith("out/")]
    assert bad == []
    assert len(RUNNABLE) >= 20


def test_every_mark_and_exception_names_a_command():
    for table in (SWEEP, SLOW, NOT_RUN):
        for key in table:
            assert any(key in c.text for c in COMMANDS), f"no command in the docs has {key!r}"


def test_every_out_file_a_command_reads_is_written_before_it():
    for c in RUNNABLE + [d for cmds in CLUSTERS.values() for d in cmds]:
        block = CLUSTERS.get((c.doc, c.block), [])
        earlier = block[:block.index(c)] if c in block else []
        for path in c.inputs:
            inside = any(path.startswith(o) for d in earlier for o in d.outputs)
            assert inside or producer(path, c) is not None, f"{c.where}: nothing writes {path}"
    slow_needed = [(c.where, p.where) for c in QUICK for p in prerequisites(c) if p not in QUICK]
    assert slow_needed == [], "a default-run command needs a marked one: mark it too"


# -- running them -------------------------------------------------------------------------------

def _workspace(tmp: Path) -> Path:
    """A folder to run the docs' commands in: a copy of models/ (the files some commands write
    next to models/, such as the RASSCMAP maps under ../../out/maps, land in it too)."""
    shutil.copytree(ROOT / "models", tmp / "models", ignore=shutil.ignore_patterns("__pycache__"))
    (tmp / "out").mkdir()
    return tmp


def _run(c: Command, cwd: Path, monkeypatch) -> None:
    t0 = time.perf_counter()
    if c.program == "python":
        done = subprocess.run([sys.executable, *c.argv[1:]], cwd=cwd, capture_output=True,
                              text=True, check=False)
        code, printed = done.returncode, done.stdout + done.stderr
    else:
        monkeypatch.chdir(cwd)
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
            code = main(list(c.argv[1:]))
        printed = buf.getvalue()
    assert code == c.exit, (f"{c.where} exited {code} (documented: {c.exit}):\n"
                            f"{printed[-3000:]}")
    missing = [o for o in c.outputs if not (cwd / o).exists()]
    assert missing == [], f"{c.where} did not write {missing}"
    print(f"{time.perf_counter() - t0:6.1f} s  {c.text}")


def _serve(c: Command, cwd: Path) -> None:
    """Run a studio command until it serves (its address and keys printed), then interrupt it as
    Ctrl-C does: it closes and exits 0."""
    proc = subprocess.Popen([str(BIN / "implantplan"), *c.argv[1:]], cwd=cwd, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(x) for x in proc.stdout], daemon=True).start()
    printed, deadline = [], time.monotonic() + 900
    try:
        while not any(x.startswith("keys: ") for x in printed):
            assert proc.poll() is None or not lines.empty(), f"{c.where} ended:\n{''.join(printed)}"
            assert time.monotonic() < deadline, f"{c.where} did not serve:\n{''.join(printed)}"
            with contextlib.suppress(queue.Empty):
                printed.append(lines.get(timeout=1))
        time.sleep(2.0)  # the keys line comes just before the loop that Ctrl-C closes
        proc.send_signal(signal.SIGINT)
        try:
            code = proc.wait(timeout=120)
        except subprocess.TimeoutExpired:  # where it is stuck (the CLI dumps its stacks on USR1)
            proc.send_signal(signal.SIGUSR1)
            time.sleep(2.0)
            while not lines.empty():
                printed.append(lines.get())
            code = None
        assert code == 0, f"{c.where} (exit {code}):\n{''.join(printed)}"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    missing = [o for o in c.outputs if not (cwd / o).exists()]
    assert missing == [], f"{c.where} did not write {missing}"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run_cluster(cmds: list[Command], cwd: Path, monkeypatch) -> None:
    port = str(_free_port())
    local = [Command(c.doc, c.line, c.block, tuple(
        a.replace("HOST", "127.0.0.1").replace("8786", port) for a in c.argv), c.exit)
             for c in cmds]
    background = []
    try:
        for c in local:
            if c.program == "dask":
                background.append(subprocess.Popen([str(BIN / "dask"), *c.argv[1:]], cwd=cwd,
                                                   stdout=subprocess.DEVNULL,
                                                   stderr=subprocess.DEVNULL))
                if c.argv[1] == "scheduler":
                    _wait_for_port(int(port))
            else:
                _run(c, cwd, monkeypatch)
    finally:
        for proc in reversed(background):
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _wait_for_port(port: int, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.2)
    raise AssertionError(f"no Dask scheduler on port {port} after {timeout:g} s")


@pytest.mark.parametrize("chain", chains(), ids=lambda chain: chain[-1].text[:60])
def test_docs_commands_run(chain, tmp_path, monkeypatch):
    cwd = _workspace(tmp_path)
    for c in chain:
        _run(c, cwd, monkeypatch)


def _long_params():
    for c in LONG:
        marks = [getattr(pytest.mark, mark(c))] if mark(c) else []
        yield pytest.param(c, marks=marks, id=c.text[:60])


@pytest.mark.parametrize("command", list(_long_params()))
def test_long_docs_command_runs(command, tmp_path, monkeypatch):
    cwd = _workspace(tmp_path)
    for c in prerequisites(command):
        _run(c, cwd, monkeypatch)
    if serves(command):
        _serve(command, cwd)
    else:
        _run(command, cwd, monkeypatch)


@pytest.mark.sweep
@pytest.mark.parametrize("key", list(CLUSTERS), ids=lambda key: f"{key[0]}-block{key[1]}")
def test_the_cluster_recipe_runs(key, tmp_path, monkeypatch):
    cmds = CLUSTERS[key]
    cwd = _workspace(tmp_path)
    first = cmds[0]
    for c in prerequisites(first):
        _run(c, cwd, monkeypatch)
    _run_cluster(cmds, cwd, monkeypatch)


def test_the_marked_commands_are_the_ones_listed():
    """What runs by default and what is marked, for the record (shown with -s)."""
    for c in RUNNABLE:
        print(f"{mark(c) or 'default':8s} {c.where}")
    for cmds in CLUSTERS.values():
        print(f"{'sweep':8s} cluster block at {cmds[0].doc}:{cmds[0].line}")
    assert QUICK and LONG


# -- the reference and the links ----------------------------------------------------------------

def _leaves(parser: argparse.ArgumentParser, prefix: str):
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield prefix, parser
    for a in subs:
        for name, sub in a.choices.items():
            yield from _leaves(sub, f"{prefix} {name}")


def _sections(text: str) -> dict[str, str]:
    """``### `implantplan X Y``` heading -> the text below it up to the next heading."""
    parts = re.split(r"^#{1,3} ", text, flags=re.M)
    out = {}
    for part in parts:
        head, _, body = part.partition("\n")
        m = re.fullmatch(r"`(implantplan [a-z -]+)`", head.strip())
        if m:
            out[m.group(1)] = body
    return out


def test_the_command_reference_lists_every_command_and_exactly_its_options():
    sections = _sections((ROOT / "docs" / "commands.md").read_text(encoding="utf-8"))
    leaves = dict(_leaves(build_parser(), "implantplan"))
    assert sorted(sections) == sorted(leaves)
    for name, parser in leaves.items():
        documented = set(re.findall(r"^\| `(--[a-z0-9-]+|[A-Z]+)[ `]", sections[name], re.M))
        options = {max(a.option_strings, key=len) if a.option_strings
                   else (a.metavar or a.dest).upper()
                   for a in parser._actions if not isinstance(a, argparse._HelpAction)}
        assert documented == options, f"{name}: docs {sorted(documented - options)}, " \
                                      f"parser {sorted(options - documented)}"


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_links_anchors_and_named_paths_exist():
    anchors = {doc: {_slug(h) for h in re.findall(r"^#+ (.*)$", doc.read_text(), re.M)}
               for doc in DOCS}
    bad = []
    for doc in DOCS:
        text = doc.read_text(encoding="utf-8")
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if target.startswith("http"):
                continue
            file, _, anchor = target.partition("#")
            path = (doc.parent / file).resolve() if file else doc
            if not path.exists():
                bad.append(f"{doc.name}: link {target}")
            elif anchor and anchor not in anchors.get(path, set()):
                bad.append(f"{doc.name}: anchor {target}")
        for name in re.findall(r"`((?:systems|analyses|diagrams|models|tests|docs)/[\w./-]*)`",
                               text):
            if not (ROOT / name).exists():
                bad.append(f"{doc.name}: path {name}")
        for dotted in re.findall(r"`((?:implantplan\.)?(?:systems|analyses|diagrams)\.[\w.]+)`",
                                 text):
            if not _resolves(dotted if dotted.startswith("implantplan.")
                             else "implantplan." + dotted):
                bad.append(f"{doc.name}: name {dotted}")
    assert bad == []


def _resolves(dotted: str) -> bool:
    parts = dotted.split(".")
    for i in range(len(parts), 1, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def test_no_text_cites_an_issue_number():
    bad = [f"{doc.name}: {m}" for doc in DOCS
           for m in re.findall(r".{0,30}\bissues? #?\d+.{0,30}", doc.read_text(), re.I)]
    assert bad == []
