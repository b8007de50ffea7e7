"""Scale-out engine (DESIGN.md section 11): where independent tasks run, on Dask distributed.

One engine serves capability-map builds (voxel blocks) and cohort planning (one case per task):

* **in this process** (``--workers 1`` without ``--scheduler``): tasks run one after the other;
  nothing is started.
* ``local`` (the default when ``--workers`` > 1, or asked for): a ``LocalCluster`` on 127.0.0.1
  only, one single-threaded worker process per ``--workers`` (processes, not threads: the numpy /
  numba cores hold the GIL in places and Drake objects are per process), every port chosen by the
  OS (scheduler, workers), the dashboard off. It is closed when the run ends, also on an error or
  Ctrl-C (the context manager's ``finally``); a run that stops early (Ctrl-C, SIGTERM, an error)
  kills its worker processes first (:func:`kill_workers`) rather than wait for their tasks, so
  the command exits at once (SIGTERM: within 2 s, DESIGN.md section 3).
* ``tcp://HOST:PORT`` (or ``tls://``): a running cluster (``dask scheduler`` + ``dask worker``,
  docs/commands.md). ``--workers N`` then means "wait until N workers have joined".

Tasks carry plain values (arrays, dataclasses of numbers, file paths), never Drake objects (they
cannot be pickled): whatever a task needs it builds in the worker process. :class:`WarmUp` is a
worker plugin that imports the task's modules (and so loads their compiled numba kernels) once per
worker process when it joins, instead of inside the first task. Each task gets ``retries`` (2 by
default) on top of Dask's own rescheduling of the tasks of a worker that died (its
``allowed-failures``), so a dead worker costs only the tasks it was running.

:func:`run_unordered` yields ``(index, result)`` as tasks finish (any engine), so a caller can
store each result as soon as it exists; :class:`Eta` turns progress into a remaining-time guess.
"""

from __future__ import annotations

import importlib
import logging
import os
import re
import signal
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass

from distributed.diagnostics.plugin import WorkerPlugin

from implantplan.systems.errors import InputError

LOCAL = "local"
RETRIES = 2
# Environment of our LocalCluster's worker processes: one BLAS/OpenMP thread each (the worker is
# the unit of parallelism), and *not* Dask's default MALLOC_TRIM_THRESHOLD_=65536: with it glibc
# hands every large numpy temporary back to the OS and maps it again, which made a case's robot
# stage 1.5-3.5x slower in a worker than in this process (measured here; the IK and collision
# cores allocate many large temporaries). A variable set in the user's environment still wins.
WORKER_ENV = {"OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1}
_ADDRESS = re.compile(r"^(tcp|tls)://[A-Za-z0-9_.\-\[\]:]+:\d{1,5}$")


@dataclass
class Engine:
    """Where tasks run. ``executor`` is None when they run in this process.

    Attributes:
        kind: "process" (this process), "local" (a LocalCluster) or "remote" (a running cluster).
        workers: worker processes (1 for this process).
        description: one line for progress output.
        executor: a ``concurrent.futures.Executor`` over the Dask client (retries set), or None.
        client: the ``distributed.Client`` (None in this process).
    """

    kind: str
    workers: int
    description: str
    executor: Executor | None = None
    client: object | None = None

    def worker_pids(self) -> dict:
        """{worker address: pid} of every worker process (this process's pid in-process)."""
        if self.client is None:
            return {"this process": os.getpid()}
        return dict(self.client.run(os.getpid))


class WarmUp(WorkerPlugin):
    """Dask worker plugin: import ``modules`` when a worker process starts (or joins).

    Importing the cores loads their numba kernels from the on-disk cache and initializes the
    libraries a task uses, once per worker process rather than in the first task it runs. With
    ``ignore_sigint`` (our own LocalCluster's workers, which share the terminal's process group)
    the worker ignores Ctrl-C: the client alone handles it and closes the cluster in order.
    """

    idempotent = True

    def __init__(self, modules: Sequence[str], *, ignore_sigint: bool = False):
        self.modules = tuple(modules)
        self.ignore_sigint = bool(ignore_sigint)
        self.name = "implantplan-warmup-" + "-".join(self.modules)

    def setup(self, worker=None):
        if self.ignore_sigint and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        for module in self.modules:
            importlib.import_module(module)


def check_scheduler(scheduler: str | None, workers: int | None) -> tuple[str, int | None]:
    """Validate ``--scheduler`` / ``--workers``; returns (kind, workers) with kind in
    ("process", "local", "remote")."""
    if workers is not None and (int(workers) != workers or workers < 1):
        raise InputError("--workers", f"expected an integer >= 1, got {workers!r}")
    if scheduler is None:
        n = workers or os.cpu_count() or 1
        return ("process", 1) if n == 1 else (LOCAL, n)
    if scheduler == LOCAL:
        return LOCAL, workers or os.cpu_count() or 1
    if not _ADDRESS.match(str(scheduler)):
        raise InputError(
            "--scheduler", f"expected 'local' or an address tcp://HOST:PORT, got {scheduler!r}"
        )
    return "remote", workers


@contextmanager
def engine(
    scheduler: str | None = None,
    workers: int | None = None,
    *,
    warm_up: Sequence[str] = (),
    retries: int = RETRIES,
    connect_timeout: float = 10.0,
    join_timeout: float = 120.0,
) -> Iterator[Engine]:
    """The engine for ``--scheduler`` / ``--workers`` (see the module docstring); closes what it
    started when the block ends, however it ends.

    Args:
        scheduler: None, "local" or "tcp://HOST:PORT".
        workers: worker processes (local), workers to wait for (remote); None: all cores (local).
        warm_up: modules each worker imports once when it starts (:class:`WarmUp`).
        retries: extra attempts of a task that raised or whose worker died.
        connect_timeout: seconds to reach a remote scheduler.
        join_timeout: seconds to wait for ``workers`` workers of a remote cluster.
    """
    kind, n = check_scheduler(scheduler, workers)
    if kind == "process":
        for module in warm_up:
            importlib.import_module(module)
        yield Engine("process", 1, "in this process")
        return
    import dask
    from distributed import Client

    cluster = client = None
    levels = {name: logging.getLogger(name).level for name in TEARDOWN_LOGGERS}
    try:
        if kind == LOCAL:
            with dask.config.set({"distributed.nanny.pre-spawn-environ": WORKER_ENV}):
                cluster = local_cluster(n)
            client = Client(cluster)
            description = f"LocalCluster on 127.0.0.1, {n} worker processes x 1 thread"
        else:
            try:
                client = Client(scheduler, timeout=connect_timeout)
            except (OSError, TimeoutError) as exc:
                raise InputError("--scheduler", f"cannot reach {scheduler}: {exc}") from None
            if n:
                try:
                    client.wait_for_workers(n, timeout=join_timeout)
                except TimeoutError:
                    have = len(client.scheduler_info(n_workers=-1)["workers"])
                    raise InputError(
                        "--workers",
                        f"{scheduler} has {have} workers, {n} did not join in {join_timeout:g} s",
                    ) from None
            n = len(client.scheduler_info(n_workers=-1)["workers"])
            description = f"cluster {scheduler}, {n} workers"
        if warm_up or kind == LOCAL:
            client.register_plugin(WarmUp(warm_up, ignore_sigint=kind == LOCAL))
        yield Engine(kind, n, description, client.get_executor(retries=retries, pure=False), client)
    except BaseException:  # Ctrl-C, SIGTERM, an error: the tasks still running are not wanted
        quiet_teardown()
        if cluster is not None:
            kill_workers(cluster)
        raise
    finally:
        try:
            if client is not None:
                client.close()
            if cluster is not None:
                cluster.close()
        finally:
            for name, level in levels.items():
                logging.getLogger(name).setLevel(level)


def kill_workers(cluster) -> list[int]:
    """SIGKILL the worker processes of our LocalCluster ``cluster`` (a run that stops early:
    what they are computing is not wanted, and a worker busy in a task stops only when the task
    ends or, after Dask's close timeout, 4 s, is killed anyway). Their nannies are told first
    not to restart them, so the cluster then closes at once. The workers' ``finally`` blocks do
    not run: what a task had begun on disk (a case's staging folder, named with the worker's
    pid) is the caller's to remove, or the next run's (analyses.out_folder.remove_stale).
    Returns the pids killed."""
    killed = []
    for nanny in list(cluster.workers.values()):
        nanny.close_gracefully(reason="the run stopped")  # no restart when its worker dies
        pid = nanny.pid
        if pid:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                continue
            killed.append(pid)
    return killed


def local_cluster(n: int):
    """A Dask LocalCluster of ``n`` single-threaded worker processes, every server (scheduler,
    workers, dashboard) on 127.0.0.1 at a free port."""
    from distributed import LocalCluster

    return LocalCluster(
        n_workers=n,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        scheduler_port=0,
        dashboard_address="127.0.0.1:0",  # loopback, a free port (None binds 8787)
        silence_logs=logging.ERROR,
        local_directory=tempfile.gettempdir(),
    )


def run_unordered(
    eng: Engine,
    fn: Callable,
    args: Sequence[tuple],
    *,
    on_error: Callable[[int, BaseException], object] | None = None,
) -> Iterator[tuple[int, object]]:
    """``fn(*args[i])`` for every i on the engine; yields ``(i, result)`` in completion order.

    A task that still fails after its retries (it raised, or its workers kept dying) raises here,
    or, with ``on_error``, yields ``(i, on_error(i, exc))`` and the others go on. Tasks not
    collected when the caller stops are cancelled."""
    if eng.executor is None:
        for i, a in enumerate(args):
            try:
                result = fn(*a)
            except Exception as exc:
                if on_error is None:
                    raise
                result = on_error(i, exc)
            yield i, result
        return
    futures = {eng.executor.submit(fn, *a): i for i, a in enumerate(args)}
    try:
        for f in as_completed(futures):
            i = futures[f]
            try:
                result = f.result()
            except Exception as exc:
                if on_error is None:
                    raise
                result = on_error(i, exc)
            yield i, result
    finally:
        cancel_pending(futures, eng.executor)


def cancel_pending(futures, executor: Executor | None = None) -> None:
    """Cancel the ``futures`` not done yet (a run that stops early). Those of a Dask client's
    ``executor`` in one message, by shutting the executor down (no task can be submitted to it
    after that): each ``Future.cancel`` of Dask's executor is a round trip to the scheduler,
    1.6 s for the 1600 blocks of a map. Dask's teardown errors (futures cancelled while their
    results were being gathered, a graph still being received) are not logged from then on:
    the run is being abandoned, and the engine's ``finally`` restores the logging levels."""
    from distributed.cfexecutor import ClientExecutor

    if all(f.done() for f in futures):
        return
    if isinstance(executor, ClientExecutor):
        quiet_teardown()
        executor.shutdown(wait=False)
        return
    for f in futures:
        f.cancel()


# Loggers that report a Dask run's teardown races as errors with tracebacks
TEARDOWN_LOGGERS = ("distributed", "tornado.application")


def quiet_teardown() -> None:
    """Silence :data:`TEARDOWN_LOGGERS` (the engine restores them when it closes)."""
    for name in TEARDOWN_LOGGERS:
        logging.getLogger(name).setLevel(logging.CRITICAL + 1)


SCHEDULER_HELP = (
    "'local' (a LocalCluster on 127.0.0.1; the default when --workers > 1) or tcp://HOST:PORT "
    "of a running Dask cluster"
)
WORKERS_HELP = "worker processes (default: all cores; 1 = this process, no cluster)"


class Eta:
    """Remaining time from the rate so far: ``eta(done)`` after ``done`` of ``total`` tasks, the
    ``skipped`` ones (already done before this run) not counted in the rate."""

    def __init__(self, total: int, skipped: int = 0):
        self.total = int(total)
        self.skipped = int(skipped)
        self.t0 = time.perf_counter()

    def __call__(self, done: int) -> float | None:
        ran = done - self.skipped
        if ran <= 0:
            return None
        return (time.perf_counter() - self.t0) / ran * (self.total - done)

    def text(self, done: int) -> str:
        eta = self(done)
        return "ETA --" if eta is None else f"ETA {eta:.0f} s"
