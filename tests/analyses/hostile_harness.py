"""Run many ``implantplan`` command lines, each in its own forked process, for
tests/analyses/test_hostile_inputs.py.

    python hostile_harness.py RUNS.json RESULTS.json

The parent test starts this program in a subprocess with its address space limited
(``resource.RLIMIT_AS``, inherited by every fork): a limit is never applied inside the pytest
process or an xdist worker (an allocation over it would kill the worker). This process imports
the command line once (1.4 s of Drake, numba and trimesh), then forks one child per run: the child
changes to the run's folder, sends its stdout and stderr to files, arms ``alarm(timeout)`` (the
default action kills it) and calls ``implantplan.analyses.cli.main``. The parent records each
child's exit code or signal and its peak resident memory (``wait4``).

RUNS.json: a list of ``{"id", "argv", "cwd", "timeout", "env", "capture"}`` (``capture``: the
path prefix of the files the child's stdout and stderr go to); RESULTS.json: per id
``{"code", "signal", "seconds", "max_rss_mb", "stdout", "stderr"}``.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time


def run_one(run: dict, main) -> dict:
    out_path, err_path = run["capture"] + ".stdout", run["capture"] + ".stderr"
    t0 = time.monotonic()
    pid = os.fork()
    if pid == 0:  # the child: never returns
        code = 99
        try:
            os.chdir(run["cwd"])
            os.environ.update(run.get("env", {}))
            for fd, path in ((1, out_path), (2, err_path)):
                f = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
                os.dup2(f, fd)
                os.close(f)
            signal.alarm(int(run["timeout"]))
            try:
                code = main(run["argv"])
            except SystemExit as exc:  # argparse
                code = exc.code if isinstance(exc.code, int) else 2
            sys.stdout.flush()
            sys.stderr.flush()
        except BaseException:  # noqa: BLE001 - reported as the harness's own code
            import traceback

            traceback.print_exc()
            sys.stderr.flush()
        os._exit(int(code or 0))
    _, status, usage = os.wait4(pid, 0)
    seconds = time.monotonic() - t0
    with open(out_path, encoding="utf-8", errors="replace") as f:
        stdout = f.read()
    with open(err_path, encoding="utf-8", errors="replace") as f:
        stderr = f.read()
    os.unlink(out_path)
    os.unlink(err_path)
    return {"code": os.WEXITSTATUS(status) if os.WIFEXITED(status) else None,
            "signal": os.WTERMSIG(status) if os.WIFSIGNALED(status) else None,
            "seconds": seconds, "max_rss_mb": usage.ru_maxrss / 1024.0,
            "stdout": stdout, "stderr": stderr}


def main() -> None:
    runs_path, results_path = sys.argv[1], sys.argv[2]
    with open(runs_path) as f:
        runs = json.load(f)
    from implantplan.analyses import budget, case, pipeline, plan  # noqa: F401 - warm
    from implantplan.analyses.cli import main as cli_main

    results = {run["id"]: run_one(run, cli_main) for run in runs}
    with open(results_path, "w") as f:
        json.dump(results, f)


if __name__ == "__main__":
    main()
