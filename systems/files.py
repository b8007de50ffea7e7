"""Reading and writing project files: atomic writes, schema versions, YAML/JSON loading.

Every file the project writes carries ``schema_version`` and is written atomically (a temporary
file in the same folder, then ``os.replace``), so a crash never leaves half a file behind and a
file already there is kept until the new one is complete.
"""

from __future__ import annotations

import errno
import json
import os
import stat
import tempfile
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from implantplan.systems.errors import InputError

SCHEMA_VERSION = 1


def to_jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        value = float(obj)
        return value if np.isfinite(value) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_atomic(path: str | os.PathLike, writer: Callable[[Path], None]) -> Path:
    """Call ``writer(tmp_path)`` then move the temporary file onto ``path`` atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        writer(tmp)
        os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp makes 0600; give the usual file mode
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def current_umask() -> int:
    """The process's file-mode creation mask (read without changing it)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    return write_atomic(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


def write_json(path: str | os.PathLike, data: dict, *, kind: str | None = None) -> Path:
    """Write ``data`` as JSON with ``schema_version`` (and ``kind``) first; NaN/inf become null."""
    head = {"schema_version": data.get("schema_version", SCHEMA_VERSION)}
    if kind is not None:
        head["kind"] = kind
    body = {**head, **{k: v for k, v in data.items() if k not in head}}
    text = json.dumps(to_jsonable(body), indent=1, allow_nan=False)
    return write_text_atomic(path, text + "\n")


def read_json(path: str | os.PathLike, *, kind: str | None = None, field: str = "file") -> dict:
    """Load a project JSON file, checking it exists, parses, and has a known schema_version."""
    path = Path(path)
    data = _parsed(path, field, json.loads, json.JSONDecodeError, "JSON")
    return _check_header(data, path, kind, field)


def read_yaml(path: str | os.PathLike, *, field: str = "file") -> dict:
    """Load a YAML mapping: the one YAML reader of the project (cases, scenarios, RASSCMAP inputs,
    cohorts).

    A missing file or malformed YAML is an InputError naming ``field``; so are a key given twice
    in one mapping (named by its dotted path, ``fpsm.slices`` or ``obstacles[2].name``, with both
    lines: YAML's own rule would let the last one win silently) and any anchor or alias
    (``&name``, ``*name``, so also ``<<`` merges): a few aliases expand to gigabytes, and no
    project file needs them.
    """
    path = Path(path)
    data = _parsed(path, field, partial(_strict_yaml, path=path, field=field), yaml.YAMLError,
                   "YAML")
    if not isinstance(data, dict):
        raise InputError(field, f"{path} must hold a YAML mapping at the top level")
    return data


class _StrictLoader(yaml.SafeLoader):
    """PyYAML's safe loader that refuses anchors and aliases while composing (before anything
    is expanded)."""

    def compose_node(self, parent, index):
        event = self.peek_event()
        if isinstance(event, yaml.AliasEvent) or getattr(event, "anchor", None) is not None:
            kind = "alias *" if isinstance(event, yaml.AliasEvent) else "anchor &"
            raise _Refused(f"{kind}{event.anchor}", event.start_mark.line + 1)
        return super().compose_node(parent, index)


class _Refused(Exception):
    def __init__(self, what: str, line: int):
        super().__init__(what)
        self.what, self.line = what, line


def _strict_yaml(text: str, *, path: Path, field: str) -> Any:
    """The document in ``text``, refusing anchors, aliases and duplicate keys (InputError)."""
    loader = _StrictLoader(text)
    try:
        try:
            node = loader.get_single_node()
        except _Refused as exc:
            raise InputError(field, f"{path} line {exc.line}: YAML anchors and aliases are not "
                             f"supported (found {exc.what}); write the value out in full") from None
        if node is None:
            return None
        _check_keys(loader, node, "", path)
        return loader.construct_document(node)
    finally:
        loader.dispose()


def _check_keys(loader: yaml.SafeLoader, node: yaml.Node, where: str, path: Path) -> None:
    """Every mapping below ``node`` holds each key once; a repeat is an InputError naming the
    key's dotted path (as systems.validate names fields) and both lines."""
    if isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            _check_keys(loader, item, f"{where}[{i}]", path)
    elif isinstance(node, yaml.MappingNode):
        seen = {}
        for key_node, value_node in node.value:
            key = (loader.construct_object(key_node, deep=True)
                   if isinstance(key_node, yaml.ScalarNode) else None)
            name = f"{where}.{key}" if where else str(key)
            if key is not None:
                if key in seen:
                    raise InputError(name, f"duplicate key in {path} (line "
                                     f"{key_node.start_mark.line + 1}, first given on line "
                                     f"{seen[key]}); each key may appear once")
                seen[key] = key_node.start_mark.line + 1
            _check_keys(loader, value_node, name, path)


MAX_TEXT_BYTES = 1_000_000  # a case, scenario, cohort or plan file (docs/formats.md, Bounds)
MAX_MESH_BYTES = 500_000_000  # a scan file


def input_file(path: str | os.PathLike, field: str, *, max_bytes: int | None = None) -> Path:
    """``path`` checked as a regular file to read, at most ``max_bytes`` long: a missing file, a
    folder, a device (``/dev/zero``), a FIFO, a socket, a broken link or a link loop, a file too
    large is an InputError naming ``field`` and saying which (nothing is opened before)."""
    path = Path(path)
    shown = repr(str(path))
    try:
        st = os.stat(path)
    except FileNotFoundError:
        if path.is_symlink():
            raise InputError(field, f"{shown} is a broken symbolic link") from None
        raise InputError(field, f"file {shown} does not exist") from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise InputError(field, f"{shown} is a symbolic link loop; expected a file") from None
        raise InputError(field, f"cannot read {shown}: {exc.strerror or exc}") from None
    mode = st.st_mode
    if stat.S_ISDIR(mode):
        raise InputError(field, f"{shown} is a folder; expected a file")
    if not stat.S_ISREG(mode):
        kind = ("a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else
                "a FIFO (named pipe)" if stat.S_ISFIFO(mode) else "not a regular file")
        raise InputError(field, f"{shown} is {kind}; expected a file")
    if max_bytes is not None and st.st_size > max_bytes:
        raise InputError(field, f"{shown} is {st.st_size / 1e6:.1f} MB; expected at most "
                         f"{max_bytes / 1e6:g} MB")
    return path


def _parsed(path: Path, field: str, loads, error, what: str) -> Any:
    """``loads`` of the file's text; a missing, folder, special, too large, unreadable or
    non-UTF-8 file or a parse ``error`` is an InputError."""
    input_file(path, field, max_bytes=MAX_TEXT_BYTES)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(field, f"cannot read {str(path)!r}: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise InputError(field, f"{str(path)!r} is not a UTF-8 text file") from None
    try:
        return loads(text)
    except error as exc:
        raise InputError(field, f"{path} is not valid {what} ({_one_line(exc)})") from None


def _one_line(exc: Exception) -> str:
    """A parser's message on one line: PyYAML's marked errors as 'line L, column C: problem'
    (their text spans lines, with a copy of the offending line), others with their white space
    folded."""
    mark, problem = getattr(exc, "problem_mark", None), getattr(exc, "problem", None)
    if mark is not None and problem:
        context = getattr(exc, "context", None)
        return " ".join(f"line {mark.line + 1}, column {mark.column + 1}: "
                        f"{context + ': ' if context else ''}{problem}".split())
    return " ".join(str(exc).split())


def _check_header(data: Any, path: Path, kind: str | None, field: str) -> dict:
    if not isinstance(data, dict):
        raise InputError(field, f"{path} must hold a JSON object")
    version = data.get("schema_version")
    if version != SCHEMA_VERSION:
        raise InputError(
            field, f"{path} has schema_version {version!r}; this version reads {SCHEMA_VERSION}"
        )
    if kind is not None and data.get("kind") != kind:
        raise InputError(field, f"{path} is a {data.get('kind')!r} file, expected {kind!r}")
    return data
