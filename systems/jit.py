"""numba as the kernels use it: ``from implantplan.systems.jit import numba``.

Importing numba through this module adds one thing: each cached kernel is compiled by one
process at a time. Processes that start together on a fresh cache (pytest-xdist workers, a
study's worker pool, Dask workers on one machine) would otherwise each compile the same kernels;
the demo's kernels alone take about a minute of CPU to compile, more than the demo's run.
numba's own compiler lock holds within a process; here a file lock (flock, beside the kernel's
cache index) is taken around the outermost compile of each thread, so a second process waits
and then finds the kernel in the cache and loads it. Only outermost compiles take the lock (no
process waits on a lock while it holds one: no deadlock); a kernel without a disk cache, a
cache folder that cannot be written or a numba without the internals used here compiles as
before. The cache's folder is chosen in ``implantplan/__init__.py``.

And one more: a kernel of ``implantplan.systems`` is cached under the package's own path
(``<cache>/implantplan/systems/placement/...``), stamped with the sources of its module and of
every ``implantplan.systems`` module that module imports, transitively (:func:`source_stamp`).
numba's own locator keys the cache by the source folder's absolute path and stamps a kernel with
its own file only: a second clone (another folder, a CI checkout, a worktree) compiled every
kernel again, and a kernel that calls a compiled function of another module kept its cached
machine code after that module changed (numba does not follow calls across files). Here a
clone with the same sources loads the kernels compiled by another, and a change in any module a
kernel's module imports compiles it again.
"""

import functools
import hashlib
import os
import re
import threading
from pathlib import Path

import numba
import numpy as np

__all__ = ["imported_modules", "kernel_array", "numba", "source_stamp"]

SYSTEMS = Path(__file__).resolve().parent  # the folder of implantplan.systems
_IMPORTS = re.compile(r"implantplan\.systems((?:\.\w+)*)"
                      r"(?:[ \t]+import[ \t]+(?:\(([^)]*)\)|([\w \t,]+)))?")


def kernel_array(a, shape=None, dtype=float) -> np.ndarray:
    """``a`` as a kernel's array argument: ``dtype``, C-contiguous and writable, broadcast to
    ``shape`` if given; copied only when it is not already so.

    numba compiles one version of a kernel per argument type, and a read-only array (a
    broadcast view, a frozen cache) is another type than a writable one: each such call
    compiles the kernel again (seconds each on a fresh cache)."""
    a = np.asarray(a, dtype=dtype)
    if shape is not None:
        a = np.broadcast_to(a, shape)
    return np.require(a, dtype, ["C", "W"])


def _one_compile_per_kernel() -> None:
    try:
        import fcntl

        from numba.core.dispatcher import Dispatcher
    except ImportError:  # not POSIX, or numba's internals moved
        return
    original = Dispatcher.compile
    if getattr(original, "one_compile_per_kernel", False):
        return
    depth = threading.local()

    def compile(self, sig):
        cache_file = getattr(getattr(self, "_cache", None), "_cache_file", None)
        index = getattr(cache_file, "_index_path", None)
        handle = None
        if getattr(depth, "n", 0) == 0 and isinstance(index, str):
            try:
                handle = open(index + ".lock", "a")  # noqa: SIM115 - held across the compile
                fcntl.flock(handle, fcntl.LOCK_EX)
            except OSError:
                if handle is not None:
                    handle.close()
                handle = None
        depth.n = getattr(depth, "n", 0) + 1
        try:
            return original(self, sig)
        finally:
            depth.n -= 1
            if handle is not None:
                handle.close()  # releases the lock

    compile.one_compile_per_kernel = True
    Dispatcher.compile = compile


_one_compile_per_kernel()


def _module_file(dotted: str) -> Path | None:
    """The file of ``implantplan.systems<dotted>`` (``.placement.fixture``), None if none."""
    base = SYSTEMS.joinpath(*dotted.split(".")[1:]) if dotted else SYSTEMS
    for f in (base.with_suffix(".py"), base / "__init__.py"):
        if f.is_file():
            return f
    return None


@functools.cache
def imported_modules(path: Path) -> frozenset[Path]:
    """The files of the implantplan.systems modules ``path`` names in its imports (module-level
    or inside functions; ``from implantplan.systems.x import y`` names x and, if a module, x.y)."""
    out = set()
    for m in _IMPORTS.finditer(path.read_text(encoding="utf-8")):
        dotted, names = m.group(1), (m.group(2) or m.group(3) or "").replace("\n", ",")
        named = (n.split()[0] for n in names.split(",") if n.split() and n.split()[0] != "#")
        for f in [_module_file(dotted)] + [_module_file(f"{dotted}.{n}") for n in named]:
            if f is not None and f != path:
                out.add(f)
    return frozenset(out)


@functools.cache
def source_stamp(path: Path) -> str:
    """sha256 over the sources of ``path`` and of every implantplan.systems module it imports,
    transitively (sorted by path relative to the package)."""
    seen, todo = {path}, [path]
    while todo:
        for f in imported_modules(todo.pop()):
            if f not in seen:
                seen.add(f)
                todo.append(f)
    h = hashlib.sha256()
    for f in sorted(seen):
        h.update(f.relative_to(SYSTEMS).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()


def _package_cache_locator() -> None:
    try:
        from numba.core import caching, config
    except ImportError:  # numba's internals moved: its own locators
        return
    base = getattr(caching, "UserProvidedCacheLocator", None)
    impl = getattr(caching, "CacheImpl", None)
    if base is None or impl is None or any(getattr(c, "implantplan", False)
                           for c in impl._locator_classes):
        return

    class PackageCacheLocator(base):
        """Caches a kernel of implantplan.systems under the package's path, stamped with
        :func:`source_stamp` (module notes)."""

        implantplan = True

        def __init__(self, py_func, py_file):
            super().__init__(py_func, py_file)
            rel = Path(py_file).resolve().relative_to(SYSTEMS).with_suffix("")
            self._cache_path = os.path.join(config.CACHE_DIR, "implantplan", "systems",
                                            *rel.parts)

        def get_source_stamp(self):
            return source_stamp(Path(self._py_file).resolve())

        @classmethod
        def from_function(cls, py_func, py_file):
            try:
                Path(py_file).resolve().relative_to(SYSTEMS)
            except ValueError:  # not a module of implantplan.systems
                return None
            return super().from_function(py_func, py_file)

    impl._locator_classes.insert(0, PackageCacheLocator)


_package_cache_locator()
