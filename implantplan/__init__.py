"""implantplan: planning and teleoperation simulation for robot-assisted dental implant surgery.

One import package: the folders ``systems/``, ``diagrams/``, ``analyses/`` and ``models/`` at the
repository root install as ``implantplan.systems``, ``implantplan.diagrams``,
``implantplan.analyses`` and ``implantplan.models`` (DESIGN.md section 2). Layers import downward
only: models <- systems <- diagrams <- analyses.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("implantplan")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"


def _numba_cache_dir() -> None:
    """Give numba's compiled-kernel cache a folder this user can write.

    numba caches beside the source file, or (for a read-only install) in a user-wide folder; when
    neither is writable (a wheel installed by root, run by an ordinary user whose HOME is read-only)
    every ``cache=True`` kernel raises at import. NUMBA_CACHE_DIR set by the user is kept;
    otherwise the first writable of $XDG_CACHE_HOME (or ~/.cache)/implantplan/numba and the
    system temp folder (per user) is used. It must be set before numba is first imported.
    """
    import os
    import tempfile
    from pathlib import Path

    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    uid = os.getuid() if hasattr(os, "getuid") else "user"
    candidates = []
    try:
        base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
        candidates.append(Path(base) / "implantplan" / "numba")
    except (RuntimeError, KeyError):  # no home directory for this user
        pass
    try:
        candidates.append(Path(tempfile.gettempdir()) / f"implantplan-numba-{uid}")
    except OSError:  # no writable temp folder at all
        pass
    for folder in candidates:
        try:
            folder.mkdir(parents=True, exist_ok=True)
            with tempfile.NamedTemporaryFile(dir=folder):
                pass
        except OSError:
            continue
        os.environ["NUMBA_CACHE_DIR"] = str(folder)
        return


_numba_cache_dir()
