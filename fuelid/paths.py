"""Checks of the files a command is given, before any work: each failure is a FuelidError naming the path and
the cause in words (not an OS error number, nor a temporary file the command would have written)."""
import os
from pathlib import Path

from fuelid.errors import FuelidError


def readable_file(path) -> Path:
    """path, when it names a file this process can read; FuelidError otherwise."""
    p = Path(path)
    if p.is_dir():
        raise FuelidError(f"{p}: is a folder, not a file (give the files in it, e.g. {p / '*'})")
    if not p.exists():
        raise FuelidError(f"{p}: no such file")
    if not os.access(p, os.R_OK):
        raise FuelidError(f"{p}: no permission to read it")
    return p


def writable_file(path) -> Path:
    """path, when a file can be written there (its folder exists and may be written in, and it is not a folder
    itself); FuelidError otherwise."""
    p = Path(path)
    folder = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise FuelidError(f"{p}: is a folder; give the name of the file to write")
    if not folder.is_dir():
        raise FuelidError(f"{p}: cannot write it: the folder {folder} does not exist")
    if not os.access(folder, os.W_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise FuelidError(f"{p}: no permission to write it")
    return p


def os_error_message(exc: OSError) -> str:
    """'PATH: reason' for an OSError that names a file, else the reason alone."""
    reason = exc.strerror or str(exc)
    paths = [f for f in (exc.filename, exc.filename2) if f is not None]
    return f"{' → '.join(map(str, paths))}: {reason}" if paths else reason
