"""The keyed on-disk store of computed RASSCMAPs (seed 004: maps are reused across runs).

A map is stored under the hash of everything it depends on; a changed input or a new
``STORE_VERSION`` (bumped when the RASSCMAP algorithm changes) is a miss, never a stale hit.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import h5py
import numpy as np

from implantplan.systems.capability.rasscmap import Instrument, Rasscmap, Trocar
from implantplan.systems.files import write_atomic

SCHEMA_VERSION = 1


STORE_VERSION = 1  # bump when the RASSCMAP algorithm changes (invalidates stored maps)


class RasscmapStore:
    """On-disk store of RASSCMAPs keyed by everything they depend on (reused across runs).

    The key hashes the CMAP's parameter key, the map kind, its geometric inputs (access pose,
    trocar, instrument, voxel, rotation step) and the base pose, plus ``STORE_VERSION``. One HDF5
    file per key under ``root/ab/<key>.h5``, written atomically. Constrained maps only: an
    unconstrained RASSCMAP is a CMAP lookup of ~25 us per base, cheaper than opening a file.
    """

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        self.hits = 0
        self.misses = 0

    @staticmethod
    def key(**parts) -> str:
        def norm(v):
            if isinstance(v, np.ndarray):
                return np.round(v.astype(float), 9).tolist()
            if isinstance(v, (Trocar, Instrument)):
                return {k: round(float(x), 9) for k, x in v.__dict__.items()}
            if isinstance(v, float):
                return round(v, 9)
            return v

        text = json.dumps(
            {"v": STORE_VERSION, **{k: norm(v) for k, v in parts.items()}}, sort_keys=True
        )
        return hashlib.sha256(text.encode()).hexdigest()[:24]

    def path(self, key: str) -> Path:
        return self.root / key[:2] / f"{key}.h5"

    def get(self, key: str) -> Rasscmap | None:
        p = self.path(key)
        if not p.is_file():
            self.misses += 1
            return None
        try:
            with h5py.File(p, "r") as f:
                if int(f.attrs.get("schema_version", -1)) != SCHEMA_VERSION:
                    self.misses += 1
                    return None
                K = int(f.attrs["directions"])
                r = Rasscmap(
                    f["centres"][()], np.unpackbits(f["reach"][()], axis=1, count=K).astype(bool),
                    f["index"][()], float(f.attrs["voxel"]),
                    f["origin"][()] if "origin" in f else None, str(f.attrs["kind"]),
                    json.loads(f.attrs["timings"]),
                )  # fmt: skip
        except (OSError, KeyError):
            self.misses += 1
            return None
        self.hits += 1
        return r

    def put(self, key: str, r: Rasscmap) -> None:
        def writer(tmp):
            with h5py.File(tmp, "w") as f:
                f.attrs["schema_version"] = SCHEMA_VERSION
                f.attrs["kind"] = r.kind
                f.attrs["voxel"] = r.voxel
                f.attrs["directions"] = r.reach.shape[1]
                f.attrs["timings"] = json.dumps(r.timings)
                f.create_dataset("centres", data=r.centres)
                f.create_dataset("reach", data=np.packbits(r.reach, axis=1))
                f.create_dataset("index", data=r.index)
                if r.origin is not None:
                    f.create_dataset("origin", data=r.origin)

        write_atomic(self.path(key), writer)
