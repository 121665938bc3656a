"""A cache of the built Dataset beside its MCAP files, for the commands that build the same one in turn
(`fuelid dataset`, `identify`, `compare`, `diagnose`, `report`, `online`).

One file beside the first MCAP, `.NAME.dataset-cache.npz` (hidden), holds one Dataset and the key it was built
under: a BLAKE2b digest of every input file's name and whole content (in the order given), the build options, and the
code that makes a Dataset (the modules of the dataset path and the DBC). A build under another key rebuilds
and replaces the file, so a recording changed in any byte, other options or another fuelid never get a stale
Dataset; a cache file that does not load is rebuilt too. Writing is best effort (a read-only folder means no
cache) and atomic (a temporary file renamed over it). `--no-cache` or FUELID_DATASET_CACHE=0 turns it off.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Callable

import numpy as np

from fuelid.dbc import FMS_DBC
from fuelid.ident import dataset
from fuelid.ident.dataset import Dataset
from fuelid.logger import columns, decode, j1939, mcap_log

FORMAT = "fuelid dataset cache v1"
_CODE = [Path(m.__file__) for m in (dataset, columns, decode, j1939, mcap_log)] + [Path(__file__), FMS_DBC]


def cache_path(first: Path) -> Path:
    """Where the cache of a build whose first file is `first` is written."""
    return first.with_name(f".{first.name}.dataset-cache.npz")


def cache_key(paths: list[Path], options: dict) -> str:
    """The digest of the files' names and contents, the options and the dataset code (hex)."""
    h = hashlib.blake2b(digest_size=32)
    names = [str(p.resolve()) for p in paths]  # the notes name the files
    h.update(json.dumps([FORMAT, options, names], sort_keys=True, default=str).encode())
    for p in _CODE + paths:
        with open(p, "rb") as f:
            h.update(hashlib.file_digest(f, "blake2b").digest())
    return h.hexdigest()


def cached_dataset(paths, options: dict, build: Callable[[], Dataset], enabled: bool = True) -> Dataset:
    """The Dataset `build()` gives for the MCAP `paths` built with `options`, from the cache when its key matches
    (see the module docstring), else built and stored."""
    paths = [Path(p) for p in paths]
    if not enabled or os.environ.get("FUELID_DATASET_CACHE") == "0" or not all(p.is_file() for p in paths):
        return build()  # a missing file: build_dataset's own error
    key = cache_key(paths, options)
    where = cache_path(paths[0])
    ds = _load(where, key)
    if ds is None:
        ds = build()
        _store(where, key, ds)
    return ds


def _load(where: Path, key: str) -> Dataset | None:
    try:
        with np.load(where, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            if meta["format"] != FORMAT or meta["key"] != key:
                return None
            return Dataset(
                Ts=meta["Ts"], t=z["t"], u=z["u"], y=z["y"], input_names=tuple(meta["input_names"]),
                input_units=tuple(meta["input_units"]), output_name=meta["output_name"],
                output_unit=meta["output_unit"], u0=z["u0"], y0=meta["y0"], valid=z["valid"], cycle=z["cycle"],
                extra={name: z[f"extra{i}"] for i, name in enumerate(meta["extra"])},
                sources=meta["sources"], notes=meta["notes"])
    except (OSError, ValueError, KeyError, TypeError, EOFError):  # none yet, or not a cache file: build
        return None


def _store(where: Path, key: str, ds: Dataset) -> None:
    meta = {"format": FORMAT, "key": key, "Ts": ds.Ts, "input_names": ds.input_names,
            "input_units": ds.input_units, "output_name": ds.output_name, "output_unit": ds.output_unit,
            "y0": ds.y0, "sources": ds.sources, "notes": ds.notes, "extra": list(ds.extra)}
    tmp = where.with_name(f"{where.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            np.savez(f, meta=np.array(json.dumps(meta)), t=ds.t, u=ds.u, y=ds.y, u0=ds.u0, valid=ds.valid,
                     cycle=ds.cycle, **{f"extra{i}": v for i, v in enumerate(ds.extra.values())})
        os.replace(tmp, where)
    except (OSError, TypeError, ValueError):  # a read-only folder, a full disk: no cache, the Dataset is built all the same
        tmp.unlink(missing_ok=True)
