"""Output folders belong to the user (DESIGN.md section 3, "Output folders").

A folder the project makes (a plan folder, a batch folder, a capability-map plan folder) carries
a marker file, :data:`MARKER`. ``--out`` is checked before any work (:func:`check_out`):

- an empty text, ``.``, the current folder or one of its parents, a symbolic link (a loop
  included), a file, a device or a FIFO, a parent that cannot be written: exit 2 with what it is;
- an existing folder that holds anything and no marker, or a marked folder holding entries the
  project did not write there (the marker of a folder completed atomically lists its entries):
  exit 2 naming some of them, unless ``force`` (``--force``): what the user keeps there is never
  replaced silently.

A folder is built in a staging folder beside its destination (:func:`staged`) and moved in at the
end: the previous folder stays whole until the new one is complete. Staging folders and the
previous folder while it is being replaced are named
``.<name>.implantplan-staging-<pid>-<random>`` and ``.<name>.implantplan-old-<pid>-<ns>``: a run
that was killed (``kill -KILL``, a power cut) leaves them behind, and the next run towards the
same ``--out`` removes those whose process is gone (:func:`remove_stale`). ``SIGTERM`` is turned
into the same ``KeyboardInterrupt`` as Ctrl-C by the CLI (analyses.cli), so the ``finally`` of
:func:`staged` removes the staging folder in both cases.
"""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import stat
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from implantplan import __version__
from implantplan.systems.errors import InputError
from implantplan.systems.files import current_umask

MARKER = ".implantplan-folder"
STAGING = "implantplan-staging"
OLD = "implantplan-old"
_LEFTOVER = re.compile(rf"^\.(?P<name>.+)\.(?:{STAGING}|{OLD})-(?P<pid>\d+)-[A-Za-z0-9_]+$")


# What a plan folder written before the marker existed holds (plan, demo, studio recordings)
_PLAN_ENTRIES = re.compile(r"^(plan\.json|fpsm\.json|report\.html|layout\.html|figures|"
                           r"recordings|scene_[A-Za-z0-9_.-]+\.html)$")


def is_project_folder(path: Path) -> bool:
    """``path`` is a folder the project made: it holds :data:`MARKER`, or it is a plan folder
    of a version before the marker (a ``plan.json`` of kind "plan" and nothing but the entries a
    plan folder has)."""
    path = Path(path)
    if (path / MARKER).is_file():
        return True
    try:
        entries = os.listdir(path)
        if "plan.json" not in entries or not all(_PLAN_ENTRIES.match(e) for e in entries):
            return False
        with open(path / "plan.json", encoding="utf-8") as f:
            head = f.read(200)
    except (OSError, UnicodeDecodeError):
        return False
    return re.search(r'"kind":\s*"plan"', head) is not None


def foreign_entries(path: Path) -> list[str]:
    """The entries of an existing folder ``path`` that the project did not write: all of them
    in a folder that is not the project's (:func:`is_project_folder`); in a marked folder that
    was completed atomically (:func:`staged` records its entries in the marker), those not
    recorded there, besides what a plan folder gains later (studio recordings, scenes): a file
    the user put into a plan folder is theirs too. Sorted."""
    path = Path(path)
    entries = sorted(os.listdir(path))
    if not is_project_folder(path):
        return entries
    try:
        written = json.loads((path / MARKER).read_text()).get("entries")
    except (OSError, ValueError, AttributeError):
        written = None  # an old plan folder, or a marker of a folder written file by file
    if not isinstance(written, list):
        return []
    return [e for e in entries
            if e != MARKER and e not in written and not _PLAN_ENTRIES.match(e)]


def _kind_of(st: os.stat_result) -> str:
    mode = st.st_mode
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "a file"


def check_out(out, *, force: bool | None = False, field: str = "--out") -> Path:
    """``out`` checked as an output folder before any work (module docstring); returns it as an
    absolute path (symbolic links in its parents kept). Stale staging folders of earlier runs
    towards it are removed. ``force`` None: the command has no ``--force`` (a folder of the
    user's is refused, and the message does not offer the flag)."""
    text = os.fspath(out) if out is not None else ""
    if not text.strip():
        raise InputError(field, "expected a folder path, got an empty text")
    path = Path(os.path.abspath(text))
    if Path(text).name in ("", ".", "..") or path == Path(path.anchor):
        raise InputError(field, f"expected a folder of its own, got {text!r} (a plan is built "
                         "beside its folder and moved in: give a new or a plan folder's name)")
    cwd = Path.cwd()
    if path == cwd or path in cwd.parents:
        raise InputError(field, f"{text!r} is the current folder or holds it; expected a folder "
                         "of its own")
    if path.is_symlink():
        try:
            os.stat(path)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                raise InputError(field, f"{text!r} is a symbolic link loop") from None
            raise InputError(field, f"{text!r} is a broken symbolic link") from None
        raise InputError(field, f"{text!r} is a symbolic link; give the folder it points to "
                         f"({os.path.realpath(path)!r}) instead")
    try:
        st = os.stat(path)
    except FileNotFoundError:
        st = None
    except OSError as exc:
        if exc.errno == errno.ENOTDIR:  # a file where a folder of the path should be
            _existing_ancestor(path.parent, text, field)
        what = "a symbolic link loop in its path" if exc.errno == errno.ELOOP else \
            (exc.strerror or str(exc))
        raise InputError(field, f"cannot use {text!r}: {what}") from None
    if st is not None and not stat.S_ISDIR(st.st_mode):
        raise InputError(field, f"{text!r} is {_kind_of(st)}, not a folder")
    parent = _existing_ancestor(path.parent, text, field)
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(field, f"cannot write in {str(parent)!r} (permission denied)")
    try:  # what permissions cannot tell (root, a read-only or special file system): try it
        os.rmdir(tempfile.mkdtemp(prefix=".implantplan-probe-", dir=parent))
    except OSError as exc:
        raise InputError(field, f"cannot create a folder in {str(parent)!r}: "
                         f"{exc.strerror or exc}") from None
    if st is not None:
        if not os.access(path, os.R_OK | os.W_OK | os.X_OK):
            raise InputError(field, f"cannot read and write {text!r} (permission denied)")
        entries = foreign_entries(path)
        if entries and not force:
            shown = ", ".join(repr(e) for e in entries[:3])
            more = f" and {len(entries) - 3} more" if len(entries) > 3 else ""
            offer = "" if force is None else ", or --force to replace it"
            raise InputError(field, f"{text!r} holds files implantplan did not write "
                             f"({shown}{more}); give a new or empty folder{offer}")
    if path.parent.is_dir():
        remove_stale(path)
    return path


def _existing_ancestor(folder: Path, text: str, field: str) -> Path:
    """The nearest existing folder at or above ``folder`` (where the output will be created)."""
    for p in (folder, *folder.parents):
        try:
            st = os.stat(p)
        except (FileNotFoundError, NotADirectoryError):
            continue
        except OSError as exc:
            what = "a symbolic link loop" if exc.errno == errno.ELOOP else \
                (exc.strerror or str(exc))
            raise InputError(field, f"cannot use {text!r}: {what} at {str(p)!r}") from None
        if not stat.S_ISDIR(st.st_mode):
            raise InputError(field, f"cannot create {text!r}: {str(p)!r} is {_kind_of(st)}, "
                             "not a folder")
        return p
    return Path(folder.anchor)


def _alive(pid: int) -> bool:
    """The process ``pid`` runs: it exists and has not exited (a zombie, exited and not yet
    reaped, has: the worker of a killed batch is one until the process it was handed to reaps
    it)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return not _zombie(pid)


def _zombie(pid: int) -> bool:
    """``pid`` has exited and waits to be reaped (Linux's /proc; False where it cannot tell)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            text = f.read()
    except OSError:
        return False
    return text[text.rfind(b")") + 2:][:1] == b"Z"  # the state follows "(command) "


def leftovers(out: Path) -> list[Path]:
    """Staging and old folders beside ``out`` left by runs towards it whose process is gone."""
    out = Path(out)
    return _leftovers_in(out.parent, out.name)


def _leftovers_in(folder: Path, name: str | None) -> list[Path]:
    """Staging and old folders in ``folder`` (towards ``name``, None: any) whose process is
    gone."""
    found = []
    try:
        entries = list(Path(folder).iterdir())
    except OSError:
        return []
    for entry in entries:
        m = _LEFTOVER.match(entry.name)
        if m and (name is None or m["name"] == name) and not _alive(int(m["pid"])) \
                and entry.is_dir() and not entry.is_symlink():
            found.append(entry)
    return found


def remove_stale(out: Path) -> list[Path]:
    """Remove :func:`leftovers` that hold the marker or nothing (nothing else is ours: a folder
    of the user's renamed aside by a ``--force`` run that was killed stays)."""
    return _remove(leftovers(out))


def remove_stale_inside(folder: Path) -> list[Path]:
    """Remove the leftovers of runs towards any folder inside ``folder`` (a batch folder: its
    cases' staging folders, named with the pid of the worker process that planned the case),
    as :func:`remove_stale` does beside one."""
    return _remove(_leftovers_in(Path(folder), None))


def _remove(found: list[Path]) -> list[Path]:
    removed = []
    for entry in found:
        if is_project_folder(entry) or not any(entry.iterdir()):
            shutil.rmtree(entry, ignore_errors=True)
            removed.append(entry)
    return removed


def claim(folder: Path, kind: str) -> Path:
    """Make ``folder`` (checked by :func:`check_out` before the work) and mark it: the output
    folder of a command that writes its files one by one (studies), not atomically."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    mark(folder, kind)
    return folder


def mark(folder: Path, kind: str, *, entries: list[str] | None = None) -> Path:
    """Write the marker into ``folder`` (what made it, for the next run's check; with
    ``entries``, the folder's entries as written: anything else found there later is the
    user's, :func:`foreign_entries`)."""
    marker = Path(folder) / MARKER
    data = {"schema_version": 1, "kind": kind, "written_by": f"implantplan {__version__}"}
    if entries is not None:
        data["entries"] = list(entries)
    marker.write_text(json.dumps(data) + "\n")
    return marker


@contextmanager
def staged(out: Path, kind: str, *, field: str = "--out") -> Iterator[Path]:
    """A staging folder beside ``out`` (marked); when the block ends without an exception it
    replaces ``out`` atomically (``out`` renamed aside, the staging folder renamed in, the old
    one removed); in every case the staging folder is gone afterwards."""
    out = Path(out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.{STAGING}-{os.getpid()}-",
                                    dir=out.parent))
    except OSError as exc:
        raise InputError(field, f"cannot create a folder in {str(out.parent)!r}: "
                         f"{exc.strerror or exc}") from None
    try:
        tmp.chmod(0o777 & ~current_umask())  # mkdtemp makes 0700; a plan is for colleagues too
        mark(tmp, kind)
        yield tmp
        mark(tmp, kind, entries=sorted(e for e in os.listdir(tmp) if e != MARKER))
        swap_in(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def swap_in(staging: Path, out: Path) -> None:
    """Move ``staging`` onto ``out``; a previous ``out`` is renamed aside first and removed
    after (a kill in between leaves it under an ``old`` name the next run removes)."""
    old = None
    if out.exists():
        old = out.with_name(f".{out.name}.{OLD}-{os.getpid()}-{time.time_ns()}")
        out.rename(old)
    staging.rename(out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
