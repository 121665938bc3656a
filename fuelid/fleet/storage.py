"""Content-addressed file storage and the checks an uploaded file passes before it is stored.

Layout under the data directory: `blobs/<first 2 hex>/<sha256>` holds every stored file (uploads, model.json,
diagnosis.json, report.html) under its own hash, so no path ever comes from a request; `incoming/` holds
partial uploads (`<sha256>-<uploader key>.part`) until their last byte arrives. A finished upload is checked,
fsync'd and renamed into `blobs/` in one step, and only then registered in the database, so a crash at any
moment leaves either nothing visible or a complete file; `sweep` removes blobs a crash left unregistered.
Every folder is created with `dir_mode(file_mode)` and every file with `file_mode` (default 0o600: the owner
only), whatever the process umask.
"""
from __future__ import annotations

import hashlib
import os
import time
from dataclasses import dataclass
from pathlib import Path

from mcap.reader import SeekingReader

from fuelid.logger.durable import fsync_path
from fuelid.logger.mcap_log import MAGIC, METADATA_NAME, chunks_located, damaged_chunks

HEX64 = r"^[0-9a-f]{64}$"
FILE_MODE = 0o600


def dir_mode(file_mode: int) -> int:
    """The folder mode going with a file mode: each class that may read may also enter (0o600 → 0o700)."""
    return file_mode | (file_mode & 0o444) >> 2


def make_dir(path: Path, file_mode: int = FILE_MODE) -> Path:
    """Create `path` (and missing parents) with dir_mode(file_mode), and set that mode on it if it exists."""
    path.mkdir(parents=True, exist_ok=True, mode=dir_mode(file_mode))
    os.chmod(path, dir_mode(file_mode))
    return path


def open_owned(path: Path, file_mode: int = FILE_MODE, append: bool = True):
    """`path` opened to write bytes, created with `file_mode` when missing: appending, or else emptied first."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | (os.O_APPEND if append else os.O_TRUNC), file_mode)
    os.fchmod(fd, file_mode)
    return os.fdopen(fd, "ab" if append else "wb")


class UploadRefused(Exception):
    """An upload that fails a check: HTTP `status` and a one-line reason."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status


class BlobStore:
    """Files by sha256 under `root/blobs`, partial uploads under `root/incoming`, all created with `file_mode`
    (their folders, root included, with dir_mode(file_mode))."""

    def __init__(self, root: str | Path, file_mode: int = FILE_MODE):
        self.root, self.file_mode = Path(root), file_mode
        self.blobs = self.root / "blobs"
        self.incoming = self.root / "incoming"
        for d in (self.root, self.blobs, self.incoming):
            make_dir(d, file_mode)

    def path(self, sha256: str) -> Path:
        return self.blobs / sha256[:2] / sha256

    def partial(self, sha256: str, uploader: str) -> Path:
        """The partial upload of `sha256` by `uploader` (hashed: uploaders never share or name a path)."""
        return self.incoming / f"{sha256}-{_uploader_key(uploader)}.part"

    def partials(self, uploader: str) -> list[Path]:
        """Every partial upload `uploader` holds."""
        return list(self.incoming.glob(f"*-{_uploader_key(uploader)}.part"))

    def expire_partials(self, max_age_s: float, keep: set[Path] = frozenset()) -> int:
        """Delete the partial uploads not written to for `max_age_s` [s], and empty ones (a partial upload holds
        at least one byte: an empty one is a leftover), but those in `keep` (being received); return how many
        went. Their age is the file's mtime, so it survives a restart of the server."""
        expired = 0
        oldest = time.time() - max_age_s
        for p in self.incoming.glob("*.part"):
            try:
                st = p.stat()
                if p not in keep and (st.st_size == 0 or st.st_mtime < oldest):
                    p.unlink()
                    expired += 1
            except FileNotFoundError:  # finished or expired by another request meanwhile
                pass
        return expired

    def commit(self, src: Path, sha256: str) -> Path:
        """Move the complete file `src` (on the same file system) to its blob path, durably."""
        dst = self.path(sha256)
        make_dir(dst.parent, self.file_mode)
        with open(src, "rb+") as f:
            os.fchmod(f.fileno(), self.file_mode)
            os.fsync(f.fileno())
        os.replace(src, dst)
        fsync_path(dst.parent)
        return dst

    def put_file(self, path: str | Path) -> str:
        """Store a copy of the file at `path`; return its sha256."""
        data = Path(path).read_bytes()
        sha256 = hashlib.sha256(data).hexdigest()
        if not self.path(sha256).exists():
            tmp = self.incoming / f"{sha256}.{os.getpid()}.tmp"
            with open_owned(tmp, self.file_mode, append=False) as f:
                f.write(data)
            self.commit(tmp, sha256)
        return sha256

    def sweep(self, registered: set[str]) -> int:
        """Delete blobs no database row names (a crash between rename and insert) and stray temporaries;
        return how many files went. Partial uploads stay: their uploads resume."""
        removed = 0
        for p in list(self.blobs.glob("*/*")) + list(self.incoming.glob("*.tmp")):
            if p.suffix == ".tmp" or p.name not in registered:
                p.unlink(missing_ok=True)
                removed += 1
        return removed


def _uploader_key(uploader: str) -> str:
    return hashlib.sha256(uploader.encode()).hexdigest()[:16]


@dataclass
class McapInfo:
    """What the registry keeps of an uploaded MCAP file: its truck, message time range [ns] and count."""

    truck: str
    start_ns: int | None
    end_ns: int | None
    messages: int


def inspect_mcap(path: str | Path) -> McapInfo:
    """Check an uploaded file is a complete fuelid MCAP log and read what the registry keeps.

    The rule: MCAP magic at both ends, a footer and summary that mcap's reader parses with statistics, chunks
    the summary locates when it holds messages (its chunk index, or for a converted file, written without one,
    a data section matching the statistics; a log of a silent bus has no chunk) so the fleet's jobs read it
    chunk by chunk, never by a sequential scan, every chunk matching its CRC, and a `fuelid` metadata record
    naming the truck. A file cut before its footer (a power cut the daemon did not recover) is refused:
    `fuelid recover` turns it into a complete file to upload. The bytes themselves are vouched for by the
    sha256 the client sent and the server recomputed."""
    with open(path, "rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise UploadRefused(422, "not an MCAP file")
        f.seek(-len(MAGIC), os.SEEK_END)
        if f.read(len(MAGIC)) != MAGIC:
            raise UploadRefused(422, "truncated MCAP file (no footer); run `fuelid recover` on it and upload the result")
        f.seek(0)
        try:
            reader = SeekingReader(f)
            summary = reader.get_summary()
            # the last `fuelid` record wins, as in logger.mcap_log.read_metadata (the VIN once seen)
            fuelid = [dict(m.metadata) for m in reader.iter_metadata() if m.name == METADATA_NAME]
        except Exception as exc:  # mcap, struct and decoding errors alike: a damaged summary
            raise UploadRefused(422, f"damaged MCAP summary or metadata ({type(exc).__name__})") from exc
    if summary is None or summary.statistics is None:
        raise UploadRefused(422, "MCAP file without statistics in its summary")
    if summary.statistics.message_count and not chunks_located(path):  # empty logs (bus silent) have no chunk
        raise UploadRefused(422, "MCAP file with messages but no chunk index, nor a data section matching its "
                                 "statistics; run `fuelid recover` on it and upload the result")
    damaged = damaged_chunks(path)  # the sha256 vouches for the transfer, not for what the logger wrote
    if damaged:
        raise UploadRefused(422, f"damaged MCAP file: chunk at bytes {damaged[0].start}-{damaged[0].end} "
                                 f"({damaged[0].reason}); run `fuelid recover` on it and upload the result")
    truck = fuelid[-1].get("truck") if fuelid else None
    if not truck:
        raise UploadRefused(422, "the MCAP file names no truck (metadata 'fuelid' has no 'truck')")
    stats = summary.statistics
    has = stats.message_count > 0
    return McapInfo(truck=truck, start_ns=stats.message_start_time if has else None,
                    end_ns=stats.message_end_time if has else None, messages=stats.message_count)
