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
