"""Writes that survive a power cut: the in-cab box loses power without warning."""
import os
from pathlib import Path


def fsync_path(path: str | Path) -> None:
    """Sync the file or directory at `path` to disk: a directory's sync makes the renames and new files in it
    durable; a file's own descriptor also reaches writes made through other descriptors (e.g. a Rust writer)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: Path, data: bytes) -> None:
    """Replace `path` with `data` so that a power cut leaves either the old content or the new, never half."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    fsync_path(path.parent)
