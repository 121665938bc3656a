"""A cache of built Datasets in the user's cache directory, for the commands that build the same one in turn
(`fuelid dataset`, `identify`, `compare`, `diagnose`, `report`, `online`). Nothing is written beside the data.

Each Dataset is one file `KEY.npz` in `cache_dir()`: FUELID_CACHE_DIR when set, else $XDG_CACHE_HOME/fuelid, else
~/.cache/fuelid. KEY is a BLAKE2b digest of every input file's name and whole content (in the order given), the
build options, and the code that makes a Dataset (the modules of the dataset path and the DBC), so a recording
changed in any byte, other options or another fuelid never get a stale Dataset; a cache file that does not load
is rebuilt. A Dataset is stored only once built (a failed build leaves nothing), atomically (a temporary file
renamed into place); after each store the least recently used files are removed until the directory holds at
most FUELID_CACHE_MAX_MB megabytes (default MAX_MB). A directory that cannot be created or written means no
cache. `--no-cache` or FUELID_DATASET_CACHE=0 turns it off.
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


MAX_MB = 2048.0  # default bound of the cache directory [MB]


def cache_dir() -> Path:
    """The directory of the Dataset cache (module docstring)."""
    if os.environ.get("FUELID_CACHE_DIR"):
        return Path(os.environ["FUELID_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "fuelid"


def max_bytes() -> float:
    """The bound of the cache directory [bytes]: FUELID_CACHE_MAX_MB, default MAX_MB."""
    try:
        return max(float(os.environ.get("FUELID_CACHE_MAX_MB") or MAX_MB), 0.0) * 1e6
    except ValueError:
        return MAX_MB * 1e6


def cache_path(key: str) -> Path:
    """Where the Dataset built under `key` (`cache_key`) is kept."""
    return cache_dir() / f"{key}.npz"


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
    where = cache_path(key)
    ds = _load(where, key)
    if ds is None:
        ds = build()
        _store(where, key, ds)
    return ds


def _clean(directory: Path, keep: Path) -> None:
    """Remove the least recently used cache files (by modification time: a hit touches its file) until the
    directory holds at most `max_bytes()`; `keep`, the file just stored, goes last."""
    files = []
    for p in directory.glob("*.npz"):
        try:
            st = p.stat()
        except OSError:  # removed meanwhile by another process
            continue
        files.append((p == keep, st.st_mtime, st.st_size, p))
    total, limit = sum(f[2] for f in files), max_bytes()
    for _, _, size, p in sorted(files, key=lambda f: (f[0], f[1])):
        if total <= limit:
            break
        p.unlink(missing_ok=True)
        total -= size


def _load(where: Path, key: str) -> Dataset | None:
    try:
        with np.load(where, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            if meta["format"] != FORMAT or meta["key"] != key:
                return None
            ds = Dataset(
                Ts=meta["Ts"], t=z["t"], u=z["u"], y=z["y"], input_names=tuple(meta["input_names"]),
                input_units=tuple(meta["input_units"]), output_name=meta["output_name"],
                output_unit=meta["output_unit"], u0=z["u0"], y0=meta["y0"], valid=z["valid"], cycle=z["cycle"],
                extra={name: z[f"extra{i}"] for i, name in enumerate(meta["extra"])},
                sources=meta["sources"], notes=meta["notes"], fuel_lag_s=meta["fuel_lag_s"],
                fuel_period_s=meta["fuel_period_s"])
        os.utime(where)  # used now: the last to be cleaned
        return ds
    except (OSError, ValueError, KeyError, TypeError, EOFError):  # none yet, or not a cache file: build
        return None


def _store(where: Path, key: str, ds: Dataset) -> None:
    meta = {"format": FORMAT, "key": key, "Ts": ds.Ts, "input_names": ds.input_names,
            "input_units": ds.input_units, "output_name": ds.output_name, "output_unit": ds.output_unit,
            "y0": ds.y0, "sources": ds.sources, "notes": ds.notes, "extra": list(ds.extra),
            "fuel_lag_s": ds.fuel_lag_s, "fuel_period_s": ds.fuel_period_s}
    tmp = where.with_name(f"{where.name}.{os.getpid()}.tmp")
    try:
        where.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:
            np.savez(f, meta=np.array(json.dumps(meta)), t=ds.t, u=ds.u, y=ds.y, u0=ds.u0, valid=ds.valid,
                     cycle=ds.cycle, **{f"extra{i}": v for i, v in enumerate(ds.extra.values())})
        os.replace(tmp, where)
        _clean(where.parent, where)
    except (OSError, TypeError, ValueError):  # a read-only folder, a full disk: no cache, the Dataset is built all the same
        try:
            tmp.unlink(missing_ok=True)
        except OSError:  # the directory itself is not there or not ours
            pass
