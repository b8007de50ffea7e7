"""Imports run downward only (DESIGN.md section 2): models <- systems <- diagrams <- analyses;
inside systems, the stage packages over the shared ground (ground <- fpsm <- placement, robot <-
capability, and teleop over fpsm and placement), with no cycle inside a stage; inside analyses:
commands -> pipeline -> cores; figures and the report are used by commands and ``plan``, never
the reverse; and no module imports another module's private (``_name``) name.
Every module's imports are read with ast (lazy ones inside functions
included), so a new module is checked without being listed here."""

import ast
import functools
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LAYERS = {"models": 0, "systems": 1, "diagrams": 2, "analyses": 3}
# Known exceptions, each with the issue that removes it. Keep this list short and dated.
ALLOWED: set[tuple[str, str]] = set()


def modules() -> dict[str, Path]:
    """Dotted names below implantplan (``analyses.figures.plan``) -> file."""
    out = {}
    for package in LAYERS:
        for path in sorted((ROOT / package).rglob("*.py")):
            rel = path.relative_to(ROOT).with_suffix("")
            parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
            out[".".join(parts)] = path
    return out


@functools.cache
def tree(path: Path) -> ast.Module:
    """The parsed file, once per test run (the tests below walk each file several times)."""
    return ast.parse(path.read_text(), filename=str(path))


def imported(path: Path) -> set[str]:
    """implantplan modules a file imports (``from implantplan.x import y`` gives x and x.y)."""
    names = set()
    for node in ast.walk(tree(path)):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            targets = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        for t in targets:
            if t.startswith("implantplan."):
                names.add(t[len("implantplan."):])
    return names


MODULES = modules()


@functools.cache
def is_command(name: str) -> bool:
    """A command module: reachable from the CLI (``register``) or run as a program (``main``,
    benchmarks)."""
    if not name.startswith("analyses.") or name.startswith("analyses.figures"):
        return False
    if name.split(".")[-1].startswith("bench_"):
        return True
    return any(isinstance(n, ast.FunctionDef) and n.name in ("register", "main")
               for n in tree(MODULES[name]).body)


def resolve(target: str) -> str | None:
    """The module an imported dotted name refers to (``systems.frames.invert`` ->
    ``systems.frames``), or None outside the four packages."""
    parts = target.split(".")
    while parts:
        name = ".".join(parts)
        if name in MODULES:
            return name
        parts.pop()
    return None


@functools.cache
def edges() -> list[tuple[str, str]]:
    """Every (module, module it imports) of the four packages, parsed once on first use (not
    at collection: both test workers collect this file)."""
    return sorted({(m, t) for m, p in MODULES.items()
                   for t in filter(None, map(resolve, imported(p))) if t != m})


def test_the_walk_sees_the_tree():
    # the parser finds the modules and edges we know exist (a broken walk would pass vacuously)
    assert {"systems.frames", "analyses.pipeline", "analyses.figures.plan"} <= set(MODULES)
    assert ("analyses.plan", "analyses.pipeline") in edges()
    assert ("diagrams.teleop", "systems.actuator") in edges()
    assert ("systems.placement.planner", "systems.fpsm.model") in edges()
    assert {"analyses.plan", "analyses.capmap", "analyses.cli", "analyses.bench_fpsm"} <= {
        m for m in MODULES if is_command(m)}
    assert not is_command("analyses.pipeline") and not is_command("analyses.report")


def test_packages_import_downward():
    upward = [(s, d) for s, d in edges() if LAYERS[d.split(".")[0]] > LAYERS[s.split(".")[0]]]
    assert upward == []


def test_pipeline_cores_figures_and_report_never_import_commands():
    bad = [(s, d) for s, d in edges()
           if s.startswith("analyses.") and not is_command(s) and is_command(d)
           and (s, d) not in ALLOWED]
    assert bad == []


def test_allowed_exceptions_still_exist():
    # an exception that is gone must leave the list (so it cannot hide a new one)
    assert ALLOWED <= set(edges())


# The stages inside systems/ and what each may import besides itself (the shared ground is the
# modules directly in systems/). A stage not listed here fails the walk test below.
STAGES = {
    "ground": set(),
    "fpsm": {"ground"},
    "anatomy": {"ground", "fpsm"},
    "placement": {"ground", "fpsm"},
    "robot": {"ground"},
    "capability": {"ground", "robot"},
    "teleop": {"ground", "fpsm", "placement"},
}


def stage(name: str) -> str:
    """The stage of a systems module (``systems.fpsm.model`` -> fpsm, ``systems.frames`` ->
    ground)."""
    parts = name.split(".")
    return parts[1] if len(parts) > 2 else "ground"


SYSTEMS = [m for m in MODULES if m.startswith("systems.") and m != "systems"]


def test_every_systems_module_is_in_a_known_stage():
    assert {stage(m) for m in SYSTEMS} == set(STAGES)
    assert stage("systems.placement.planner") == "placement" and stage("systems.errors") == "ground"


def test_stages_import_only_their_floors():
    bad = [(s, d) for s, d in edges() if s in SYSTEMS and d in SYSTEMS
           and stage(d) != stage(s) and stage(d) not in STAGES[stage(s)]]
    assert bad == []


def test_no_import_cycle_inside_systems():
    graph = {m: {d for s, d in edges() if s == m and d in SYSTEMS} for m in SYSTEMS}
    done, stack, cycles = set(), [], []

    def visit(m):
        if m in stack:
            cycles.append(stack[stack.index(m):] + [m])
            return
        if m in done:
            return
        stack.append(m)
        for d in sorted(graph[m]):
            visit(d)
        stack.pop()
        done.add(m)

    for m in sorted(graph):
        visit(m)
    assert cycles == []


def private_uses(path: Path) -> list[str]:
    """Private names a file takes from implantplan modules: ``from implantplan.x import _y`` and
    ``alias._y`` where ``alias`` is an imported implantplan module (dunders are not private)."""
    parsed = tree(path)
    aliases, out = set(), []
    for node in ast.walk(parsed):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module \
                and node.module.startswith("implantplan"):
            for a in node.names:
                if a.name.startswith("_") and not a.name.startswith("__"):
                    out.append(f"{node.lineno}: {node.module}.{a.name}")
                aliases.add(a.asname or a.name)
        elif isinstance(node, ast.Import):
            aliases |= {a.asname for a in node.names
                        if a.name.startswith("implantplan") and a.asname}
    for node in ast.walk(parsed):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) \
                and node.value.id in aliases and node.attr.startswith("_") \
                and not node.attr.startswith("__"):
            out.append(f"{node.lineno}: {node.value.id}.{node.attr}")
    return out


def test_private_use_is_detected(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("from implantplan.systems.fpsm.model import _x, Fpsm\n"
                 "from implantplan.systems import frames as fr\nfr._y(1); fr.__name__\n")
    assert private_uses(f) == ["1: implantplan.systems.fpsm.model._x", "3: fr._y"]


def test_no_module_imports_another_modules_private_name():
    files = [p for p in MODULES.values()] + sorted((ROOT / "tests").rglob("*.py"))
    bad = {str(p.relative_to(ROOT)): u for p in files if (u := private_uses(p))}
    assert bad == {}
