"""Reading and writing project files: atomic writes, schema versions, YAML/JSON loading.

Every file the project writes carries ``schema_version`` and is written atomically (a temporary
file in the same folder, then ``os.replace``), so a crash never leaves half a file behind and a
file already there is kept until the new one is complete.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
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
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual file mode
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def _umask() -> int:
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
    """Load a YAML mapping with a clear error for a missing file or malformed YAML."""
    path = Path(path)
    data = _parsed(path, field, yaml.safe_load, yaml.YAMLError, "YAML")
    if not isinstance(data, dict):
        raise InputError(field, f"{path} must hold a YAML mapping at the top level")
    return data


def _parsed(path: Path, field: str, loads, error, what: str) -> Any:
    """``loads`` of the file's text; a missing file or a parse ``error`` is an InputError."""
    if not path.is_file():
        raise InputError(field, f"file {str(path)!r} does not exist")
    try:
        return loads(path.read_text(encoding="utf-8"))
    except error as exc:
        raise InputError(field, f"{path} is not valid {what} ({exc})") from None


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
