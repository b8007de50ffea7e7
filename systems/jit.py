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
"""

import threading

import numba
import numpy as np

__all__ = ["kernel_array", "numba"]


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
