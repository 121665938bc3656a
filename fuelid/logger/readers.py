"""Reading recorded CAN traffic as `can.Message` frames, whatever tool recorded it.

Formats, recognised from the file's content by their real header (its name does not matter; ``.gz`` is
undone first), one entry each in `FORMATS` (name → sniff, read), as in python-can's reader table:

- candump -L (``(1543532003.571000) can1 18F00131#FFFFFF3F00FFFFFF``) and candump's printed text with
  ``-ta``/``-tz`` timestamps (`` (000.005001)  can0  18FEDF00   [8]  8A A0 28 ...``): parsed here,
  because python-can's candump reader stops at the first malformed line and has no reader for the
  printed text at all; the first line must be one;
- Vector ASC (``date``/``base`` header) and PCAN TRC (``;$FILEVERSION=`` header, or v1.0's numbered
  lines): python-can's readers; TRC error frames (``ER``) are kept as error frames, as the ASC reader does;
- Vector BLF (``LOGG``): python-can's reader;
- ASAM MDF 4 from CANedge loggers (``MDF ``/``UnFinMF ``): python-can's MF4 reader (needs the ``mf4``
  extra, asammdf); a gzipped MF4 is decompressed in memory.

`open_frames` gives a `FrameSource`: iterate it for the frames; it counts them (`frames`) and the
malformed lines it skipped (`skipped`: unparsable, or with a value out of range — a time that is not a
finite number of seconds within MCAP's range, an identifier wider than its 11 or 29 bits, more data
than the length says). Afterwards `status` says how the file ended: ``complete``; ``truncated`` (cut
mid-record: power loss, a cut download, a truncated ``.gz``; every frame before the cut is given and
`position` says where: ``line N`` or ``byte N``); or ``damaged`` (bytes that are not the format: a
failed gzip CRC, a BLF container that does not decompress; frames read before it are given, frames
after it are not, and frames already given from a gzip with a failed CRC may be wrong). An unreadable
file or an unknown format raises `FuelidError`.
"""
import gzip
import io
import logging
import math
import re
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import can

from fuelid.errors import FuelidError
from fuelid.logger.frame_block import FrameBlock, candump_l_items

_CAN_ERR_FLAG = 0x20000000  # SocketCAN marks error frames in the identifier
_SNIFF_BYTES = 1 << 16
MAX_TIME_S = (2**64 - 1) / 1e9  # MCAP log times are unsigned 64-bit nanoseconds

# (1543532003.571000) can1 18F00131#FFFFFF3F00FFFFFF  -- also 123#R, 123##1AABB (CAN FD)
_CANDUMP_L = re.compile(
    r"\((\d+\.\d+)\)\s+(\S+)\s+([0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#(?:(R\d?)|#([0-9A-Fa-f])?([0-9A-Fa-f]*)"
    r"|([0-9A-Fa-f]*))(?:\s+[RT])?\s*$")
#  (000.005001)  can0  18FEDF00   [8]  8A A0 28 7D 7D FF FF F5
_CANDUMP_TA = re.compile(
    r"\s*\((\d+\.\d+)\)\s+(\S+)\s+([0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})\s+\[(\d{1,2})\]"
    r"((?:\s+[0-9A-Fa-f]{2})*|\s+remote request)\s*$")
#       1)      1841.0  0001  8  00 00 00 00 00 00 00 00   -- PCAN TRC v1.0, which has no version line
_TRC_V1_0 = re.compile(r"\s*\d+\)\s+\d+(\.\d+)?\s+[0-9A-Fa-f]{1,8}\s+\d\s")


def _frame(t: str, channel: str, can_id: str, data: bytes, dlc: int | None = None,
           remote: bool = False, fd: bool = False) -> can.Message:
    ident = int(can_id, 16)
    return can.Message(timestamp=float(t), channel=channel, arbitration_id=ident & 0x1FFFFFFF,
                       is_extended_id=len(can_id) == 8, is_error_frame=bool(ident & _CAN_ERR_FLAG),
                       is_remote_frame=remote, is_fd=fd, dlc=len(data) if dlc is None else dlc,
                       data=data)


def parse_candump_l(line: str) -> can.Message | None:
    """One candump -L line as a frame, None if malformed."""
    m = _CANDUMP_L.match(line)
    if m is None:
        return None
    t, channel, can_id, remote, fd_flags, fd_data, data = m.groups()
    if remote is not None:
        return _frame(t, channel, can_id, b"", dlc=int(remote[1:] or 0), remote=True)
    hexdata = data if data is not None else fd_data
    if len(hexdata) % 2 or len(hexdata) > (128 if data is None else 16):
        return None
    return _frame(t, channel, can_id, bytes.fromhex(hexdata), fd=data is None)


def parse_candump_ta(line: str) -> can.Message | None:
    """One line of candump's printed output with -ta/-tz timestamps as a frame, None if malformed."""
    m = _CANDUMP_TA.match(line)
    if m is None:
        return None
    t, channel, can_id, dlc, rest = m.groups()
    if rest.strip() == "remote request":
        return _frame(t, channel, can_id, b"", dlc=int(dlc), remote=True)
    data = bytes.fromhex(rest)
    if len(data) != int(dlc) or len(data) > 64:
        return None
    return _frame(t, channel, can_id, data, fd=len(data) > 8)


def in_range(msg: can.Message) -> bool:
    """Whether every value of `msg` is one a CAN frame can have: a finite time [s] within MCAP's range,
    an identifier within 11 or 29 bits, and (data and remote frames) as many data bytes as the DLC says."""
    if not (math.isfinite(msg.timestamp) and 0 <= msg.timestamp <= MAX_TIME_S):
        return False
    if not 0 <= msg.arbitration_id <= (0x1FFFFFFF if msg.is_extended_id else 0x7FF):
        return False
    if msg.is_error_frame or msg.is_remote_frame:
        return len(msg.data) <= 64
    expected = can.util.dlc2len(msg.dlc) if msg.is_fd else min(msg.dlc, 8)
    return 0 <= msg.dlc <= 15 and len(msg.data) == expected


class _Lines:
    """The lines of a text file for a line reader, counted; a last line without its newline was cut by the
    end of the file and is withheld (`cut` is then its line number). `position` is the last line given."""

    def __init__(self, f: IO[str]):
        self._f = f
        self.position = 0
        self.cut: int | None = None

    def __iter__(self) -> Iterator[str]:
        for line in self._f:
            if not line.endswith("\n"):
                if line.strip():
                    self.cut = self.position + 1
                return
            self.position += 1
            yield line

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> "_Lines":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _TextBlocks:
    """The complete lines of a binary file in big pieces, for `candump_l_items`: the same lines `_Lines` gives
    (newlines made universal as text mode does, a cut last line withheld with its number in `cut`), as bytes.
    `position` counts the lines given. Read with read1, whose failure loses nothing read before it."""

    PIECE_BYTES = 1 << 20

    def __init__(self, f: IO[bytes]):
        self._f = f
        self.position = 0
        self.cut: int | None = None

    def __iter__(self) -> Iterator[bytes]:
        pending = b""
        while True:
            pieces = [pending]
            try:
                while sum(map(len, pieces)) < self.PIECE_BYTES and (piece := self._f.read1(self.PIECE_BYTES)):
                    pieces.append(piece)
            except BaseException:  # the lines read before the failure are given first
                lines, _ = self._split(b"".join(pieces))
                if lines:
                    yield lines
                raise
            if len(pieces) == 1:
                break
            data = b"".join(pieces)
            held = data.endswith(b"\r")  # may be the first half of a \r\n
            lines, pending = self._split(data[:-1] if held else data)
            pending += b"\r" if held else b""
            if lines:
                yield lines
        lines, pending = self._split(pending)
        if lines:
            yield lines
        if pending.decode("latin-1").strip():
            self.cut = self.position + 1

    def _split(self, data: bytes) -> tuple[bytes, bytes]:
        """(the complete lines of `data`, counted, the rest)."""
        if b"\r" in data:
            data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
        cut = data.rfind(b"\n") + 1
        self.position += data.count(b"\n", 0, cut)
        return data[:cut], data[cut:]

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> "_TextBlocks":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _SkipMalformed:
    """Mixin for python-can's line readers: a line whose parse raises is counted, not fatal
    (python-can would end the file there). Relies on each reader's per-line hook; the tests feed
    malformed lines, so a renamed hook in a new python-can shows up there."""

    skipped = 0

    def _guard(self, parse: Callable, *args):
        try:
            return parse(*args)
        except (ValueError, IndexError, OverflowError, KeyError):
            self.skipped += 1
            return None


class _ASCReader(_SkipMalformed, can.ASCReader):
    def _process_classic_can_frame(self, line, msg_kwargs):
        return self._guard(super()._process_classic_can_frame, line, msg_kwargs)


class _TRCReader(_SkipMalformed, can.TRCReader):
    def _parse_line(self, line):
        return self._guard(self._parse_error_or_frame, line)

    def _parse_error_or_frame(self, line: str) -> can.Message | None:
        cols = line.split()
        if self.columns and len(cols) > 2 and cols[self.columns["T"]] == "ER":
            return self._error_frame(cols)
        return super()._parse_line(line)

    def _error_frame(self, cols: list[str]) -> can.Message:
        """A v2.x ``ER`` line: number, offset [ms], ER, [bus,] Rx/Tx, then the error bytes (no identifier)."""
        direction = next(i for i, c in enumerate(cols) if c in ("Rx", "Tx"))
        bus = self.columns.get("B")
        data = bytes(int(b, 16) for b in cols[direction + 1 :])
        if len(data) > 8:
            raise ValueError("error frame with more than 8 bytes")
        return can.Message(timestamp=float(cols[self.columns["O"]]) / 1000 + self._start_time,
                           is_error_frame=True, arbitration_id=0, dlc=len(data), data=data,
                           channel=int(cols[bus]) if bus is not None and bus < direction else 1,
                           is_rx=cols[direction] == "Rx")


class _CountWarnings(logging.Handler):
    """Counts a python-can reader's warnings about data it skipped (e.g. a BLF container with an
    unknown compression method): the reader goes on silently, the file is damaged."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.count = 0

    def emit(self, record: logging.LogRecord) -> None:
        self.count += 1


def _first_lines(head: bytes) -> list[str]:
    return [ln.strip() for ln in head.decode("latin-1").splitlines()[:200] if ln.strip()]


def _is_trc(head: bytes) -> bool:
    lines = _first_lines(head)
    if not lines or not lines[0].startswith(";"):
        return False
    header = [ln for ln in lines if ln.startswith(";")]
    data = next((ln for ln in lines if not ln.startswith(";")), "")
    return any(ln.startswith(";$FILEVERSION=") for ln in header) or bool(_TRC_V1_0.match(data))


def _is_asc(head: bytes) -> bool:
    return any(ln.startswith(("date ", "base hex", "base dec")) for ln in _first_lines(head)[:5])


def _first_line_parses(parse: Callable[[str], can.Message | None]) -> Callable[[bytes], bool]:
    def sniff(head: bytes) -> bool:
        lines = _first_lines(head)
        return bool(lines) and parse(lines[0]) is not None
    return sniff


def _read_candump(source: "FrameSource", parse: Callable[[str], can.Message | None]) -> Iterator[can.Message]:
    with source.lines() as lines:
        for line in lines:
            if not line.strip():
                continue
            msg = parse(line)
            if msg is None:
                source.skipped += 1
            else:
                yield msg


def _read_candump_l_blocks(source: "FrameSource") -> Iterator[FrameBlock | can.Message]:
    """What `_read_candump` gives for candump -L, runs of ordinary lines as FrameBlocks."""
    with source.text_blocks() as blocks:
        for text in blocks:
            for item in candump_l_items(text, parse_candump_l):
                if item is None:
                    source.skipped += 1
                else:
                    yield item


def _read_lines_with(reader_cls) -> Callable[["FrameSource"], Iterator[can.Message]]:
    def read(source: "FrameSource") -> Iterator[can.Message]:
        with source.lines() as lines:
            reader = reader_cls(lines)
            try:
                yield from reader
            finally:
                source.skipped += reader.skipped
    return read


def _read_blf(source: "FrameSource") -> Iterator[can.Message]:
    with source.binary() as f:
        try:
            reader = can.BLFReader(f)
            skipped = _CountWarnings()
            log = logging.getLogger(can.io.blf.__name__)
            log.addHandler(skipped)
            read = 0
            try:
                for msg in reader:
                    read += 1
                    yield msg
            finally:
                log.removeHandler(skipped)
            if skipped.count:
                raise ValueError(f"{skipped.count} containers could not be read")
            if reader._tail:  # python-can read to the end of the file and kept an object cut short here
                source.at_end, source.position = True, f"byte {source.path.stat().st_size}"
                raise ValueError("the last object is incomplete")
            if reader.object_count and not read:
                raise ValueError(f"the header lists {reader.object_count} objects, none could be read")
        except Exception:
            if not f.closed:  # python-can closes the file when it has read to its end
                source.ended_at(f)
            raise


def _read_mf4(source: "FrameSource") -> Iterator[can.Message]:
    with source.binary() as f:  # asammdf seeks all over the file: a gzipped one is given decompressed
        data = f.read() if source.compressed else None
    try:
        reader = can.MF4Reader(io.BytesIO(data) if data is not None else source.path)
    except (ImportError, NotImplementedError):
        raise FuelidError("reading MF4 needs asammdf: pip install 'fuelid[mf4]'") from None
    except Exception as e:  # noqa: BLE001 -- asammdf's errors on a bad file are of many kinds
        raise FuelidError(f"cannot read {source.path} as MF4: {e}") from None
    yield from reader


@dataclass(frozen=True)
class Format:
    """A recording format: `sniff` tells it from the file's first (decompressed) bytes, `read` gives the
    frames of a `FrameSource` in recorded order."""

    name: str
    sniff: Callable[[bytes], bool]
    read: Callable[["FrameSource"], Iterator[can.Message]]


FORMATS: dict[str, Format] = {f.name: f for f in [
    Format("blf", lambda head: head.startswith(b"LOGG"), _read_blf),
    Format("mf4", lambda head: head.startswith((b"MDF ", b"UnFinMF ")), _read_mf4),
    Format("trc", _is_trc, _read_lines_with(_TRCReader)),
    Format("asc", _is_asc, _read_lines_with(_ASCReader)),
    Format("candump-L", _first_line_parses(parse_candump_l), lambda s: _read_candump(s, parse_candump_l)),
    Format("candump-ta", _first_line_parses(parse_candump_ta), lambda s: _read_candump(s, parse_candump_ta)),
]}
"""Format name → Format, in the order they are tried; a new format is one entry here."""


class FrameSource:
    """A recorded CAN file: its `format` (a key of `FORMATS`); iterating it yields its frames in recorded
    order. After reading: `frames` read, malformed lines `skipped`, and how the file ended: `status`
    (``complete``, ``truncated`` or ``damaged``), `position` (``line N``/``byte N`` where it ended) and
    `error` (what was wrong)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.frames = 0
        self.skipped = 0
        self.status = "complete"
        self.position: str | None = None
        self.error: str | None = None
        self.at_end = False  # set by a reader whose failure is the end of the data (a cut, not damage)
        self._lines: _Lines | _TextBlocks | None = None
        try:
            with open(self.path, "rb") as f:
                self.compressed = f.read(2) == b"\x1f\x8b"
            with self.binary() as f:
                head = f.read(_SNIFF_BYTES)
        except (OSError, EOFError, zlib.error) as e:
            raise FuelidError(f"cannot read {self.path}: {getattr(e, 'strerror', None) or e}") from None
        self.format = next((name for name, fmt in FORMATS.items() if fmt.sniff(head)), None)
        if self.format is None:
            raise FuelidError(f"{self.path}: not a CAN recording fuelid reads ({', '.join(FORMATS)})")

    @property
    def truncated(self) -> bool:
        return self.status == "truncated"

    def __iter__(self) -> Iterator[can.Message]:
        return self._checked(FORMATS[self.format].read(self))

    def blocks(self) -> Iterator[can.Message | FrameBlock]:
        """The frames as iterating gives them, runs of ordinary candump -L frames as FrameBlocks (they are all in
        range); other formats frame by frame. The counts and the status as when iterating."""
        if self.format != "candump-L":
            return iter(self)
        return self._checked(_read_candump_l_blocks(self))

    def _checked(self, items: Iterator[can.Message | FrameBlock]) -> Iterator[can.Message | FrameBlock]:
        try:
            for item in items:
                if isinstance(item, FrameBlock):
                    self.frames += len(item)
                elif not in_range(item):
                    self.skipped += 1
                    continue
                else:
                    self.frames += 1
                yield item
        except FuelidError:
            raise
        except Exception as e:  # noqa: BLE001 -- any failure inside a reader: the data ends here
            self._ended(e)
        else:
            if self._lines is not None and self._lines.cut is not None:
                self.status, self.position = "truncated", f"line {self._lines.cut}"
                self.error = "the last line is cut short"
                self.skipped += 1

    def _ended(self, e: Exception) -> None:
        """How the data ended: cut (by the end of the file or of its .gz stream) or damaged."""
        self.error = str(e) or type(e).__name__
        cut = isinstance(e, EOFError) or (self.at_end and not isinstance(e, (gzip.BadGzipFile, zlib.error)))
        self.status = "truncated" if cut else "damaged"
        if self._lines is not None:
            self.position = f"line {self._lines.position + 1}"

    def ended_at(self, f: IO[bytes]) -> None:
        """Note where a binary reader failed in `f` and whether nothing followed (a cut, not damage)."""
        try:
            self.position = f"byte {f.tell()}"
            self.at_end = f.read(1) == b""
        except (OSError, EOFError, zlib.error, gzip.BadGzipFile):
            self.at_end = True

    def lines(self) -> _Lines:
        """The file's text lines (latin-1 maps every byte, so stray binary garbage is a malformed line)."""
        if self.compressed:
            f = gzip.open(self.path, "rt", encoding="latin-1", newline=None)
        else:
            f = open(self.path, encoding="latin-1", newline=None)
        self._lines = _Lines(f)
        return self._lines

    def text_blocks(self) -> _TextBlocks:
        """The file's complete lines in big pieces of bytes (see `_TextBlocks`)."""
        self._lines = _TextBlocks(self.binary())
        return self._lines

    def binary(self) -> IO[bytes]:
        return gzip.open(self.path, "rb") if self.compressed else open(self.path, "rb")


def open_frames(path: str | Path) -> FrameSource:
    """A recorded CAN file in any of `FORMATS`, ready to iterate; `FuelidError` if it can't be read."""
    return FrameSource(path)


def read_frames(path: str | Path) -> Iterator[can.Message]:
    """The frames of a recorded CAN file in any of `FORMATS` (use `open_frames` for the counts)."""
    return iter(FrameSource(path))


RELATIVE_BEFORE_S = 1e9
"""Frame times [s] before this (2001-09-09 as Unix time) count from boot or from the recording's start
(candump -ta, a logger without a clock): they say nothing about when the recording was made."""


def one_timeline(sources: list[FrameSource], notes: list[str], blocks: bool = False
                 ) -> Iterator[can.Message | FrameBlock]:
    """The frames of `sources`, one recording after another in the order given (with `blocks`, as
    `FrameSource.blocks` gives them). A recording after the first whose times are relative
    (`RELATIVE_BEFORE_S`) cannot be placed by its clock, and merging it by time would interleave two trips:
    it is shifted to start where the previous one ended, and `notes` says so, naming it."""
    end = previous = None
    for source in sources:
        shift = None
        for item in source.blocks() if blocks else source:
            block = isinstance(item, FrameBlock)
            if shift is None:
                first = float(item.t[0]) if block else item.timestamp
                shift = 0.0
                if end is not None and first < RELATIVE_BEFORE_S:
                    shift = end - first
                    notes.append(f"{source.path} has relative (boot-time) timestamps: placed after {previous}, "
                                 f"shifted by {shift:+.6f} s")
            if block:
                item = item.shifted(shift) if shift else item
                last = float(item.t.max())
            else:
                item.timestamp += shift
                last = item.timestamp
            end = last if end is None else max(end, last)
            yield item
        previous = source.path
