"""Provenance of a plan (DESIGN.md section 9): what made it, from what, when.

``plan.json`` carries a ``provenance`` block so a plan can be traced to the software and the
inputs that produced it (IEC 62304-style traceability): the implantplan version and, when run from
a git checkout, its commit (and whether the work tree had uncommitted changes); the versions of
Python and the numerical dependencies; the command line; the UTC time; the sha256 of the case file
and of every mesh read; the seed. Like ``timing``, it differs between two runs of the same case;
:func:`without_volatile` removes it and every timing value, which is what two plans of the same
case and seed are compared on.
"""

from __future__ import annotations

import hashlib
import platform
import subprocess
import sys
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path

# Keys of plan.json that change from run to run of the same case and seed: top level, in each
# site's placement, in each site's simulation and in each of its runs.
VOLATILE_KEYS = ("timing", "provenance")
VOLATILE_PLACEMENT_KEYS = ("seconds",)
VOLATILE_SIMULATION_KEYS = ("realtime_factor",)
VOLATILE_RUN_KEYS = ("wall_seconds",)

# Distributions whose versions decide the numbers in a plan (absent ones are left out).
DEPENDENCIES = ("drake", "numpy", "scipy", "trimesh", "embreex", "numba", "python-fcl", "coal",
                "dask", "distributed", "h5py", "matplotlib", "PyYAML")

_SOURCE = Path(__file__).resolve().parents[1]  # the checkout, for an editable install


def sha256_file(path: str | Path, *, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(chunk), b""):
            h.update(block)
    return h.hexdigest()


def git_commit(source: Path = _SOURCE) -> dict | None:
    """``{"commit", "dirty"}`` of the checkout the code runs from, or None outside one (an
    installed wheel) or without git."""
    if not (source / ".git").exists():
        return None
    try:
        head = subprocess.run(["git", "-C", str(source), "rev-parse", "HEAD"], capture_output=True,
                              text=True, timeout=5, check=True).stdout.strip()
        status = subprocess.run(["git", "-C", str(source), "status", "--porcelain",
                                 "--untracked-files=no"], capture_output=True, text=True,
                                timeout=5, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    return {"commit": head, "dirty": bool(status.strip())}


def versions() -> dict:
    """Python and dependency versions (only the installed ones)."""
    out = {"implantplan": _version("implantplan") or "0+unknown",
           "python": platform.python_version()}
    for name in DEPENDENCIES:
        v = _version(name)
        if v is not None:
            out[name] = v
    return out


def _version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def provenance(*, case_file: str | Path | None, meshes: list[str | Path], seed: int,
               argv: list[str] | None = None) -> dict:
    """The provenance block of a plan.

    Args:
        case_file: the case YAML read (None for a case built in code).
        meshes: every mesh file read.
        seed: the case's seed.
        argv: the command line (default ``sys.argv``).
    """
    files = {}
    if case_file is not None:
        files["case"] = {"path": str(case_file), "sha256": sha256_file(case_file)}
    files["meshes"] = [{"path": str(m), "sha256": sha256_file(m)} for m in meshes]
    return {
        "software": versions(),
        "git": git_commit(),
        "command": list(sys.argv if argv is None else argv),
        "utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "platform": platform.platform(),
        "inputs": files,
        "seed": int(seed),
    }


def without_volatile(plan: dict) -> dict:
    """A copy of a plan without what changes between runs of the same case and seed (timings,
    provenance): two such copies are equal when the plans are the same."""
    out = {k: v for k, v in plan.items() if k not in VOLATILE_KEYS}
    sites = []
    for site in plan.get("sites", []):
        site = dict(site)
        if isinstance(site.get("placement"), dict):
            site["placement"] = {k: v for k, v in site["placement"].items()
                                 if k not in VOLATILE_PLACEMENT_KEYS}
        sim = site.get("simulation")
        if isinstance(sim, dict):
            sim = {k: v for k, v in sim.items() if k not in VOLATILE_SIMULATION_KEYS}
            sim["runs"] = [{k: v for k, v in r.items() if k not in VOLATILE_RUN_KEYS}
                           for r in sim.get("runs", [])]
            site["simulation"] = sim
        sites.append(site)
    if "sites" in plan:
        out["sites"] = sites
    return out
