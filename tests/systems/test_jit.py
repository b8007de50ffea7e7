"""systems.jit: processes that start together on a fresh cache compile each kernel once."""

import json
import os
import subprocess
import sys
import textwrap

# a kernel whose compile takes long enough (~1 s) for two processes to meet in it
_BODY = "\n".join(f"    x = x * 1.0000001 + {i}.0 / (x + {i + 1}.0)" for i in range(150))
KERNEL = f"""
from implantplan.systems.jit import numba


@numba.njit(cache=True)
def slow(x):
{_BODY}
    return x
"""

RUNNER = textwrap.dedent("""
    import json, os, sys, time
    sys.path.insert(0, sys.argv[1])
    import slow_kernel
    while not os.path.exists(sys.argv[2]):  # start together
        time.sleep(0.001)
    slow_kernel.slow(1.5)
    stats = slow_kernel.slow.stats
    print(json.dumps({"hits": sum(stats.cache_hits.values()),
                      "misses": sum(stats.cache_misses.values())}))
""")


def test_two_processes_on_a_fresh_cache_compile_a_kernel_once(tmp_path):
    (tmp_path / "slow_kernel.py").write_text(KERNEL)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    go = tmp_path / "go"
    procs = [subprocess.Popen([sys.executable, "-c", RUNNER, str(tmp_path), str(go)], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    go.write_text("")
    results = []
    for proc in procs:
        out, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err
        results.append(json.loads(out.strip().splitlines()[-1]))
    # one compiled it (a cache miss), the other waited and loaded it from the cache
    assert sorted(r["misses"] for r in results) == [0, 1], results
    assert sorted(r["hits"] for r in results) == [0, 1], results


def _tree(root, files: dict) -> None:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_a_kernel_module_is_stamped_with_every_module_it_imports(tmp_path, monkeypatch):
    """The stamp of a module covers its own source and, transitively, every
    implantplan.systems module it imports (one line, parenthesized, lazy, ``as``); a module it
    does not import leaves it unchanged."""
    from implantplan.systems import jit

    root = tmp_path / "systems"
    _tree(root, {
        "__init__.py": "",
        "a.py": "from implantplan.systems.b import f\n"
                "from implantplan.systems.pkg import (\n    c,  # a module\n    VALUE,\n)\n"
                "def g():\n    from implantplan.systems import lazy as L\n",
        "b.py": "import implantplan.systems.deep\n",
        "deep.py": "X = 1\n", "lazy.py": "Y = 1\n", "other.py": "Z = 1\n",
        "pkg/__init__.py": "VALUE = 1\n", "pkg/c.py": "W = 1\n",
    })  # fmt: skip
    monkeypatch.setattr(jit, "SYSTEMS", root)

    def stamp():
        jit.source_stamp.cache_clear()
        jit.imported_modules.cache_clear()
        return jit.source_stamp(root / "a.py")

    names = {f.relative_to(root).as_posix() for f in jit.imported_modules(root / "a.py")}
    assert names == {"b.py", "pkg/__init__.py", "pkg/c.py", "__init__.py", "lazy.py"}
    before = stamp()
    (root / "other.py").write_text("Z = 2\n")
    assert stamp() == before
    for name in ("deep.py", "lazy.py", "pkg/c.py", "a.py"):
        (root / name).write_text((root / name).read_text() + "\n# changed\n")
        after = stamp()
        assert after != before, name
        before = after
    jit.source_stamp.cache_clear()
    jit.imported_modules.cache_clear()


def test_the_project_kernels_are_cached_under_the_package_path():
    """A kernel of implantplan.systems is cached under <cache>/implantplan/systems/<module>,
    not under a hash of the source folder's absolute path (another clone with the same sources
    finds it), and stamped with its module's imports."""
    from pathlib import Path

    from implantplan.systems import jit
    from implantplan.systems.robot import collision_primitives

    cache = collision_primitives.seg_seg._cache
    assert Path(cache._cache_path) == Path(os.environ["NUMBA_CACHE_DIR"], "implantplan",
                                           "systems", "robot", "collision_primitives")
    assert cache._impl.locator.get_source_stamp() == jit.source_stamp(
        Path(collision_primitives.__file__).resolve())
