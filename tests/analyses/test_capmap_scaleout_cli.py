"""``implantplan capmap build --scheduler/--workers/--resume``: an interrupted build keeps its
finished blocks, ``--resume`` computes only the missing ones and gives the map an uninterrupted
build gives; Ctrl-C on a LocalCluster build (a real SIGINT to the process group, slow: its own
process and cluster) leaves no worker process behind."""

import glob
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import psutil
import pytest

from implantplan.analyses.cli import main
from implantplan.systems.capability import maps as cm

# 21 blocks of <= 10k poses (tens of ms each): Ctrl-C lands with most of them left
ARGS = ["capmap", "build", "--voxel-mm", "150", "--directions", "30", "--block-poses", "10000"]


def _same_as_uninterrupted(out) -> None:
    ref = cm.build(cm.make_params(0.15, 30), workers=1)
    m = cm.load(out)
    np.testing.assert_array_equal(m.voxel_ids, ref.voxel_ids)
    np.testing.assert_array_equal(m.reach_bits, ref.reach_bits)
    np.testing.assert_array_equal(m.all_roll_bits, ref.all_roll_bits)


def test_interrupted_build_resumes_with_only_the_missing_blocks(tmp_path, capsys, monkeypatch):
    out = tmp_path / "m.h5"
    real = cm.build_block
    calls = []

    def interrupted(params, ids):  # Ctrl-C arrives while the 4th block is computed
        calls.append(1)
        if len(calls) == 4:
            raise KeyboardInterrupt
        return real(params, ids)

    monkeypatch.setattr(cm, "build_block", interrupted)
    assert main([*ARGS, "--workers", "1", "--out", str(out)]) == 130
    monkeypatch.setattr(cm, "build_block", real)
    assert "interrupted" in capsys.readouterr().err and not out.exists()
    (folder,) = glob.glob(str(tmp_path / "m.h5.blocks-*"))
    assert len(glob.glob(os.path.join(folder, "block-*.npz"))) == 3
    assert main([*ARGS, "--workers", "1", "--out", str(out)]) == 2
    assert "holds 3 of 21 blocks" in capsys.readouterr().err
    assert main([*ARGS, "--workers", "1", "--resume", "--out", str(out)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert (summary["blocks"], summary["blocks_reused"], summary["blocks_computed"]) == (21, 3, 18)
    assert not os.path.exists(folder)
    _same_as_uninterrupted(out)


@pytest.mark.slow
def test_ctrl_c_then_resume_computes_only_the_missing_blocks(tmp_path, capsys):
    out = tmp_path / "m.h5"
    cmd = [sys.executable, "-m", "implantplan.analyses.cli", *ARGS, "--workers", "2",
           "--scheduler", "local", "--out", str(out)]  # fmt: skip
    # its own session: the test sends SIGINT to the whole process group, as a terminal's Ctrl-C
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # fmt: skip
    children = {}  # pid -> psutil.Process: everything the command started
    deadline = time.monotonic() + 120
    while len(glob.glob(str(tmp_path / "m.h5.blocks-*" / "block-*.npz"))) < 2:
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        children.update({c.pid: c for c in psutil.Process(proc.pid).children(recursive=True)})
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    assert not out.exists()
    # the workers (and multiprocessing's resource tracker) end with the command
    _, alive = psutil.wait_procs(list(children.values()), timeout=10)
    assert len(children) >= 2 and alive == []
    (folder,) = glob.glob(str(tmp_path / "m.h5.blocks-*"))
    done_before = len(glob.glob(os.path.join(folder, "block-*.npz")))
    assert done_before >= 2

    # without --resume the finished blocks are not thrown away silently
    assert main([*ARGS, "--workers", "1", "--out", str(out)]) == 2
    assert "pass --resume" in capsys.readouterr().err
    assert main([*ARGS, "--workers", "1", "--resume", "--out", str(out)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["blocks_reused"] == done_before
    assert summary["blocks_computed"] == summary["blocks"] - done_before > 0
    assert not os.path.exists(folder)  # the store goes once the map is written
    _same_as_uninterrupted(out)
