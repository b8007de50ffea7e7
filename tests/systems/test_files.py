"""Atomic, versioned project files."""

import json

import numpy as np
import pytest

from implantplan.systems import files
from implantplan.systems.errors import InputError


def test_json_round_trip_and_header(tmp_path):
    path = tmp_path / "a.json"
    files.write_json(path, {"x": np.arange(3), "y": np.float64(1.5), "z": np.nan}, kind="demo")
    data = files.read_json(path, kind="demo")
    assert list(data)[:2] == ["schema_version", "kind"]
    assert data["x"] == [0, 1, 2] and data["y"] == 1.5 and data["z"] is None


def test_failed_write_keeps_the_old_file(tmp_path):
    path = tmp_path / "a.json"
    files.write_json(path, {"v": 1})

    def broken(tmp):
        tmp.write_text("half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        files.write_atomic(path, broken)
    assert json.loads(path.read_text())["v"] == 1
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]


def test_bad_files_name_the_field(tmp_path):
    with pytest.raises(InputError, match="plan: file .* does not exist"):
        files.read_json(tmp_path / "missing.json", field="plan")
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1, 2\n")
    with pytest.raises(InputError, match="case: .* not valid YAML"):
        files.read_yaml(bad, field="case")
    old = tmp_path / "old.json"
    old.write_text('{"schema_version": 99}')
    with pytest.raises(InputError, match="schema_version 99"):
        files.read_json(old)


def test_written_files_get_the_usual_mode(tmp_path):
    import os

    path = files.write_json(tmp_path / "m.json", {"v": 1})
    mask = os.umask(0)
    os.umask(mask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~mask
