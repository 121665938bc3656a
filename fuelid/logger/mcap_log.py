"""Crash-safe MCAP logs: JSON messages with jsonschema schemas, zstd chunks closed at least once a second.

`McapLogWriter` writes; `read_messages` and `read_metadata` read complete files chunk by chunk (found through
their chunk index, or in converted files, which have none, by walking the data section) and truncated ones
(power cut before `close()`) by a sequential scan that stops at the last complete chunk; `recover` rewrites a
truncated file as a valid indexed one. Channel and record layout: docs/reference/formats.md.
"""
from __future__ import annotations

import errno
import io
import itertools
import logging
import mmap
import re
import struct
import threading
import time
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Callable, Iterable, Iterator

import numpy as np
import orjson
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import (Attachment, AttachmentIndex, Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, McapRecord,
                          Message, MessageIndex, Metadata, MetadataIndex, Schema, Statistics, SummaryOffset)
from mcap.writer import CompressionType, Writer

from fuelid import __version__
from fuelid.errors import FuelidError
from fuelid.logger import columns as message_columns
from fuelid.logger.durable import fsync_path
from fuelid.logger.frame_block import FrameBlock
from fuelid.logger.json_rows import records, text_matrix

METADATA_NAME = "fuelid"
MAGIC = b"\x89MCAP0\r\n"

RAW_SCHEMA = {
    "title": "fuelid.can.raw",
    "description": "One CAN frame as received, decoded or not",
    "type": "object",
    "properties": {
        "t": {"type": "number", "description": "receive time [s]"},
        "id": {"type": "integer", "description": "arbitration id, 29-bit when extended, else 11-bit"},
        "extended": {"type": "boolean", "description": "29-bit identifier"},
        "dlc": {"type": "integer", "description": "data length code"},
        "data": {"type": "string", "description": "payload bytes as hex"},
        "error": {"type": "boolean", "description": "error frame"},
        "remote": {"type": "boolean", "description": "remote transmission request"},
        "channel": {"type": ["string", "integer", "null"], "description": "bus the frame came from"},
    },
    "required": ["t", "id", "extended", "dlc", "data", "error", "remote", "channel"],
}

FLOWMETER_SCHEMA = {
    "title": "fuelid.flowmeter",
    "description": "One reading of the gas-flow meter (thermal mass flow, 2.5-125 kg/h, 0-10 V)",
    "type": "object",
    "properties": {
        "t": {"type": "number", "description": "host receive time [s]"},
        "device_t": {"type": ["number", "null"], "description": "data logger clock [s]"},
        "volts": {"type": ["number", "null"], "description": "meter analog output [V]"},
        "flow_kg_h": {"type": ["number", "null"], "description": "gas mass flow [kg/h], null unless status ok"},
        "status": {"type": "string", "enum": ["ok", "below_range", "over_range", "invalid"]},
        "raw": {"type": "string", "description": "received line, bytes outside printable ASCII as \\xHH"},
    },
    "required": ["t", "device_t", "volts", "flow_kg_h", "status", "raw"],
}


def raw_record(msg) -> dict:
    """The `/can/raw` message for a `can.Message`."""
    return {
        "t": msg.timestamp,
        "id": msg.arbitration_id,
        "extended": msg.is_extended_id,
        "dlc": msg.dlc,
        "data": msg.data.hex(),
        "error": msg.is_error_frame,
        "remote": msg.is_remote_frame,
        "channel": msg.channel,
    }


_HEX_DIGITS = np.frombuffer(b"0123456789abcdef", np.uint8)


def raw_records(block: FrameBlock, t_texts: np.ndarray) -> tuple[bytes, np.ndarray]:
    """The `/can/raw` messages of `block`, byte for byte what `raw_record` gives for each frame, serialised:
    (all of them, one after another, their n + 1 offsets). `t_texts`: the JSON text of each receive time."""
    n = len(block)
    digits = np.empty((n, 16), np.uint8)
    digits[:, 0::2] = _HEX_DIGITS[block.data >> 4]
    digits[:, 1::2] = _HEX_DIGITS[block.data & 15]
    digits[np.arange(16) >= 2 * block.dlc[:, None]] = 0
    ids, id_of_row = np.unique(block.can_id, return_inverse=True)
    channels = text_matrix([orjson.dumps(c) for c in block.channels])
    return records([b'{"t":', t_texts, b',"id":', text_matrix([b"%d" % i for i in ids.tolist()])[id_of_row.ravel()],
                    b',"extended":true,"dlc":', (block.dlc + ord("0")).astype(np.uint8)[:, None],
                    b',"data":"', digits, b'","error":false,"remote":false,"channel":', channels[block.channel],
                    b"}"], n)


class _SinkErrors(logging.Filter):
    """The Foxglove SDK does not raise a failed message write (disk full, I/O error) to the caller: it logs a
    warning per message, thousands a second on a full disk. This filter takes those warnings off the log and
    keeps the first for the thread that wrote (the SDK writes in the caller's thread, compression included),
    whose McapLogWriter.write raises it."""

    PREFIX = "error logging message"

    def __init__(self):
        super().__init__()
        self.failed = threading.local()

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if not message.startswith(self.PREFIX):
            return True
        if getattr(self.failed, "message", None) is None:
            self.failed.message = message
        return False

    def take(self) -> OSError | None:
        """The write failure this thread caused since the last call, as an OSError with its errno."""
        message = getattr(self.failed, "message", None)
        if message is None:
            return None
        self.failed.message = None
        code = re.search(r"code: (\d+)", message)
        return OSError(int(code.group(1)) if code else errno.EIO, f"MCAP write failed: {message[len(self.PREFIX) + 2:]}")


_SINK_ERRORS = _SinkErrors()
logging.getLogger("foxglove.log_sink_set").addFilter(_SINK_ERRORS)


def _metadata_strings(metadata: dict) -> dict[str, str]:
    # MCAP metadata is str -> str; anything else (lists of sources, numbers) is stored as JSON.
    return {k: v if isinstance(v, str) else orjson.dumps(v).decode() for k, v in metadata.items()}


class McapLogWriter:
    """Writes one MCAP log that survives a power cut (live) or a compact one (`chunk_flush_s=None`).

    Messages are JSON (orjson) on channels with jsonschema schemas, in zstd chunks. Live, a chunk is closed
    and pushed to the OS as soon as a write finds `chunk_flush_s` [s] of log time passed since the chunk
    began, or the chunk exceeds `chunk_size` [bytes of records]; every `chunk_flush_s` of wall time
    everything is also fsync'd (when `fsync`). Live, log time is wall time, so a file cut at any byte loses
    only the last second. A caller whose messages may pause (quiet bus) calls `flush_if_due()` from its idle
    loop to keep that bound. With `chunk_flush_s=None` chunks close at `chunk_size` only and nothing is
    flushed before `close()` (a conversion, which can be run again).

    `message_indexes`: MCAP's optional per-chunk, per-channel index of every message (16 bytes each, about
    half of a file of one-second chunks) and the summary's chunk index with it. False writes neither: MCAP's
    TypeScript indexed reader (@mcap/core, Foxglove) refuses a chunk index without message indexes, and
    without a chunk index every reference reader reads the file as a stream. fuelid locates the chunks of
    such a file by walking its top-level records (`_located_chunks`).

    Built on the Foxglove SDK's MCAP writer (Rust) rather than the pure-Python `mcap` Writer, which
    caps at ~120,000 messages/s on one core, too slow for the logger's decode + write budget.
    `metadata` is the `fuelid` metadata record (truck, dbc_sha256, source, ...; logger_version is added).
    `columns`: also write the messages as `logger.columns` attachments (`self.columns` collects them; a block
    is written when full, at most `columns.BLOCK_ROWS` rows held in memory, and the rest at `close()`). Only a
    closed file's summary lists them, so a file cut before `close()` reads through its JSON channels.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        metadata: dict,
        chunk_flush_s: float | None = 1.0,
        chunk_size: int = 1 << 20,
        message_indexes: bool = True,
        fsync: bool = True,
        columns: bool = False,
    ):
        import foxglove  # imported here: loading the SDK takes a moment and readers do not need it
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        self._foxglove = foxglove
        self.path = Path(path)
        self.metadata = {"logger_version": __version__, **metadata}
        self._context = foxglove.Context()  # this file's own channels, apart from other writers
        options = MCAPWriteOptions(
            compression=MCAPCompression.Zstd,
            chunk_size=chunk_size,
            profile="",
            compression_threads=0,  # compress in the calling thread: the in-cab box has few cores
            emit_message_indexes=message_indexes,
            emit_chunk_indexes=message_indexes,
        )
        self._writer = foxglove.open_mcap(
            self.path, allow_overwrite=True, context=self._context, writer_options=options
        )
        self._channels: dict[str, tuple] = {}  # topic -> (channel, its native log)
        self._timed = chunk_flush_s is not None
        self._flush_ns = int(chunk_flush_s * 1e9) if self._timed else 0
        self._fsync = fsync and self._timed
        self._log_due_ns: int | None = None  # set by the first message after a flush
        self._wall_due_ns = time.monotonic_ns() + self._flush_ns
        self._closed = False
        self.columns = message_columns.ColumnWriter(self._attach_columns) if columns else None
        self.set_metadata({})

    def _attach_columns(self, data: bytes, log_time_ns: int) -> None:
        self._writer.attach(log_time=log_time_ns, create_time=time.time_ns(), name=message_columns.NAME,
                            media_type=message_columns.MEDIA_TYPE, data=data)

    def add_channel(self, topic: str, schema: dict) -> None:
        """Register `topic` with a jsonschema `schema` (named by its "title", else the topic)."""
        if topic in self._channels:
            raise ValueError(f"channel {topic} already added")
        mcap_schema = self._foxglove.Schema(
            name=schema.get("title", topic), encoding="jsonschema", data=orjson.dumps(schema)
        )
        channel = self._foxglove.Channel(topic, schema=mcap_schema, message_encoding="json", context=self._context)
        # the SDK's native log(bytes, log_time, sink_id): Channel.log's checks of the encoding and the message
        # type cost as much again per message, and the bytes here are always JSON
        self._channels[topic] = (channel, channel.base.log)

    def has_channel(self, topic: str) -> bool:
        return topic in self._channels

    def write(self, topic: str, log_time_ns: int, record: dict) -> None:
        """Write one message; `log_time_ns` is the receive time [ns]. A failed write raises OSError (errno
        ENOSPC for a full disk), and so does every write after it: the file is broken from there on."""
        self.write_json(topic, log_time_ns, orjson.dumps(record, option=orjson.OPT_SERIALIZE_NUMPY))

    def write_json(self, topic: str, log_time_ns: int, data: bytes) -> None:
        """`write` of a message already serialised to JSON."""
        self._channels[topic][1](data, log_time_ns, None)
        failure = _SINK_ERRORS.take()
        if failure is not None:
            raise failure
        if not self._timed:
            return
        if self._log_due_ns is None:
            self._log_due_ns = log_time_ns + self._flush_ns
        elif log_time_ns >= self._log_due_ns:
            self._close_chunk()
        if time.monotonic_ns() >= self._wall_due_ns:
            self.flush()

    def write_many(self, topics: list[str], topic: list[int], data: bytes, start: list[int], end: list[int],
                   log_time_ns: list[int]) -> None:
        """`write_json` of many messages: message k is data[start[k] : end[k]] on topics[topic[k]] at
        log_time_ns[k]. Without timed chunks (a conversion) a failed write raises after the last message."""
        if self._timed:
            for k, a, b, t in zip(topic, start, end, log_time_ns):
                self.write_json(topics[k], t, data[a:b])
            return
        logs = [self._channels[t][1] for t in topics]
        for k, a, b, t in zip(topic, start, end, log_time_ns):
            logs[k](data[a:b], t, None)
        failure = _SINK_ERRORS.take()
        if failure is not None:
            raise failure

    def set_metadata(self, metadata: dict) -> None:
        """Update keys of the `fuelid` metadata (e.g. truck = VIN when first seen) and write the whole
        record again; readers take the last one. Flushed at once, so a cut file still names its truck."""
        self.metadata.update(metadata)
        self._writer.write_metadata(METADATA_NAME, _metadata_strings(self.metadata))
        if self._timed:
            self.flush()

    def flush_if_due(self) -> None:
        """Flush when `chunk_flush_s` of wall time has passed since the last flush."""
        if self._timed and time.monotonic_ns() >= self._wall_due_ns:
            self.flush()

    def _close_chunk(self) -> None:
        # One chunk per `chunk_flush_s` of log time, pushed to the OS; the disk sync waits for flush(), on
        # the wall clock, so converting a recording (hours of log time a minute) does not fsync per chunk.
        self._writer.flush()
        self._log_due_ns = None

    def flush(self) -> None:
        """Close the open chunk and push everything to the OS (and the disk when fsync)."""
        self._close_chunk()
        if self._fsync:
            fsync_path(self.path)
        self._wall_due_ns = time.monotonic_ns() + self._flush_ns

    def close(self) -> None:
        """Write the summary and index (MCAP finish) and close the file."""
        if self._closed:
            return
        self._closed = True
        if self.columns is not None:
            self.columns.flush()
        self._channels.clear()  # a write after close raises KeyError instead of vanishing without a sink
        self._writer.close()
        if self._fsync:
            fsync_path(self.path)

    def __enter__(self) -> McapLogWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass(frozen=True)
class DamagedChunk:
    """Bytes [`start`, `end`) of an MCAP file that fail verification: a chunk whose records do not
    decompress or do not match their CRC, or bytes where no record parses (a garbled record header)."""

    path: Path
    start: int
    end: int
    reason: str

    def __str__(self) -> str:
        return f"{self.path}: damaged chunk at bytes {self.start}-{self.end} ({self.reason})"

    def to_dict(self) -> dict:
        return {"start": self.start, "end": self.end, "bytes": self.end - self.start, "reason": self.reason}


_RECORD_HEAD = struct.Struct("<BQ")  # opcode, record length
_CHUNK_HEAD_BYTES = 8 + 8 + 8 + 4 + 4 + 8  # times, uncompressed size and CRC, empty compression, records length
_OPCODES = set(range(Opcode.HEADER, Opcode.DATA_END + 1))


def chunk_records(chunk: Chunk) -> bytes:
    """The uncompressed records of `chunk`, verified against its size and CRC; ValueError saying what is wrong.

    (mcap's readers decompress without checking the CRC on the indexed path: a flipped byte inside a zstd
    frame often still decompresses, to different records.)"""
    if chunk.compression == "zstd":
        try:
            data = zstandard.decompress(chunk.data, max_output_size=chunk.uncompressed_size)
        except zstandard.ZstdError as exc:
            raise ValueError(f"does not decompress: {exc}") from None
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise ValueError(f"compression {chunk.compression!r} not written by fuelid")
    if len(data) != chunk.uncompressed_size:
        raise ValueError("uncompressed size differs from the chunk header")
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise ValueError("CRC mismatch")
    return data


def _verified_chunk(buf, pos: int, size: int) -> tuple[Chunk, bytes, int] | None:
    """(chunk, its verified records, end offset) when a whole, intact Chunk record starts at `pos`, else None."""
    if pos + 9 > size:
        return None
    opcode, length = _RECORD_HEAD.unpack_from(buf, pos)
    if opcode != Opcode.CHUNK or length < _CHUNK_HEAD_BYTES or pos + 9 + length > size:
        return None
    try:
        chunk = Chunk.read(ReadDataStream(io.BytesIO(buf[pos + 9 : pos + 9 + length])))
        return chunk, chunk_records(chunk), pos + 9 + length
    except Exception:  # noqa: BLE001 -- mcap, struct and zstd errors alike: not an intact chunk
        return None


def _summary_intact(buf, size: int) -> bool:
    """Whether the footer's summary CRC (when written) matches the summary section: the chunk index, channel
    list and statistics have no CRC of their own."""
    footer = size - len(MAGIC) - 9 - 20
    if footer < len(MAGIC) or buf[footer] != Opcode.FOOTER:
        return False
    summary_start, _, crc = struct.unpack_from("<QQI", buf, footer + 9)
    if not len(MAGIC) <= summary_start <= footer:
        return False
    return crc == 0 or zlib.crc32(buf[summary_start : footer + 9 + 16]) == crc


class _Scan:
    """Sequential reading of an MCAP file from its start, for files without a usable footer and index.

    Hand-written on top of mcap's record classes because mcap's StreamReader cannot tell a record cut by
    the end of the file from a whole one (short reads pass silently) and its errors discard everything
    read so far. Here a record counts only when all its bytes are present and it parses; a chunk counts
    only when it decompresses and matches its CRC, so its messages come out all or none. Bytes where no
    record parses are damage: the scan goes on at the next intact chunk and reports the bytes skipped to
    `on_damage`; when no intact chunk follows, the file was cut there. `good_end` is the offset just after
    the last record that counted; `complete` tells whether the footer was reached, `statistics` is the
    summary's Statistics record when the summary CRC vouches for it.
    """

    # every record is parsed, so one whose bytes are not what its opcode says is damage, not skipped unread
    _PARSERS = {
        Opcode.HEADER: Header.read,
        Opcode.SCHEMA: Schema.read,
        Opcode.CHANNEL: Channel.read,
        Opcode.METADATA: Metadata.read,
        Opcode.STATISTICS: Statistics.read,
        Opcode.FOOTER: Footer.read,
        Opcode.MESSAGE_INDEX: MessageIndex.read,
        Opcode.CHUNK_INDEX: ChunkIndex.read,
        Opcode.ATTACHMENT: Attachment.read,
        Opcode.ATTACHMENT_INDEX: AttachmentIndex.read,
        Opcode.METADATA_INDEX: MetadataIndex.read,
        Opcode.SUMMARY_OFFSET: SummaryOffset.read,
        Opcode.DATA_END: DataEnd.read,
    }
    _KEPT = {Opcode.SCHEMA, Opcode.CHANNEL, Opcode.METADATA, Opcode.STATISTICS, Opcode.FOOTER}

    def __init__(self, f: IO[bytes], path: Path, on_damage: Callable[[DamagedChunk], None]):
        f.seek(0, io.SEEK_END)
        self.size = f.tell()
        f.seek(0)
        if f.read(len(MAGIC)) != MAGIC:
            raise FuelidError(f"not an MCAP file: {path}")
        self._buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        self._path = path
        self._on_damage = on_damage
        self.good_end = len(MAGIC)
        self.complete = False
        self.statistics: Statistics | None = None

    def records(self) -> Iterator[McapRecord]:
        """Schema, Channel, Message and Metadata records in file order, chunks broken up."""
        buf, size, pos = self._buf, self.size, len(MAGIC)
        while pos + 9 <= size:
            opcode, length = _RECORD_HEAD.unpack_from(buf, pos)
            end = pos + 9 + length
            try:
                # a wrong length would swallow what follows; a chunk's CRC vouches for its own length, so
                # garbage after an intact chunk is damage after it, not in it
                followed = end == size or opcode in (Opcode.FOOTER, Opcode.CHUNK) or self._record_starts_at(end)
                if opcode not in _OPCODES or end > size or not followed:
                    raise ValueError("garbled record header")
                records = self._parse(opcode, buf, pos, end)
            except Exception as exc:  # noqa: BLE001 -- any failure to parse a whole record is damage or the cut
                whole = end == size or end < size and self._record_starts_at(end)  # its length is believable
                resume = end if whole else self._next_chunk(pos + 1)
                if resume is None:  # nothing intact follows: the file ends inside this record
                    return
                self._on_damage(DamagedChunk(self._path, pos, resume, str(exc) or type(exc).__name__))
                pos = resume
                continue
            pos = self.good_end = end
            yield from records
            if opcode == Opcode.FOOTER:
                self.complete = True
                self.good_end = size  # the closing magic
                return

    def _parse(self, opcode: int, buf, pos: int, end: int) -> list[McapRecord]:
        if opcode == Opcode.CHUNK:
            found = _verified_chunk(buf, pos, end)
            if found is None:
                raise ValueError(_what_is_wrong(buf, pos, end))
            return list(_records_in(found[1]))
        body = buf[pos + 9 : end]
        stream = ReadDataStream(io.BytesIO(body))
        if opcode == Opcode.MESSAGE:
            return [Message.read(stream, len(body))]
        record = self._PARSERS[opcode](stream)
        if stream.count != len(body):  # e.g. a chunk whose opcode byte turned into a message index's
            raise ValueError(f"a {Opcode(opcode).name} record that does not fill its length")
        if opcode not in self._KEPT:  # indexes, attachments: nothing to recover from them
            return []
        if isinstance(record, Statistics):
            self.statistics = record if _summary_intact(buf, self.size) else None
            return []
        return [] if isinstance(record, Footer) else [record]

    def _record_starts_at(self, pos: int) -> bool:
        """Whether a record plausibly starts at `pos`: a known opcode, whole or cut by the end of the file (a
        record's length is believed when what follows it looks like a record)."""
        return pos < self.size and self._buf[pos] in _OPCODES

    def _next_chunk(self, start: int) -> int | None:
        """Offset of the first intact chunk at or after `start`, None when there is none."""
        pos = start
        while (pos := self._buf.find(bytes([Opcode.CHUNK]), pos)) != -1:
            if _verified_chunk(self._buf, pos, self.size) is not None:
                return pos
            pos += 1
        return None


def _records_in(data: bytes) -> Iterator[McapRecord]:
    """The Schema, Channel and Message records of a chunk's verified records."""
    stream = ReadDataStream(io.BytesIO(data))
    while stream.count < len(data):
        opcode, length = stream.read1(), stream.read8()
        if opcode == Opcode.MESSAGE:
            yield Message.read(stream, length)
        elif opcode == Opcode.SCHEMA:
            yield Schema.read(stream)
        elif opcode == Opcode.CHANNEL:
            yield Channel.read(stream)
        else:
            stream.read(length)


def _indexed_reader(f: IO[bytes]) -> SeekingReader | None:
    """mcap's own reader when the file ends in a footer with a summary that its CRC vouches for, else None."""
    f.seek(-len(MAGIC), io.SEEK_END)
    if f.read(len(MAGIC)) != MAGIC:
        return None
    with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
        if not _summary_intact(buf, len(buf)):
            return None
    f.seek(0)  # SeekingReader reads the leading magic from the current position
    reader = SeekingReader(f)
    return reader if reader.get_summary() is not None else None


@dataclass(frozen=True)
class _ChunkSpan:
    """Bytes [`start`, `end`) of one Chunk record; `channels`: the ids its message indexes name (None: unknown)."""

    start: int
    end: int
    channels: frozenset[int] | None = None


def _located_chunks(f: IO[bytes], reader: SeekingReader | None) -> list[_ChunkSpan] | None:
    """Every chunk of a file with an intact summary, in file order: from its chunk index, or, for a file written
    without one (`convert`), by walking the data section's top-level records by their length fields. The walk
    counts only when it ends on the DataEnd record where the summary begins, meets no message outside a chunk
    and finds as many chunks as the statistics say. None when neither vouches: the caller scans the file."""
    if reader is None:
        return None
    summary = reader.get_summary()
    if summary.chunk_indexes:
        return [_ChunkSpan(c.chunk_start_offset, c.chunk_start_offset + c.chunk_length,
                           frozenset(c.message_index_offsets) or None)
                for c in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)]
    if summary.statistics is None:
        return None
    with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
        (data_end,) = struct.unpack_from("<Q", buf, len(buf) - len(MAGIC) - 20)  # the footer's summary start
        pos, spans = len(MAGIC), []
        while pos + 9 <= data_end:
            opcode, length = _RECORD_HEAD.unpack_from(buf, pos)
            end = pos + 9 + length
            if opcode not in _OPCODES or opcode == Opcode.MESSAGE or end > data_end:
                return None  # a garbled length, or messages the chunks do not hold
            if opcode == Opcode.CHUNK:
                spans.append(_ChunkSpan(pos, end))
            pos = end
            if opcode == Opcode.DATA_END:
                break
        else:
            return None
    return spans if pos == data_end and len(spans) == summary.statistics.chunk_count else None


def chunks_located(path: str | Path) -> bool:
    """Whether `path` is a complete file whose summary locates every chunk (see `_located_chunks`), so that it
    reads chunk by chunk without a sequential scan; FuelidError if not MCAP."""
    f, reader = _open(path)
    with f:
        return _located_chunks(f, reader) is not None


def _open(path: str | Path) -> tuple[IO[bytes], SeekingReader | None]:
    f = open(path, "rb")
    try:
        if f.read(len(MAGIC)) != MAGIC:
            raise FuelidError(f"not an MCAP file: {path}")
        try:
            return f, _indexed_reader(f)
        except (McapError, OSError, ValueError, struct.error, UnicodeDecodeError):
            return f, None  # no footer, or a damaged one: read sequentially
    except BaseException:
        f.close()
        raise


_MESSAGE_HEAD = struct.Struct("<HIQ")  # Message record: channel id, sequence, log time (then publish time, data)


def _chunk_messages(data: bytes, topics: dict[int, str]) -> Iterator[tuple[str, int, bytes]]:
    """(topic, log_time, data) of a chunk's verified records on the channels `topics` (id → topic), in order.

    The records are walked by their length fields and only wanted messages are sliced out: mcap's
    breakup_chunk builds an object for every record, which made reading a decoded topic cost as much as
    reading the /can/raw frames interleaved with it in every chunk (5× slower on the 1.5 h trip)."""
    pos, end = 0, len(data)
    while pos < end:
        opcode, (length,) = data[pos], struct.unpack_from("<Q", data, pos + 1)
        body = pos + 9
        if opcode == Opcode.MESSAGE:
            channel, _, log_time = _MESSAGE_HEAD.unpack_from(data, body)
            if channel in topics:
                yield topics[channel], log_time, data[body + 22 : body + length]
        pos = body + length


def _damage_handler(damaged: list[DamagedChunk] | None) -> Callable[[DamagedChunk], None]:
    """Collect damage into `damaged`, or, when the caller gave no list, stop with an error naming the bytes."""
    if damaged is not None:
        return damaged.append

    def refuse(d: DamagedChunk) -> None:
        raise FuelidError(f"{d}; `fuelid recover` keeps every intact chunk")

    return refuse


def _indexed_chunks(path: str | Path, f: IO[bytes], reader: SeekingReader, chunks: list[_ChunkSpan],
                    wanted: set[str] | None,
                    on_damage: Callable[[DamagedChunk], None]) -> Iterator[tuple[dict[int, str], bytes]]:
    """(channel id → topic of the wanted JSON channels, verified records) of each of the `chunks` that may hold a
    wanted channel, in file order."""
    ids = {i: c.topic for i, c in reader.get_summary().channels.items()
           if c.message_encoding == "json" and (wanted is None or c.topic in wanted)}
    with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
        for chunk in chunks:
            if chunk.channels is not None and not ids.keys() & chunk.channels:
                continue  # the chunk's message index says none of the wanted channels is in it
            start, end = chunk.start, chunk.end
            found = _verified_chunk(buf, start, min(end, len(buf)))
            if found is None or found[2] != end:
                on_damage(DamagedChunk(Path(path), start, end, _what_is_wrong(buf, start, end)))
                continue
            yield ids, found[1]


def _raw_messages(path: str | Path, topics: Iterable[str] | None,
                  on_damage: Callable[[DamagedChunk], None]) -> Iterator[tuple[str, int, bytes]]:
    wanted = None if topics is None else set([topics] if isinstance(topics, str) else topics)
    f, reader = _open(path)
    with f:
        chunks = _located_chunks(f, reader)
        if chunks is not None:
            for ids, data in _indexed_chunks(path, f, reader, chunks, wanted, on_damage):
                yield from _chunk_messages(data, ids)
            return
        channels: dict[int, Channel] = {}
        for record in _Scan(f, Path(path), on_damage).records():
            if isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message) and record.channel_id in channels:
                channel = channels[record.channel_id]
                if channel.message_encoding == "json" and (wanted is None or channel.topic in wanted):
                    yield channel.topic, record.log_time, record.data


def read_chunks(path: str | Path, topics: Iterable[str], *,
                damaged: list[DamagedChunk] | None = None) -> Iterator[tuple[dict[int, str], bytes]]:
    """(channel id → topic of the wanted JSON channels, records) for every chunk of `path` that may hold one
    of `topics`, in file order: the chunk's uncompressed records in MCAP record framing, verified as in
    `read_messages`, for callers that parse many messages at once. A file without a usable index is scanned
    and its messages come re-framed as Message records, a few thousand at a time. Damage as in
    `read_messages`; FuelidError for a file that is not MCAP."""
    wanted, on_damage = set(topics), _damage_handler(damaged)
    f, reader = _open(path)
    with f:
        chunks = _located_chunks(f, reader)
        if chunks is not None:
            yield from _indexed_chunks(path, f, reader, chunks, wanted, on_damage)
            return
    batch, ids = [], {}
    for topic, log_time, data in _raw_messages(path, wanted, on_damage):
        channel = ids.setdefault(topic, len(ids) + 1)
        batch.append(_MESSAGE_RECORD.pack(Opcode.MESSAGE, 22 + len(data), channel, 0, log_time, log_time) + data)
        if len(batch) == 4096:
            yield {i: t for t, i in ids.items()}, b"".join(batch)
            batch = []
    if batch:
        yield {i: t for t, i in ids.items()}, b"".join(batch)


_MESSAGE_RECORD = struct.Struct("<BQHIQQ")  # opcode, length, channel id, sequence, log time, publish time


def _what_is_wrong(buf, start: int, end: int) -> str:
    """Why the Chunk record at bytes [start, end) of `buf` fails verification, for the damage report."""
    try:
        chunk_records(Chunk.read(ReadDataStream(io.BytesIO(buf[start + 9 : end]))))
    except Exception as exc:  # noqa: BLE001 -- the reason is all that is wanted here
        return str(exc) or type(exc).__name__
    return "garbled record header"


def read_messages(path: str | Path, topics: Iterable[str] | str | None = None, *,
                  damaged: list[DamagedChunk] | None = None) -> Iterator[tuple[str, int, dict]]:
    """(topic, log_time [ns], record) of every JSON message, in file order, optionally of some topics only.

    A complete file is read through its index; a truncated one (no footer, cut at any byte) sequentially,
    giving every message up to its last complete chunk. Every chunk is verified against its CRC: a damaged
    one raises FuelidError naming the file and its byte range, or, when the caller passes a `damaged` list,
    is skipped and appended to it. Raises FuelidError for a file that is not MCAP.
    """
    for topic, log_time, data in _raw_messages(path, topics, _damage_handler(damaged)):
        try:
            yield topic, log_time, orjson.loads(data)
        except orjson.JSONDecodeError as exc:
            raise FuelidError(f"{path}: a message on {topic} at {log_time} ns is not JSON ({exc})") from exc


def read_attachments(path: str | Path, name: str) -> tuple[dict[str, int], list[bytes]] | None:
    """(messages per topic, the data of every attachment named `name` in file order) of a complete file whose
    summary CRC vouches for its index and statistics and that has such attachments; None for any other file.
    An attachment failing its CRC raises FuelidError naming its bytes. The counts are the summary's."""
    f, reader = _open(path)
    with f:
        if reader is None:
            return None
        summary = reader.get_summary()
        indexes = sorted((a for a in summary.attachment_indexes if a.name == name), key=lambda a: a.offset)
        if not indexes or summary.statistics is None:
            return None
        counts = {c.topic: summary.statistics.channel_message_counts.get(i, 0) for i, c in summary.channels.items()}
        blocks = []
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
            for a in indexes:
                start, end = a.offset, a.offset + a.length
                try:
                    if buf[start] != Opcode.ATTACHMENT or end > len(buf):
                        raise ValueError("no attachment record there")
                    record = Attachment.read(ReadDataStream(io.BytesIO(buf[start + 9:end])))
                    if struct.unpack_from("<I", buf, end - 4)[0] not in (0, zlib.crc32(buf[start + 9:end - 4])):
                        raise ValueError("CRC mismatch")
                except (ValueError, struct.error, McapError, UnicodeDecodeError, EOFError) as exc:
                    raise FuelidError(f"{path}: damaged attachment {name} at bytes {start}-{end} ({exc}); "
                                      "`fuelid recover` keeps every intact chunk") from None
                blocks.append(record.data)
        return counts, blocks


def damaged_chunks(path: str | Path) -> list[DamagedChunk]:
    """Every chunk of `path` that fails verification (empty for an intact file); FuelidError if not MCAP."""
    damaged: list[DamagedChunk] = []
    for _ in _raw_messages(path, None, damaged.append):
        pass
    return damaged


def read_metadata(path: str | Path) -> dict[str, dict[str, str]]:
    """Metadata records by name, the last record of a name winning (e.g. `fuelid` with the VIN)."""
    f, reader = _open(path)
    with f:
        records = reader.iter_metadata() if reader is not None else _Scan(f, Path(path), lambda d: None).records()
        return {r.name: dict(r.metadata) for r in records if isinstance(r, Metadata)}


def _summary_schemas_and_channels(path: Path) -> list[Schema | Channel]:
    """The Schema and Channel records of the file's summary when its CRC vouches for it, else none."""
    f, reader = _open(path)
    with f:
        if reader is None:
            return []
        summary = reader.get_summary()
        return [*summary.schemas.values(), *summary.channels.values()]


@dataclass
class RecoverStats:
    """What `recover` found: messages per topic, bytes of the source [B] kept and lost (damaged chunks skipped,
    and everything after the last complete record), the `damaged` byte ranges, the messages lost when the
    source's summary says how many it held, and whether the source was complete and intact."""

    messages: Counter = field(default_factory=Counter)
    metadata_records: int = 0
    bytes_total: int = 0
    bytes_recovered: int = 0
    complete: bool = False
    truncated: bool = False
    damaged: list[DamagedChunk] = field(default_factory=list)
    messages_lost: int | None = None

    @property
    def bytes_lost(self) -> int:
        return self.bytes_total - self.bytes_recovered

    def to_dict(self) -> dict:
        return {
            "messages": dict(self.messages),
            "message_count": sum(self.messages.values()),
            "metadata_records": self.metadata_records,
            "bytes_total": self.bytes_total,
            "bytes_recovered": self.bytes_recovered,
            "bytes_lost": self.bytes_lost,
            "complete": self.complete,
            "truncated": self.truncated,
            "damaged": [d.to_dict() for d in self.damaged],
            "messages_lost": self.messages_lost,
        }


def recover(src: str | Path, dst: str | Path) -> RecoverStats:
    """Rewrite the readable part of `src` (cut by a power loss, or with damaged chunks) as a valid, indexed
    MCAP `dst`: the same schemas, channels, metadata records and message bytes of every intact chunk up to
    the last complete one; damaged chunks are skipped and listed in the stats."""
    src, dst = Path(src), Path(dst)
    if dst.exists() and dst.resolve() == src.resolve():
        raise FuelidError("recover writes a new file: give an output path other than the input")
    stats = RecoverStats()
    with open(src, "rb") as f:
        scan = _Scan(f, src, stats.damaged.append)
        stats.bytes_total = scan.size
        with open(dst, "wb") as out:
            writer = Writer(out, compression=CompressionType.ZSTD)
            writer.start(library=f"fuelid/{__version__} recover")
            schema_ids: dict[int, int] = {}  # source id -> new id
            channels: dict[int, tuple[int, str]] = {}
            # schemas and channels from an intact summary first: they survive damage to the chunk that held them
            for record in itertools.chain(_summary_schemas_and_channels(src), scan.records()):
                if isinstance(record, Schema) and record.id not in schema_ids:
                    schema_ids[record.id] = writer.register_schema(record.name, record.encoding, record.data)
                elif isinstance(record, Channel) and record.id not in channels:
                    new_id = writer.register_channel(
                        record.topic, record.message_encoding, schema_ids.get(record.schema_id, 0), record.metadata
                    )
                    channels[record.id] = (new_id, record.topic)
                elif isinstance(record, Message) and record.channel_id in channels:
                    new_id, topic = channels[record.channel_id]
                    writer.add_message(new_id, record.log_time, record.data, record.publish_time, record.sequence)
                    stats.messages[topic] += 1
                elif isinstance(record, Metadata):
                    writer.add_metadata(record.name, record.metadata)
                    stats.metadata_records += 1
            writer.finish()
        stats.bytes_recovered = scan.good_end - sum(d.end - d.start for d in stats.damaged)
        stats.complete = scan.complete and not stats.damaged
        stats.truncated = not scan.complete
        if scan.statistics is not None:
            stats.messages_lost = scan.statistics.message_count - sum(stats.messages.values())
        elif not stats.damaged and scan.complete:
            stats.messages_lost = 0
    return stats
