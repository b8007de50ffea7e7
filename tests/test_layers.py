"""Imports run downward only (DESIGN.md section 2): models <- systems <- diagrams <- analyses, and
inside analyses: commands -> pipeline -> cores; figures and the report are used by commands and
``plan``, never the reverse. Every module's imports are read with ast (lazy ones inside functions
included), so a new module is checked without being listed here."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LAYERS = {"models": 0, "systems": 1, "diagrams": 2, "analyses": 3}
# Known exceptions, each with the issue that removes it. Keep this list short and dated.
ALLOWED = {
    # issue 11: the one MOPRP search moves initial_population out of the robot command
    ("analyses.pipeline", "analyses.robot_place"),
}


def modules() -> dict[str, Path]:
    """Dotted names below implantplan (``analyses.figures.plan``) -> file."""
    out = {}
    for package in LAYERS:
        for path in sorted((ROOT / package).rglob("*.py")):
            rel = path.relative_to(ROOT).with_suffix("")
            parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
            out[".".join(parts)] = path
    return out


def imported(path: Path) -> set[str]:
    """implantplan modules a file imports (``from implantplan.x import y`` gives x and x.y)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
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


def is_command(name: str) -> bool:
    """A command module: reachable from the CLI (``register``) or run as a program (``main``,
    benchmarks)."""
    if not name.startswith("analyses.") or name.startswith("analyses.figures"):
        return False
    if name.split(".")[-1].startswith("bench_"):
        return True
    tree = ast.parse(MODULES[name].read_text())
    return any(isinstance(n, ast.FunctionDef) and n.name in ("register", "main")
               for n in tree.body)


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


EDGES = sorted({(m, t) for m, p in MODULES.items() for t in filter(None, map(resolve, imported(p)))
                if t != m})


def test_the_walk_sees_the_tree():
    # the parser finds the modules and edges we know exist (a broken walk would pass vacuously)
    assert {"systems.frames", "analyses.pipeline", "analyses.figures.plan"} <= set(MODULES)
    assert ("analyses.plan", "analyses.pipeline") in EDGES
    assert ("diagrams.teleop", "systems.actuator") in EDGES
    assert {"analyses.plan", "analyses.capmap", "analyses.cli", "analyses.bench_fpsm"} <= {
        m for m in MODULES if is_command(m)}
    assert not is_command("analyses.pipeline") and not is_command("analyses.report")


def test_packages_import_downward():
    upward = [(s, d) for s, d in EDGES if LAYERS[d.split(".")[0]] > LAYERS[s.split(".")[0]]]
    assert upward == []


def test_pipeline_cores_figures_and_report_never_import_commands():
    bad = [(s, d) for s, d in EDGES
           if s.startswith("analyses.") and not is_command(s) and is_command(d)
           and (s, d) not in ALLOWED]
    assert bad == []


def test_allowed_exceptions_still_exist():
    # an exception that is gone must leave the list (so it cannot hide a new one)
    assert ALLOWED <= set(EDGES)
