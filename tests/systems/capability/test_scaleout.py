"""Capability maps on the Dask engine: a 2-worker LocalCluster (127.0.0.1 only; those tests are
marked ``cluster``) builds the same map as one process, survives a worker killed mid-build, and an
interrupted build resumes doing only the missing blocks."""

import os
import signal

import numpy as np
import pytest

from implantplan.systems.capability import maps as cm
from implantplan.systems.capability import scaleout
from implantplan.systems.errors import InputError

# 21 blocks of ~10k IK poses (~30 ms each): enough blocks to kill a worker in the middle
PARAMS = cm.make_params(0.15, 30)
PER_BLOCK = 10_000


def _same(a: cm.CapabilityMap, b: cm.CapabilityMap) -> None:
    assert a.params == b.params and a.grid.shape == b.grid.shape
    np.testing.assert_array_equal(a.grid.origin, b.grid.origin)
    for name in ("voxel_ids", "reach_bits", "all_roll_bits", "index"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)


@pytest.fixture(scope="module")
def reference():
    return cm.build(PARAMS, workers=1, poses_per_block=PER_BLOCK)


@pytest.fixture(scope="module")
def local2():
    with scaleout.engine("local", 2, warm_up=["implantplan.systems.capability.maps"]) as eng:
        yield eng
    # closed: the scheduler no longer answers
    assert eng.client.status == "closed"


@pytest.mark.cluster
def test_two_worker_local_cluster_builds_the_single_process_map(reference, local2, tmp_path):
    assert local2.kind == "local" and local2.workers == 2
    info = local2.client.scheduler_info()
    assert info["address"].startswith("tcp://127.0.0.1:")
    assert all(w.startswith("tcp://127.0.0.1:") for w in info["workers"])
    pids = local2.worker_pids()
    assert len(set(pids.values())) == 2 and os.getpid() not in pids.values()
    store = cm.BlockStore.beside(tmp_path / "m.h5", PARAMS, poses_per_block=PER_BLOCK)
    assert len(store.blocks) >= 10
    m = cm.build(PARAMS, executor=local2.executor, poses_per_block=PER_BLOCK, store=store)
    _same(m, reference)
    assert store.written == len(store.blocks) and store.reused == 0


@pytest.mark.cluster
def test_a_running_cluster_by_its_address(reference, local2):
    address = local2.client.scheduler.address  # tcp://127.0.0.1:<port>, as `dask scheduler`'s
    with scaleout.engine(address, 2, warm_up=["implantplan.systems.capability.maps"]) as eng:
        assert eng.kind == "remote" and eng.workers == 2 and address in eng.description
        _same(cm.build(PARAMS, executor=eng.executor, poses_per_block=PER_BLOCK), reference)
    assert eng.client.status == "closed"
    assert local2.client.status == "running"  # a cluster we did not start stays up
    with pytest.raises(InputError, match="--workers: .* 3 did not join"):
        with scaleout.engine(address, 3, join_timeout=0.5):
            pass


@pytest.mark.cluster
def test_a_task_failing_after_its_retries_is_reported_not_fatal(local2):
    got = dict(scaleout.run_unordered(local2, divmod, [(7, 2), (1, 0)],
                                      on_error=lambda i, e: type(e).__name__))  # fmt: skip
    assert got == {0: (3, 1), 1: "ZeroDivisionError"}


@pytest.mark.cluster
def test_a_worker_killed_mid_build_costs_only_its_blocks(reference, local2):
    pids = local2.worker_pids()
    killed = []

    def progress(done, total):
        if done == 2 and not killed:  # after two blocks, kill a worker that is running one
            busy = [w for w, keys in local2.client.processing().items() if keys] or list(pids)
            os.kill(pids[busy[0]], signal.SIGKILL)
            killed.append(pids[busy[0]])

    m = cm.build(PARAMS, executor=local2.executor, poses_per_block=PER_BLOCK, progress=progress)
    assert killed
    _same(m, reference)
    local2.client.wait_for_workers(2, timeout=60)  # the nanny restarted it
    assert killed[0] not in local2.worker_pids().values()


def test_an_interrupted_build_resumes_with_only_the_missing_blocks(reference, tmp_path):
    store = cm.BlockStore.beside(tmp_path / "m.h5", PARAMS, poses_per_block=PER_BLOCK)
    n = len(store.blocks)

    def stop_after_5(done, total):
        if done == 5:
            raise KeyboardInterrupt

    partial = store.folder / ".block-000006.npz.abc123.npz"  # as a signal mid-write leaves it

    def stop_after_5_mid_write(done, total):
        if done == 5:
            partial.write_bytes(b"half a block")
        stop_after_5(done, total)

    with pytest.raises(KeyboardInterrupt):
        cm.build(PARAMS, workers=1, poses_per_block=PER_BLOCK, progress=stop_after_5_mid_write,
                 store=store)
    assert store.finished() == list(range(5))
    assert not partial.exists()  # the stopped build removed its temporary file
    partial.write_bytes(b"left by a killed build")  # SIGKILL: no cleanup ran
    # a block file that does not read back as its block is recomputed, not trusted
    (store.folder / "block-000003.npz").write_bytes(b"not a block")
    resumed = cm.BlockStore.beside(tmp_path / "m.h5", PARAMS, poses_per_block=PER_BLOCK)
    assert resumed.folder == store.folder
    computed = []
    m = cm.build(
        PARAMS,
        workers=1,
        poses_per_block=PER_BLOCK,
        store=resumed,
        progress=lambda done, total: computed.append(done),
    )
    _same(m, reference)
    assert not partial.exists()  # the resumed build removed it
    assert resumed.reused == 4 and resumed.written == n - 4
    assert computed[0] == 4 and computed[-1] == n  # first call reports the 4 reused blocks
    # another map (different parameters or block size) gets another folder
    other = cm.BlockStore.beside(tmp_path / "m.h5", cm.make_params(0.15, 31))
    assert other.folder != store.folder
    assert cm.BlockStore.beside(tmp_path / "m.h5", PARAMS).folder != store.folder


def test_scheduler_arguments_are_checked():
    assert scaleout.check_scheduler(None, 1) == ("process", 1)
    assert scaleout.check_scheduler(None, 3) == ("local", 3)
    assert scaleout.check_scheduler("tcp://10.0.0.5:8786", None) == ("remote", None)
    with pytest.raises(InputError, match="--scheduler: expected 'local' or an address"):
        scaleout.check_scheduler("10.0.0.5", None)
    with pytest.raises(InputError, match="--workers: expected an integer >= 1"):
        scaleout.check_scheduler("local", 0)
    with pytest.raises(InputError, match="--scheduler: cannot reach"):
        with scaleout.engine("tcp://127.0.0.1:9", connect_timeout=1.0):
            pass


def test_in_process_engine_runs_tasks_in_order():
    with scaleout.engine(None, 1) as eng:
        assert eng.executor is None and eng.worker_pids() == {"this process": os.getpid()}
        assert list(scaleout.run_unordered(eng, pow, [(2, 3), (3, 2)])) == [(0, 8), (1, 9)]
        got = scaleout.run_unordered(eng, divmod, [(7, 2), (1, 0)], on_error=lambda i, e: repr(e))
        assert list(got) == [
            (0, (3, 1)),
            (1, "ZeroDivisionError('integer division or modulo by zero')"),
        ]
        with pytest.raises(ZeroDivisionError):
            list(scaleout.run_unordered(eng, divmod, [(1, 0)]))
    eta = scaleout.Eta(10, skipped=4)
    assert eta(4) is None and eta.text(4) == "ETA --"


@pytest.mark.cluster
def test_the_local_cluster_binds_loopback_at_free_ports():
    """No fixed port (Dask's dashboard default, 8787) and nothing outside 127.0.0.1."""
    from urllib.parse import urlparse

    cluster = scaleout.local_cluster(1)
    try:
        dash = urlparse(cluster.dashboard_link)
        sched = urlparse(cluster.scheduler_address)
        assert dash.hostname == "127.0.0.1" and dash.port != 8787
        assert sched.hostname == "127.0.0.1"
    finally:
        cluster.close()
