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


def _yaml(tmp_path, text: str):
    path = tmp_path / "f.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("text, field, line, first", [
    ("a: 1\nb: 2\na: 3\n", "a", 3, 1),
    ("s:\n  x: 1\n  y: {p: 1, p: 2}\n", "s.y.p", 3, 3),
    ("l:\n  - {k: 1}\n  - {k: 1, j: 2, k: 3}\n", "l[1].k", 3, 3),
    ("m:\n  - [0, {q: 1}]\n  - [1, {q: 1,\n        q: 2}]\n", "m[1][1].q", 4, 3),
    ("1: a\n'1': b\n1: c\n", "1", 3, 1),  # the int key 1 twice (the text '1' is another key)
])
def test_a_duplicate_key_is_an_error_naming_its_path_and_lines(tmp_path, text, field, line,
                                                               first):
    with pytest.raises(InputError) as err:
        files.read_yaml(_yaml(tmp_path, text), field="case")
    assert err.value.field == field
    assert f"duplicate key in {tmp_path / 'f.yaml'} (line {line}, first given on line {first})" \
        in str(err.value)


def test_the_same_key_in_different_mappings_is_fine(tmp_path):
    data = files.read_yaml(_yaml(tmp_path, "a: {k: 1}\nb: {k: 2}\nl: [{k: 1}, {k: 2}]\n"))
    assert data == {"a": {"k": 1}, "b": {"k": 2}, "l": [{"k": 1}, {"k": 2}]}


def _alias_bomb(levels: int = 9) -> str:
    """The billion laughs: each level lists the previous one 9 times (9^9 strings expanded)."""
    lines = ['l0: &l0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for k in range(1, levels):
        lines.append(f"l{k}: &l{k} [" + ", ".join([f"*l{k - 1}"] * 9) + "]")
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("text, what, line", [
    (_alias_bomb(), "anchor &l0", 1),
    ("base: {a: 1}\ncopy: *base\n", "alias *base", 2),
    ("base: &b {a: 1}\nmore: {<<: *b, c: 2}\n", "anchor &b", 1),
])
def test_anchors_and_aliases_are_refused(tmp_path, text, what, line):
    assert len(_alias_bomb()) < 2000  # a small file: what matters is that nothing is expanded
    with pytest.raises(InputError) as err:
        files.read_yaml(_yaml(tmp_path, text), field="scenario")
    assert err.value.field == "scenario"
    message = str(err.value)
    assert f"line {line}:" in message and "aliases are not supported" in message
    assert f"(found {what})" in message
