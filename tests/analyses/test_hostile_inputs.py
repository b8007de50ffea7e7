"""A catalogue of hostile and careless inputs to ``implantplan plan`` (DESIGN.md section 3: output
folders belong to the user, exit codes are a contract, bounded work, names are names).

Each entry runs the real command line in a child process whose address space is limited to 2 GB
(``RLIMIT_AS``, applied only in the subprocess that runs tests/analyses/hostile_harness.py, never
in this process or an xdist worker) with a 10 s alarm, and asserts: the exit code; one line on
stderr naming the field (the case's own key or the flag), no traceback; the previous plan in
``--out`` untouched; nothing written anywhere else (the inputs, the working folder, the folder
around ``--out``); no internal-error log. The entries that plan (exit 3) are marked ``sweep``
except one planning failure. Then ``kill -TERM`` of a running ``plan``, ``batch`` (in its process
and, marked ``cluster``, on a LocalCluster of 2 workers), ``capmap build`` and ``studio``: exit 143
within 2 s (:data:`EXIT_BOUND`, the one timing asserted), nothing left behind, the previous plan
intact; and ``kill -KILL`` of each followed by the next run, which removes the leftovers.
"""

from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml

from implantplan import models
from implantplan.analyses.out_folder import MARKER, STAGING, mark
from tests.analyses.cases import default_case_data

HARNESS = Path(__file__).with_name("hostile_harness.py")
AS_LIMIT = 2 * 1024**3  # bytes of address space per run
TIMEOUT = 10  # s per run unless the input is legitimately large
PREVIOUS = b'{"schema_version": 1, "kind": "plan", "note": "the previous plan"}\n'


def _limit_memory():  # runs in the child between fork and exec
    resource.setrlimit(resource.RLIMIT_AS, (AS_LIMIT, AS_LIMIT))


def small_case(**edits) -> dict:
    """The small default case without feeds, with ``edits`` (dotted keys, list indices)."""
    data = default_case_data(small=True)
    data["simulation"]["runs"] = 0
    data["safety"]["registration_samples"] = 20
    for dotted, value in edits.items():
        d, keys = data, dotted.split(".")
        for k in keys[:-1]:
            d = d[int(k)] if isinstance(d, list) else d[k]
        if isinstance(d, list):
            d[int(keys[-1])] = value
        else:
            d[keys[-1]] = value
    return data


@dataclass
class Ctx:
    """One entry's folders: ``inputs`` (case files), ``cwd`` (the run's working folder, empty),
    ``out`` (a previous plan folder, marked, inside ``outs``)."""

    root: Path
    inputs: Path
    cwd: Path
    out: Path

    def case(self, data: dict | None = None, *, text: str | None = None,
             name: str = "case.yaml") -> str:
        path = self.inputs / name
        path.write_text(text if text is not None else yaml.safe_dump(data or small_case()))
        return str(path)

    def plan(self, case: str, *flags: str, out: str | None = None) -> list[str]:
        return ["plan", case, "--out", str(self.out) if out is None else out, "--quiet",
                "--no-figures", *flags]


def _symlink(ctx: Ctx, target: Path, name: str = "link") -> Path:
    link = ctx.root / "outs" / name
    link.symlink_to(target)
    return link


def _loop(ctx: Ctx) -> Path:
    a, b = ctx.root / "outs" / "loop_a", ctx.root / "outs" / "loop_b"
    a.symlink_to(b)
    b.symlink_to(a)
    return a


def _fifo(folder: Path, name: str = "fifo") -> Path:
    path = folder / name
    os.mkfifo(path)
    return path


def _alias_bomb() -> str:
    text = yaml.safe_dump(small_case())
    lines = ['l0: &l0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    lines += [f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]" for i in range(1, 9)]
    return "\n".join(lines) + "\n" + text.replace("name: default", "name: *l8")


def _holey_scan(ctx: Ctx, share: float) -> str:
    """The bundled scan with ``share`` of its triangles deleted (seeded), as OBJ."""
    import trimesh

    mesh = trimesh.load(models.model_path("oral/oralCavityMesh.obj"), process=False,
                        force="mesh")
    keep = np.random.default_rng(0).random(len(mesh.faces)) >= share
    path = ctx.inputs / f"holey_{share:g}.obj"
    trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False).export(path)
    return str(path)


def _far_scenario(ctx: Ctx) -> str:
    data = yaml.safe_load(models.model_path("scenarios/lying.yaml").read_text())
    data["base_bounds_m"] = {"x": [3.0, 3.5], "y": [-0.7, 0.1], "z": [-0.5, 0.5]}
    path = ctx.inputs / "far.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def _user_folder(ctx: Ctx) -> str:
    folder = ctx.root / "outs" / "patient42"
    folder.mkdir()
    (folder / "consent_form.pdf").write_bytes(b"%PDF-1.4 the patient's consent")
    (folder / "scan.obj").write_text("v 0 0 0\n")
    return str(folder)


SITE0 = small_case()["sites"][0]["position_mm"]

# name -> (argv maker, exit code, what the one-line message must say); the message names the
# field (a case key, a flag) or the path as the user typed it
CATALOGUE = {
    # -- --out: the user's folders, special files, links -----------------------------------------
    "out holds the patient's files": (
        lambda c: c.plan(c.case(), out=_user_folder(c)), 2, "--out: "),
    "out is an empty text": (lambda c: c.plan(c.case(), out=""), 2,
                             "--out: expected a folder path, got an empty text"),
    "out is .": (lambda c: c.plan(c.case(), out="."), 2, "--out: expected a folder of its own"),
    "out is ..": (lambda c: c.plan(c.case(), out=".."), 2, "--out: expected a folder of its own"),
    "out is the working folder": (lambda c: c.plan(c.case(), out=str(c.cwd)), 2,
                                  "is the current folder or holds it"),
    "out is /": (lambda c: c.plan(c.case(), out="/"), 2, "--out: expected a folder of its own"),
    "out is a symlink to the plan": (lambda c: c.plan(c.case(), out=str(_symlink(c, c.out))),
                                     2, "is a symbolic link; give the folder it points to"),
    "out is a symlink loop": (lambda c: c.plan(c.case(), out=str(_loop(c))), 2,
                              "is a symbolic link loop"),
    "out is below a symlink loop": (lambda c: c.plan(c.case(), out=str(_loop(c) / "plan")), 2,
                                    "symbolic link loop"),
    "out is a broken symlink": (
        lambda c: c.plan(c.case(), out=str(_symlink(c, c.root / "nowhere"))), 2,
        "is a broken symbolic link"),
    "out is a file": (lambda c: c.plan(c.case(), out=c.case(name="notes.txt")), 2,
                      "is a file, not a folder"),
    "out is below a file": (lambda c: c.plan(c.case(), out=c.case(name="f.txt") + "/plan"), 2,
                            "is a file, not a folder"),
    "out is /dev/null": (lambda c: c.plan(c.case(), out="/dev/null"), 2, "is a device"),
    "out is a FIFO": (lambda c: c.plan(c.case(), out=str(_fifo(c.root / "outs"))), 2,
                      "is a FIFO"),
    "out cannot be written": (lambda c: c.plan(c.case(), out="/proc/1/plan"), 2,
                              "--out: cannot write in '/proc/1'"),
    # -- names that would become paths --------------------------------------------------------
    "site name escapes": (lambda c: c.plan(c.case(small_case(**{
        "sites.0.name": "../../../../ESCAPED"}))), 2, "sites[0].name: expected a name"),
    "site name makes folders": (lambda c: c.plan(c.case(small_case(**{"sites.0.name": "a/b"}))),
                                2, "sites[0].name: expected a name"),
    "site name of 300 characters": (
        lambda c: c.plan(c.case(small_case(**{"sites.1.name": "x" * 300}))), 2,
        "sites[1].name: expected a name of 1 to 64"),
    "site name is ..": (lambda c: c.plan(c.case(small_case(**{"sites.0.name": ".."}))), 2,
                        "sites[0].name"),
    "site name with a newline": (
        lambda c: c.plan(c.case(small_case(**{"sites.0.name": "36\n46"}))), 2, "sites[0].name"),
    "case name escapes": (lambda c: c.plan(c.case(small_case(name="../../x"))), 2,
                          "name: expected a name"),
    # -- counts and sizes past their bounds ---------------------------------------------------
    "fpsm samples 1e9": (lambda c: c.plan(c.case(small_case(**{"fpsm.samples": 10**9}))), 2,
                         "fpsm.samples: expected a number <= 2000"),
    "fpsm slices 100000": (lambda c: c.plan(c.case(small_case(**{"fpsm.slices": 100000}))), 2,
                           "fpsm.slices: expected a number <= 200"),
    "fpsm control points 1e6": (
        lambda c: c.plan(c.case(small_case(**{"fpsm.control_points": 10**6}))), 2,
        "fpsm.control_points"),
    "robot pop 1e9": (lambda c: c.plan(c.case(small_case(**{"robot.pop": 10**9}))), 2,
                      "robot.pop: expected a number <= 1000"),
    "robot generations 1e6": (lambda c: c.plan(c.case(small_case(**{"robot.gen": 10**6}))), 2,
                              "robot.gen"),
    "registration samples 1e9": (
        lambda c: c.plan(c.case(small_case(**{"safety.registration_samples": 10**9}))), 2,
        "safety.registration_samples: expected a number <= 100000"),
    "capability directions 1e9": (
        lambda c: c.plan(c.case(small_case(**{"capability.directions": 10**9}))), 2,
        "capability.directions"),
    "simulation runs 1e6": (lambda c: c.plan(c.case(small_case(**{"simulation.runs": 10**6}))),
                            2, "simulation.runs"),
    "--runs 1e6": (lambda c: c.plan(c.case(), "--runs", "1000000"), 2,
                   "--runs: expected a number <= 100"),
    "rod radius 1e308 mm": (
        lambda c: c.plan(c.case(small_case(**{"instrument": "paper",
                                               "sites.0.rod_radius_mm": 1e308}))), 2,
        "sites[0].rod_radius_mm: expected a number <= 20"),
    "implant length 1 km": (
        lambda c: c.plan(c.case(small_case(**{"sites.0.implant_length_mm": 1e6}))), 2,
        "sites[0].implant_length_mm: applies to instrument: paper only"),
    "a paper key on the actuator": (
        lambda c: c.plan(c.case(small_case(**{"sites.1.rod_radius_mm": 3.0}))), 2,
        "sites[1].rod_radius_mm: applies to instrument: paper only"),
    "site 1e300 mm away": (
        lambda c: c.plan(c.case(small_case(**{"sites.0.position_mm": [1e300, 0, 0]}))), 2,
        "sites[0].position_mm: expected 3 numbers within +-300"),
    "a 400-digit seed": (lambda c: c.plan(c.case(text=yaml.safe_dump(small_case()).replace(
        "seed: 0", "seed: " + "9" * 400))), 2, "seed: expected a finite number"),
    "clearance 1e308 mm": (
        lambda c: c.plan(c.case(small_case(**{"safety.clearance_mm": 1e308}))), 2,
        "safety.clearance_mm: expected a number <= 20"),
    "memory over a small budget": (lambda c: c.plan(c.case(), "--memory-budget-mb", "300"), 2,
                                   "over the memory budget of 300 MB"),
    "a large dense check over the budget": (
        lambda c: c.plan(c.case(small_case(**{"fpsm.slices": 200, "fpsm.samples": 2000})),
                         "--memory-budget-mb", "3000"), 2, "fpsm.slices/samples: the plan "
        "would need about"),
    "a negative memory budget": (lambda c: c.plan(c.case(), "--memory-budget-mb", "-5"), 2,
                                 "--memory-budget-mb: expected a positive number"),
    # -- files: YAML, special files, sizes ----------------------------------------------------
    "an alias bomb under name": (lambda c: c.plan(c.case(text=_alias_bomb())), 2,
                                 "YAML anchors and aliases are not supported"),
    "a duplicated tolerance": (lambda c: c.plan(c.case(text=yaml.safe_dump(small_case()).replace(
        "tolerance_mm: 1.0", "tolerance_mm: 1.0\n  tolerance_mm: 50"))), 2,
        "site_check.tolerance_mm: duplicate key"),
    "a 2 MB case file": (lambda c: c.plan(c.case(text=yaml.safe_dump(small_case())
                                                 + "# " + "x" * 2_000_000 + "\n")), 2,
                         "expected at most 1 MB"),
    "case is /dev/zero": (lambda c: c.plan("/dev/zero"), 2, "case: '/dev/zero' is a device"),
    "case is a FIFO": (lambda c: c.plan(str(_fifo(c.inputs))), 2, "is a FIFO (named pipe)"),
    "case is a symlink loop": (lambda c: c.plan(str(_loop(c))), 2,
                               "case: '%s' is a symbolic link loop"),
    "mesh is /dev/zero": (lambda c: c.plan(c.case(small_case(**{"mesh.path": "/dev/zero"}))), 2,
                          "mesh.path: '/dev/zero' is a device"),
    "mesh is a FIFO": (lambda c: c.plan(c.case(small_case(**{
        "mesh.path": str(_fifo(c.inputs, "scan.obj"))}))), 2, "mesh.path: "),
    # -- what a clinician would stop at -------------------------------------------------------
    "two sites at the same place": (
        lambda c: c.plan(c.case(small_case(**{"sites.1.position_mm": SITE0}))), 2,
        "sites[1].position_mm: site '46' lies 0.00 mm from site '36'; expected at least 5.5"),
    "sites 4 mm apart": (lambda c: c.plan(c.case(small_case(**{
        "sites.1.position_mm": [SITE0[0] - 4.0, SITE0[1], SITE0[2]]}))), 2,
        "sites[1].position_mm"),
    "no clearance margin": (lambda c: c.plan(c.case(small_case(**{"safety.clearance_mm": 0}))),
                            2, "safety.clearance_mm: 0 mm is below 0.5 mm"),
    "margin 0.3 mm": (lambda c: c.plan(c.case(small_case(**{"safety.clearance_mm": 0.3}))), 2,
                      "--accept-small-margin"),
    "a scan with 30% of its faces missing": (
        lambda c: c.plan(c.case(small_case(**{"mesh.path": _holey_scan(c, 0.3)}))), 2,
        "mesh.close_open_cuts: the scan has"),
    "an open scan not closed": (
        lambda c: c.plan(c.case(small_case(**{"mesh.close_open_cuts": False}))), 2,
        "Set mesh.cap_radius_mm to cap those rays or mesh.close_open_cuts: true"),
    # -- the other commands that write folders and maps ---------------------------------------
    "demo into the patient's folder": (lambda c: ["demo", "--out", _user_folder(c), "--quiet"],
                                       2, "--out: "),
    "batch into the patient's folder": (
        lambda c: ["batch", c.case(), "--out", _user_folder(c), "--quiet"], 2,
        "holds files implantplan did not write"),
    "batch into a symlink loop": (lambda c: ["batch", c.case(), "--out", str(_loop(c))], 2,
                                  "--out: "),
    "capmap voxels of 1 mm": (lambda c: ["capmap", "build", "--voxel-mm", "1", "--out",
                                         str(c.root / "outs" / "map.h5")], 2,
                              "--voxel-mm: expected a voxel edge in [5 mm, 500 mm]"),
    "capmap 1e6 directions": (lambda c: ["capmap", "build", "--directions", "1000000", "--out",
                                         str(c.root / "outs" / "map.h5")], 2, "--directions: "),
    "head-motion study into the patient's folder": (
        lambda c: ["analyze", "head-motion", "--out", _user_folder(c), "--quiet"], 2,
        "give a new or empty folder"),
    "an FPSM that does not reach the site": (
        lambda c: c.plan(c.case(small_case(**{"fpsm.margin_mm": 8.0}))), 2,
        "outside the FPSM (the placement allows 5.000 mm) although it lies on the scanned "
        "tissue (within site_check.tolerance_mm 1 mm)"),
    "the memory budget variable is not a number": (
        lambda c: c.plan(c.case()), 2, "IMPLANTPLAN_MEMORY_BUDGET_MB: expected a positive"),
}
ENV = {"the memory budget variable is not a number": {"IMPLANTPLAN_MEMORY_BUDGET_MB": "lots"}}

# entries that plan (each a few seconds on the small case, legitimately more than 10 s on a busy
# machine): exit 3; under the sweep mark
PLANNING_TIMEOUT = 90
PLANNING = {
    "no base reaches the sites": (
        lambda c: c.plan(c.case(small_case(**{"robot.scenario": _far_scenario(c)}))), 3,
        "planning failed: no base position in the bounds"),
}
SWEEP = {
    "a failed check exits 3 (30% of the scan missing, accepted)": (
        lambda c: c.plan(c.case(small_case(**{"mesh.path": _holey_scan(c, 0.3)})),
                         "--accept-repairs"), 3, "(failed: "),
}


def _snapshot(root: Path, skip: Path) -> dict:
    """Every path under ``root`` but ``skip``'s contents -> (size, mtime) for files and links
    (not followed), None for folders (a staging folder made and removed again changes its
    folder's mtime, not its entries)."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        if Path(dirpath) == skip:
            dirnames[:] = []
            continue
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            st = p.lstat()
            out[str(p.relative_to(root))] = (None if p.is_dir() and not p.is_symlink()
                                             else (st.st_size, st.st_mtime_ns))
    return out


def _prepare(base: Path, name: str, entries: dict) -> tuple[Ctx, dict]:
    root = base / name.replace(" ", "_").replace("/", "_").replace(".", "dot")
    ctx = Ctx(root, root / "inputs", root / "cwd", root / "outs" / "plan")
    for folder in (ctx.inputs, ctx.cwd, ctx.out):
        folder.mkdir(parents=True)
    mark(ctx.out, "plan")
    (ctx.out / "plan.json").write_bytes(PREVIOUS)
    make, code, message = entries[name]
    argv = make(ctx)
    message = message.replace("%s", argv[1])
    run = {"id": name, "argv": argv, "cwd": str(ctx.cwd), "timeout": TIMEOUT,
           "env": ENV.get(name, {})}
    return ctx, {"run": run, "code": code, "message": message,
                 "before": _snapshot(root, ctx.out)}


def _run_harness(base: Path, entries: dict, logs: Path, timeouts: dict | None = None) -> dict:
    """Every entry in one harness subprocess (limited to :data:`AS_LIMIT`), each run in its own
    fork with its timeout (``timeouts[name]``, else :data:`TIMEOUT`)."""
    timeouts = timeouts or {}
    prepared = {name: _prepare(base, name, entries) for name in entries}
    (base / "capture").mkdir()
    runs = [p[1]["run"] | {"timeout": timeouts.get(name, TIMEOUT),
                           "capture": str(base / "capture" / str(i))}
            for i, (name, p) in enumerate(prepared.items())]
    runs_path, results_path = base / "runs.json", base / "results.json"
    runs_path.write_text(json.dumps(runs))
    env = dict(os.environ, IMPLANTPLAN_LOG_DIR=str(logs))
    env.pop("IMPLANTPLAN_MEMORY_BUDGET_MB", None)
    subprocess.run([sys.executable, str(HARNESS), str(runs_path), str(results_path)], env=env,
                   preexec_fn=_limit_memory, check=True,
                   timeout=60 + sum(run["timeout"] for run in runs))
    results = json.loads(results_path.read_text())
    return {name: (ctx, info, results[name]) for name, (ctx, info) in prepared.items()}


@pytest.fixture(scope="module")
def catalogue(tmp_path_factory):
    base = tmp_path_factory.mktemp("hostile")
    logs = base / "logs"
    return _run_harness(base, CATALOGUE, logs), logs


def _assert_clean_failure(ctx: Ctx, info: dict, result: dict, logs: Path) -> None:
    assert result["signal"] is None, f"killed by signal {result['signal']} (timeout or memory)"
    assert result["code"] == info["code"], result["stderr"]
    err = result["stderr"]
    assert "Traceback" not in err and "Error:" not in err.replace("error:", ""), err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err  # one line
    assert info["message"] in lines[0], lines[0]
    assert lines[0].startswith("implantplan: "), lines[0]
    assert (ctx.out / "plan.json").read_bytes() == PREVIOUS  # the previous plan intact
    assert sorted(p.name for p in ctx.out.iterdir()) == sorted([MARKER, "plan.json"])
    assert _snapshot(ctx.root, ctx.out) == info["before"]  # nothing written anywhere else
    assert not list(ctx.cwd.iterdir())
    assert result["max_rss_mb"] < AS_LIMIT / 2**20
    assert not logs.exists() or not list(logs.iterdir())  # no internal error


@pytest.mark.parametrize("name", list(CATALOGUE))
def test_a_hostile_input_fails_cleanly(name, catalogue):
    results, logs = catalogue
    ctx, info, result = results[name]
    _assert_clean_failure(ctx, info, result, logs)


@pytest.mark.sweep  # the default run: tests/analyses/test_plan.py's bad inputs plan it too
@pytest.mark.parametrize("name", list(PLANNING))
def test_a_planning_failure_fails_cleanly(name, tmp_path):
    logs = tmp_path / "logs"
    results = _run_harness(tmp_path, {name: PLANNING[name]}, logs,
                           timeouts={name: PLANNING_TIMEOUT})
    _assert_clean_failure(*results[name], logs)


def test_the_catalogue_has_at_least_40_hostile_inputs():
    assert len(CATALOGUE) + len(PLANNING) + len(SWEEP) >= 40


def test_the_escaping_name_wrote_nothing_above(catalogue):
    results, _ = catalogue
    ctx = results["site name escapes"][0]
    for folder in [ctx.root, *ctx.root.parents][:6]:
        assert not (folder / "ESCAPED").exists()


def test_the_patients_files_are_kept(catalogue):
    results, _ = catalogue
    ctx = results["out holds the patient's files"][0]
    folder = ctx.root / "outs" / "patient42"
    assert sorted(p.name for p in folder.iterdir()) == ["consent_form.pdf", "scan.obj"]
    err = results["out holds the patient's files"][2]["stderr"]
    assert "'consent_form.pdf'" in err and "--force" in err


@pytest.mark.sweep
def test_a_failed_check_exits_3_and_is_marked(tmp_path):
    logs = tmp_path / "logs"
    results = _run_harness(tmp_path, SWEEP, logs, timeouts={name: 300 for name in SWEEP})
    for ctx, info, result in results.values():
        assert result["code"] == info["code"], result["stderr"]
        assert info["message"] in result["stdout"], result["stdout"]
        plan = json.loads((ctx.out / "plan.json").read_text())
        assert not plan["passed"] and plan["acknowledged"][0]["flag"] == "--accept-repairs"
        assert "Traceback" not in result["stderr"]


# -- signals -------------------------------------------------------------------------------------


def _start_plan(tmp_path: Path, out: Path) -> subprocess.Popen:
    case = tmp_path / "case.yaml"
    case.write_text(yaml.safe_dump(small_case()))
    env = dict(os.environ, IMPLANTPLAN_LOG_DIR=str(tmp_path / "logs"))
    return subprocess.Popen([sys.executable, "-m", "implantplan.analyses.cli", "plan", str(case),
                             "--out", str(out), "--no-figures"], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=_limit_memory)


EXIT_BOUND = 2.0  # s from SIGTERM to the exit (issue 23's spec: the one timing asserted)


def _stop(proc: subprocess.Popen, sig: int = signal.SIGTERM) -> tuple[float, str]:
    """Send ``sig`` to the run and wait for its exit: (seconds from the signal, its stderr)."""
    t0 = time.monotonic()
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    return time.monotonic() - t0, (err or b"").decode(errors="replace")


def _cli(*argv: str) -> list[str]:
    return [sys.executable, "-m", "implantplan.analyses.cli", *argv]


def _staging(out: Path) -> list[Path]:
    return sorted(out.parent.glob(f".{out.name}.{STAGING}-*"))


def _wait_for_staging(proc: subprocess.Popen, out: Path) -> None:
    """Until the run has made its staging folder and started fitting (the first stage)."""
    for _ in range(600):
        if _staging(out) and any((s / MARKER).is_file() for s in _staging(out)):
            return
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    raise AssertionError("the plan made no staging folder in 30 s")


def _previous_plan(tmp_path: Path) -> Path:
    out = tmp_path / "outs" / "plan"
    out.mkdir(parents=True)
    mark(out, "plan")
    (out / "plan.json").write_bytes(PREVIOUS)
    return out


def test_sigterm_stops_a_plan_and_cleans_up(tmp_path):
    out = _previous_plan(tmp_path)
    proc = _start_plan(tmp_path, out)
    _wait_for_staging(proc, out)
    time.sleep(0.3)  # inside the FPSM fit
    seconds, err = _stop(proc)
    assert proc.returncode == 143, err
    assert "terminated (SIGTERM)" in err and "Traceback" not in err
    assert seconds < EXIT_BOUND, f"exited {seconds:.2f} s after SIGTERM"
    assert _staging(out) == []
    assert (out / "plan.json").read_bytes() == PREVIOUS
    assert sorted(p.name for p in out.parent.iterdir()) == ["plan"]


def test_the_run_after_a_sigkill_removes_its_leftovers(tmp_path):
    out = _previous_plan(tmp_path)
    proc = _start_plan(tmp_path, out)
    _wait_for_staging(proc, out)
    proc.kill()
    proc.communicate(timeout=30)
    left = _staging(out)
    assert len(left) == 1 and (out / "plan.json").read_bytes() == PREVIOUS
    # the next run towards the same --out (here one that stops at its bad case) removes them
    env = dict(os.environ, IMPLANTPLAN_LOG_DIR=str(tmp_path / "logs"))
    rerun = subprocess.run([sys.executable, "-m", "implantplan.analyses.cli", "plan",
                            str(tmp_path / "missing.yaml"), "--out", str(out)], cwd=tmp_path,
                           env=env, capture_output=True, text=True, timeout=60,
                           preexec_fn=_limit_memory)
    assert rerun.returncode == 2 and "case: file" in rerun.stderr
    assert _staging(out) == [] and sorted(p.name for p in out.parent.iterdir()) == ["plan"]
    assert (out / "plan.json").read_bytes() == PREVIOUS


# -- noise ---------------------------------------------------------------------------------------


def test_drake_info_is_dropped_and_a_repeated_warning_shows_once_with_its_count():
    import logging

    from implantplan.analyses.progress import DrakeNoise

    logger = logging.Logger("drake-test")  # not the real "drake" logger: nothing else logs here
    shown = []
    handler = logging.Handler()
    handler.emit = lambda record: shown.append(record.getMessage())
    logger.addHandler(handler)
    noise = DrakeNoise()
    logger.addFilter(noise)
    logger.info("Meshcat listening for connections at http://localhost:7000")
    for t in range(94):
        logger.warning(f"Differential IK is stuck at t = {t * 0.005:.3f} s (status 2)")
    logger.warning("another warning")
    assert shown == ["Differential IK is stuck at t = 0.000 s (status 2)", "another warning"]
    assert noise.summary() == ["drake warning repeated 94 times in all (shown once): "
                               "Differential IK is stuck at t = 0.000 s (status 2)"]
    noise.reset()
    assert noise.summary() == []


def test_an_internal_error_is_one_line_naming_its_log(tmp_path, monkeypatch, capsys):
    from implantplan.analyses import plan
    from implantplan.analyses.cli import main

    def bug(args):
        raise ZeroDivisionError("a bug\nwith a second line")

    monkeypatch.setattr(plan, "_cmd_plan", bug)
    monkeypatch.setenv("IMPLANTPLAN_LOG_DIR", str(tmp_path / "logs"))
    assert main(["plan", "case.yaml", "--out", str(tmp_path / "x")]) == 1
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("implantplan: internal error: ZeroDivisionError: a bug (traceback "
                               f"in {tmp_path / 'logs'}")
    (log,) = (tmp_path / "logs").iterdir()
    text = log.read_text()
    assert "Traceback" in text and "ZeroDivisionError: a bug" in text and "'plan'" in text


def test_help_states_the_exit_codes():
    from implantplan.analyses.cli import build_parser

    text = " ".join(build_parser([]).format_help().split())
    assert ("exit codes: 0 every check passes; 3 a planning failure or a failed check; 2 bad "
            "input") in text


def test_sigterm_stops_a_capmap_build_and_keeps_only_its_resumable_blocks(tmp_path):
    """``capmap build`` stopped by SIGTERM as by Ctrl-C: exit 143, no map and no temporary file;
    the finished blocks stay in the store beside the map for ``--resume`` (by design)."""
    out = tmp_path / "map.h5"
    proc = subprocess.Popen([sys.executable, "-m", "implantplan.analyses.cli", "capmap", "build",
                             "--voxel-mm", "50", "--directions", "20", "--cell", "centre",
                             "--workers", "1", "--block-poses", "2000", "--out", str(out)],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=_limit_memory)
    for _ in range(1200):
        stores = list(tmp_path.glob("map.h5.blocks-*"))
        if stores and list(stores[0].glob("block-*.npz")):
            break
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    else:
        raise AssertionError("no block finished in 60 s")
    seconds, err = _stop(proc)
    assert proc.returncode == 143, err
    assert "Traceback" not in err
    assert seconds < EXIT_BOUND, f"exited {seconds:.2f} s after SIGTERM"
    assert not out.exists()
    (store,) = [p for p in tmp_path.iterdir()]
    assert store.name.startswith("map.h5.blocks-")
    names = [p.name for p in store.iterdir()]
    assert "manifest.json" in names and len(names) >= 2
    assert all(n == "manifest.json" or (n.startswith("block-") and n.endswith(".npz"))
               for n in names), names  # no temporary file of a half-written block


@pytest.mark.sweep  # plans a case and starts the studio's servers: ~50 s at load
def test_sigterm_stops_the_studio(tmp_path):
    """The studio serving a case it planned stops on SIGTERM as on Ctrl-C (it closes its
    servers and exits), with SIGTERM's exit code 143 as every command, its plan folder kept."""
    case = tmp_path / "case.yaml"
    case.write_text(yaml.safe_dump(small_case()))
    printed = tmp_path / "printed.txt"
    with printed.open("wb") as stdout:
        proc = subprocess.Popen([sys.executable, "-m", "implantplan.analyses.cli", "studio",
                                 str(case), "--out", str(tmp_path / "plan"), "--quiet"],
                                cwd=tmp_path, stdout=stdout, stderr=subprocess.STDOUT,
                                preexec_fn=_limit_memory)
        for _ in range(2400):
            if "studio: http" in printed.read_text(errors="replace"):
                break
            assert proc.poll() is None, printed.read_text()
            time.sleep(0.05)
        else:
            raise AssertionError("the studio did not start in 120 s")
        seconds, _ = _stop(proc)
    text = printed.read_text(errors="replace")
    assert "studio: closed" in text and "Traceback" not in text, text
    assert proc.returncode == 143 and "terminated (SIGTERM)" in text, (proc.returncode, text)
    assert seconds < EXIT_BOUND, f"exited {seconds:.2f} s after SIGTERM"
    assert (tmp_path / "plan" / "plan.json").is_file() and (tmp_path / "plan" / MARKER).is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["case.yaml", "plan", "printed.txt"]


def test_a_plan_folder_from_before_the_marker_is_the_projects_and_a_mixed_one_is_not(tmp_path):
    from implantplan.analyses.out_folder import check_out, is_project_folder

    old = tmp_path / "old"
    (old / "figures").mkdir(parents=True)
    (old / "plan.json").write_bytes(PREVIOUS)
    (old / "report.html").write_text("<html></html>")
    (old / "scene_36.html").write_text("<html></html>")
    assert is_project_folder(old) and check_out(old) == old
    (old / "consent_form.pdf").write_bytes(b"%PDF")
    assert not is_project_folder(old)
    with pytest.raises(Exception, match="consent_form.pdf"):
        check_out(old)
    other = tmp_path / "other"
    other.mkdir()
    (other / "plan.json").write_text('{"kind": "capmap_plan"}')
    assert not is_project_folder(other)


def test_sigterm_stops_a_batch_and_cleans_up(tmp_path):
    """``batch`` on this process (``--workers 1``) stopped by SIGTERM while a case plans: exit
    143, the case's staging folder removed, no summary written (the batch did not finish)."""
    case = tmp_path / "case.yaml"
    case.write_text(yaml.safe_dump(small_case()))
    out = tmp_path / "study"
    proc = subprocess.Popen([sys.executable, "-m", "implantplan.analyses.cli", "batch", str(case),
                             "--workers", "1", "--no-figures", "--quiet", "--out", str(out)],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=_limit_memory)
    _wait_for_staging(proc, out / "case")
    seconds, err = _stop(proc)
    assert proc.returncode == 143, err
    assert "Traceback" not in err
    assert seconds < EXIT_BOUND, f"exited {seconds:.2f} s after SIGTERM"
    assert sorted(p.name for p in out.iterdir()) == [MARKER]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["case.yaml", "study"]


def _start_batch(tmp_path: Path, names: tuple[str, ...], workers: int) -> tuple[subprocess.Popen,
                                                                                  Path]:
    """``batch`` of the small case under each name in ``names`` (one case file each) into
    ``tmp_path/study``, with ``workers`` (2: a LocalCluster), once every case plans in its
    staging folder (marked). No address-space limit: a LocalCluster's workers inherit it."""
    cases = []
    for name in names:
        (tmp_path / f"{name}.yaml").write_text(yaml.safe_dump(small_case()))
        cases.append(str(tmp_path / f"{name}.yaml"))
    out = tmp_path / "study"
    proc = subprocess.Popen(_cli("batch", *cases, "--workers", str(workers), "--no-figures",
                                 "--quiet", "--out", str(out)),
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    for name in names:
        _wait_for_staging(proc, out / name)
    return proc, out


def _planner_pids(out: Path) -> set[int]:
    """The pids in the names of the staging folders in the batch folder ``out`` (the processes
    planning its cases: the batch's own with --workers 1, else its workers')."""
    return {int(p.name.split(f".{STAGING}-")[1].split("-")[0])
            for p in out.glob(f".*.{STAGING}-*")}


def _gone(pids, within: float) -> bool:
    """Every process of ``pids`` has exited (not even a zombie) within ``within`` s."""
    import psutil

    end = time.monotonic() + within
    while time.monotonic() < end:
        alive = [p for p in pids if psutil.pid_exists(p)
                 and psutil.Process(p).status() != psutil.STATUS_ZOMBIE]
        if not alive:
            return True
        time.sleep(0.05)
    return False


def _rerun_batch_on_a_missing_case(tmp_path: Path, out: Path) -> subprocess.CompletedProcess:
    """The next batch into ``out``: its one case file is missing (bad input, exit 2)."""
    return subprocess.run(_cli("batch", str(tmp_path / "missing.yaml"), "--workers", "1",
                               "--no-figures", "--quiet", "--out", str(out)),
                          cwd=tmp_path, capture_output=True, text=True, timeout=60,
                          preexec_fn=_limit_memory)


@pytest.mark.sweep  # a kill of a worker pool or a server: CI; plan and run kills by default
def test_the_batch_after_a_killed_batch_removes_its_leftovers(tmp_path):
    """``kill -KILL`` of a batch (``--workers 1``) while its case plans leaves the case's
    staging folder in the batch folder; the next batch into that folder removes it before its
    first case, even a batch whose only case is bad input."""
    proc, out = _start_batch(tmp_path, ("case",), 1)
    assert _planner_pids(out) == {proc.pid}
    _stop(proc, signal.SIGKILL)
    assert len(list(out.glob(f".case.{STAGING}-*"))) == 1
    rerun = _rerun_batch_on_a_missing_case(tmp_path, out)
    assert rerun.returncode == 2 and "Traceback" not in rerun.stderr, rerun.stderr
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == [MARKER]


@pytest.mark.cluster  # a LocalCluster of 2 workers planning 2 cases: ~10 s at load
def test_sigterm_stops_a_two_worker_batch_within_2_s_and_cleans_up(tmp_path):
    """``batch`` on its default engine (a LocalCluster, 2 worker processes) stopped by SIGTERM
    while both cases plan: exit 143 within 2 s (the workers are killed, not waited for), the
    staging folders the workers were planning into removed, no worker process left."""
    import psutil

    proc, out = _start_batch(tmp_path, ("a", "b"), 2)
    workers = _planner_pids(out)
    assert len(workers) == 2 and proc.pid not in workers
    children = psutil.Process(proc.pid).children(recursive=True)
    assert workers <= {c.pid for c in children}
    seconds, err = _stop(proc)
    assert proc.returncode == 143 and "terminated (SIGTERM)" in err, err
    assert "Traceback" not in err and "ERROR" not in err, err
    assert seconds < EXIT_BOUND, f"exited {seconds:.2f} s after SIGTERM"
    assert sorted(p.name for p in out.iterdir()) == [MARKER]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.yaml", "b.yaml", "study"]
    assert _gone([c.pid for c in children], within=5.0)


@pytest.mark.cluster  # a LocalCluster of 2 workers planning 2 cases: ~10 s at load
def test_the_batch_after_a_killed_two_worker_batch_removes_its_workers_leftovers(tmp_path):
    """``kill -KILL`` of a LocalCluster batch: its workers exit with it (Dask's watch of the
    parent), leaving the staging folders named with their pids; the next batch into the folder
    removes them."""
    proc, out = _start_batch(tmp_path, ("a", "b"), 2)
    workers = _planner_pids(out)
    assert len(workers) == 2 and proc.pid not in workers
    _stop(proc, signal.SIGKILL)
    assert _gone(workers, within=10.0), "the workers outlived their killed batch"
    assert _planner_pids(out) == workers  # the leftovers
    rerun = _rerun_batch_on_a_missing_case(tmp_path, out)
    assert rerun.returncode == 2 and "Traceback" not in rerun.stderr, rerun.stderr
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == [MARKER]


CAPMAP_SMALL = ("capmap", "build", "--voxel-mm", "80", "--directions", "20", "--cell", "centre",
                "--block-poses", "2000")  # ~400 blocks of a few ms each


def _start_capmap(tmp_path: Path, workers: int, blocks: int = 1) -> tuple[subprocess.Popen, Path]:
    """``capmap build`` of :data:`CAPMAP_SMALL` into ``tmp_path/map.h5``, once ``blocks`` are
    in its block store."""
    out = tmp_path / "map.h5"
    proc = subprocess.Popen(_cli(*CAPMAP_SMALL, "--workers", str(workers), "--out", str(out)),
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    for _ in range(1200):
        stores = list(tmp_path.glob("map.h5.blocks-*"))
        if stores and len(list(stores[0].glob("block-*.npz"))) >= blocks:
            return proc, stores[0]
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.02)
    raise AssertionError(f"not {blocks} blocks in 24 s")


@pytest.mark.cluster  # a LocalCluster of 2 workers
def test_sigterm_stops_a_two_worker_capmap_build_within_2_s(tmp_path):
    """``capmap build`` on a LocalCluster stopped by SIGTERM: exit 143 within 2 s (its
    hundreds of queued blocks cancelled in one message, the workers killed), no map, only the
    finished blocks kept for ``--resume``, no worker process left."""
    import psutil

    proc, store = _start_capmap(tmp_path, 2)
    children = psutil.Process(proc.pid).children(recursive=True)
    assert children
    seconds, err = _stop(proc)
    assert proc.returncode == 143 and "Traceback" not in err and "ERROR" not in err, err
    assert seconds < EXIT_BOUND, f"exited {seconds:.2f} s after SIGTERM"
    assert sorted(p.name for p in tmp_path.iterdir()) == [store.name]
    names = [p.name for p in store.iterdir()]
    assert all(n == "manifest.json" or (n.startswith("block-") and n.endswith(".npz"))
               for n in names), names
    assert _gone([c.pid for c in children], within=5.0)


@pytest.mark.sweep  # a kill of a worker pool or a server: CI; plan and run kills by default
def test_the_capmap_build_after_a_killed_one_removes_its_leftovers(tmp_path):
    """``kill -KILL`` of ``capmap build`` mid-build: its finished blocks stay (for
    ``--resume``), and a block being written when the kill came leaves its temporary file
    (made here as :func:`systems.files.write_atomic` names it: the kill cannot be aimed inside
    the write). The next build removes that file even when it is refused for a missing
    ``--resume``; the resumed build writes the map and removes the store: nothing else left."""
    proc, store = _start_capmap(tmp_path, 1)
    _stop(proc, signal.SIGKILL)
    assert not (tmp_path / "map.h5").exists()
    half_written = store / ".block-000399.npz.k1ll3d.npz"
    half_written.write_bytes(b"PK\x03\x04")
    refused = subprocess.run(_cli(*CAPMAP_SMALL, "--workers", "1", "--out", "map.h5"),
                             cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert refused.returncode == 2 and "--resume" in refused.stderr, refused.stderr
    assert not half_written.exists() and len(list(store.glob("block-*.npz"))) >= 1
    resumed = subprocess.run(_cli(*CAPMAP_SMALL, "--workers", "1", "--resume",
                                  "--out", "map.h5"),
                             cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert resumed.returncode == 0, resumed.stderr
    assert json.loads(resumed.stdout)["blocks_reused"] >= 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.h5"]


def _start_studio(tmp_path: Path, *argv: str) -> tuple[subprocess.Popen, Path]:
    """``studio ARGV`` with its output in ``tmp_path/printed.txt``."""
    printed = tmp_path / "printed.txt"
    with printed.open("wb") as stdout:
        proc = subprocess.Popen(_cli("studio", *argv), cwd=tmp_path, stdout=stdout,
                                stderr=subprocess.STDOUT, preexec_fn=_limit_memory)
    return proc, printed


def test_sigterm_stops_the_studio_while_it_plans_and_cleans_up(tmp_path):
    """The studio planning a case into ``--out`` stopped by SIGTERM: exit 143 within 2 s, the
    plan's staging folder removed, the previous plan in ``--out`` intact."""
    out = _previous_plan(tmp_path)
    (tmp_path / "case.yaml").write_text(yaml.safe_dump(small_case()))
    proc, printed = _start_studio(tmp_path, str(tmp_path / "case.yaml"), "--out", str(out),
                                  "--quiet")
    _wait_for_staging(proc, out)
    seconds, _ = _stop(proc)
    text = printed.read_text(errors="replace")
    assert proc.returncode == 143 and "terminated (SIGTERM)" in text, text
    assert "Traceback" not in text and seconds < EXIT_BOUND, (seconds, text)
    assert _staging(out) == [] and (out / "plan.json").read_bytes() == PREVIOUS
    assert sorted(p.name for p in out.parent.iterdir()) == ["plan"]


@pytest.mark.sweep  # a kill of a worker pool or a server: CI; plan and run kills by default
def test_the_studio_after_a_killed_one_removes_its_leftovers(tmp_path):
    """``kill -KILL`` of the studio while it plans leaves the staging folder beside ``--out``;
    the next studio towards that folder removes it before reading its case (here a missing
    one: exit 2), the previous plan intact."""
    out = _previous_plan(tmp_path)
    (tmp_path / "case.yaml").write_text(yaml.safe_dump(small_case()))
    proc, _ = _start_studio(tmp_path, str(tmp_path / "case.yaml"), "--out", str(out), "--quiet")
    _wait_for_staging(proc, out)
    _stop(proc, signal.SIGKILL)
    assert len(_staging(out)) == 1
    rerun = subprocess.run(_cli("studio", str(tmp_path / "missing.yaml"), "--out", str(out)),
                           cwd=tmp_path, capture_output=True, text=True, timeout=60,
                           preexec_fn=_limit_memory)
    assert rerun.returncode == 2 and "case: file" in rerun.stderr, rerun.stderr
    assert _staging(out) == [] and sorted(p.name for p in out.parent.iterdir()) == ["plan"]
    assert (out / "plan.json").read_bytes() == PREVIOUS


@pytest.mark.sweep  # a kill of a worker pool or a server: CI; plan and run kills by default
def test_sigterm_stops_the_studio_serving_a_plan_within_2_s(tmp_path, small_plan):
    """The studio serving a plan folder (``--plan``) stopped by SIGTERM: it closes its servers,
    exits 143 within 2 s, the plan folder as it was (every file, byte for byte)."""
    import shutil

    plan = shutil.copytree(small_plan[1], tmp_path / "plan")
    before = {p.relative_to(plan): p.read_bytes() for p in plan.rglob("*") if p.is_file()}
    proc, printed = _start_studio(tmp_path, "--plan", str(plan))
    for _ in range(1200):
        if "studio: http" in printed.read_text(errors="replace"):
            break
        assert proc.poll() is None, printed.read_text()
        time.sleep(0.05)
    else:
        raise AssertionError("the studio did not start in 60 s")
    seconds, _ = _stop(proc)
    text = printed.read_text(errors="replace")
    assert proc.returncode == 143 and "studio: closed" in text, text
    assert "Traceback" not in text and seconds < EXIT_BOUND, (seconds, text)
    after = {p.relative_to(plan): p.read_bytes() for p in plan.rglob("*") if p.is_file()}
    assert after == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plan", "printed.txt"]


def test_a_file_put_into_a_plan_folder_is_the_users(tmp_path):
    """A plan folder (marked, written atomically) into which the user copied a file: the next
    run towards it is refused naming that file (exit 2 in the CLI), the file kept; what a plan
    folder gains later (studio recordings) is still the project's; --force replaces it."""
    from implantplan.analyses.out_folder import check_out, foreign_entries, staged
    from implantplan.systems.errors import InputError

    out = tmp_path / "patient42"
    with staged(out, "plan") as stage:
        (stage / "plan.json").write_text('{"kind": "plan"}')
        (stage / "figures").mkdir()
    assert foreign_entries(out) == [] and check_out(out) == out
    (out / "recordings").mkdir()  # the studio's, written into the plan folder later
    assert check_out(out) == out
    (out / "xray_of_patient.png").write_bytes(b"\x89PNG")
    assert foreign_entries(out) == ["xray_of_patient.png"]
    with pytest.raises(InputError, match="xray_of_patient.png"):
        check_out(out)
    assert (out / "xray_of_patient.png").read_bytes() == b"\x89PNG"
    assert check_out(out, force=True) == out


def test_a_leftover_of_a_process_that_exited_but_is_not_reaped_is_stale(tmp_path):
    """A killed batch's worker is a zombie until the process it was handed to reaps it: its
    staging folder is stale already (the pid still answers a signal 0, the process runs no
    more)."""
    from implantplan.analyses.out_folder import remove_stale

    child = subprocess.Popen(["true"])  # exits at once; not reaped until wait()
    stat = Path(f"/proc/{child.pid}/stat")
    for _ in range(200):
        text = stat.read_bytes()
        if text[text.rfind(b")") + 2:][:1] == b"Z":
            break
        time.sleep(0.01)
    else:
        raise AssertionError("the child did not exit in 2 s")
    leftover = tmp_path / f".plan.{STAGING}-{child.pid}-abcd1234"
    leftover.mkdir()
    mark(leftover, "plan")
    try:
        assert remove_stale(tmp_path / "plan") == [leftover] and not leftover.exists()
    finally:
        child.wait()
