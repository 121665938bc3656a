"""The one decode-and-write path: CAN frames (and flow-meter readings) in, MCAP channels out.

`fuelid convert` drives a Recorder from recorded files, the daemon from a live `can.Notifier`; both write the
same channels (docs/reference/formats.md), so a replayed log and its conversion hold identical decoded values.
"""
import hashlib
from collections import Counter
from dataclasses import dataclass, field

import can
import numpy as np

from fuelid import __version__
from fuelid.dbc import FMS_DBC
from fuelid.logger.decode import Decoder, message_schema
from fuelid.logger.flowmeter import FlowReading
from fuelid.logger.frame_block import FrameBlock
from fuelid.logger.j1939 import parse_ids
from fuelid.logger.json_rows import number_texts
from fuelid.logger.mcap_log import FLOWMETER_SCHEMA, RAW_SCHEMA, McapLogWriter, raw_record, raw_records
from fuelid.logger.tp import TransportReassembler


def dbc_sha256() -> str:
    return hashlib.sha256(FMS_DBC.read_bytes()).hexdigest()


CONVERT_CHUNK_BYTES = 4 << 20
"""Records per chunk of a converted file [bytes, uncompressed]: about a minute of a busy bus."""


def open_writer(path, *, truck: str = "unknown", source: str = "", live: bool = True) -> McapLogWriter:
    """An MCAP writer for `path` with the fuelid metadata record (truck, logger version, DBC hash, source).

    live (the daemon, which a power cut may stop): one-second chunks with message indexes, synced to disk
    every second of wall time. Otherwise (a conversion, which can be run again): big chunks, no message
    indexes, no sync; less than half the bytes (README, Logging and converting). Both write the decoded
    messages also as column attachments (logger.columns) that the dataset reads without JSON: a block when
    full and the rest at close, so a file cut before its close (no summary) reads through its JSON."""
    metadata = {"truck": truck, "logger_version": __version__, "dbc_sha256": dbc_sha256(), "source": source}
    if live:
        return McapLogWriter(path, metadata=metadata, columns=True)
    return McapLogWriter(path, metadata=metadata, chunk_flush_s=None, chunk_size=CONVERT_CHUNK_BYTES,
                         message_indexes=False, fsync=False, columns=True)


@dataclass
class RecorderStats:
    """What a Recorder has seen: counts a summary or a status file reports."""

    frames: int = 0
    error_frames: int = 0
    remote_frames: int = 0
    standard_frames: int = 0
    messages: Counter = field(default_factory=Counter)
    """(message name, source address, ((null signal, status), ...)) -> messages: one count per message, the
    per-signal counts below are summed from it when asked for."""
    flow_readings: Counter = field(default_factory=Counter)  # status -> readings

    @property
    def decoded(self) -> Counter:
        """(message name, source address) -> messages."""
        counts: Counter = Counter()
        for (name, sa, _), n in self.messages.items():
            counts[name, sa] += n
        return counts

    @property
    def invalid(self) -> Counter:
        """(message name, signal, status) -> null values."""
        counts: Counter = Counter()
        for (name, _, nulls), n in self.messages.items():
            for signal, status in nulls:
                counts[name, signal, status] += n
        return counts


class Recorder(can.Listener):
    """Decodes every frame (single-frame J1939 and transport-protocol sessions) and writes it to an MCAP writer.

    /can/raw gets every frame as received; /j1939/<MESSAGE> one record per decoded message and source address;
    /flowmeter one record per meter reading. The first VIN seen names the truck in the file's metadata.
    """

    def __init__(self, writer: McapLogWriter, decoder: Decoder | None = None, reassembler: TransportReassembler | None = None):
        self.decoder = decoder or Decoder()
        self.reassembler = reassembler or TransportReassembler()
        self.stats = RecorderStats()
        self.vin: str | None = None
        self._attach(writer)

    def _attach(self, writer: McapLogWriter) -> None:
        self.writer = writer
        self._topics: set[str] = set()
        if self.vin:
            self.writer.set_metadata({"truck": self.vin})

    def rotate(self, writer: McapLogWriter) -> McapLogWriter:
        """Continue in `writer`; return the previous one for the caller to close."""
        old = self.writer
        self._attach(writer)
        return old

    def _write(self, topic: str, schema: dict, log_time_ns: int, record: dict) -> None:
        if topic not in self._topics:
            self.writer.add_channel(topic, schema)
            self._topics.add(topic)
        self.writer.write(topic, log_time_ns, record)

    def on_message_received(self, msg: can.Message) -> None:
        stats = self.stats
        stats.frames += 1
        self._write("/can/raw", RAW_SCHEMA, int(msg.timestamp * 1e9), raw_record(msg))
        if msg.is_error_frame or msg.is_remote_frame or not msg.is_extended_id:
            stats.error_frames += msg.is_error_frame
            stats.remote_frames += msg.is_remote_frame
            stats.standard_frames += not (msg.is_error_frame or msg.is_remote_frame)
            return
        for session in self.reassembler.feed(msg):
            self._record(self.decoder.decode_payload(session.t, session.pgn, session.sa, session.da, session.payload, tp=session.kind),
                         session.payload)
        self._record(self.decoder.decode(msg), msg.data)

    def on_block(self, block: FrameBlock, readings: list[tuple[int, FlowReading]] = ()) -> None:
        """`on_message_received` of every frame of `block`, in order, with the same messages written and the
        same counts, done column by column: frames of transport-protocol sessions and VI go frame by frame.
        `readings`: (frame, reading) for `on_flow_reading` just before that frame (len(block): after the last)."""
        by_frame = self.reassembler.takes(block.can_id) | self.decoder.frame_by_frame(block.can_id)
        plain_rows = np.flatnonzero(~by_frame)
        plain = block.rows(~by_frame) if len(plain_rows) < len(block) else block
        t_texts = number_texts(plain.t.tolist())
        raw, raw_offsets = raw_records(plain, t_texts)
        decoded = self.decoder.decode_block(plain, t_texts)
        self.stats.frames += len(plain)
        for rows in decoded:
            for (sa, nulls), n in rows.messages.items():
                self.stats.messages[rows.name, sa, nulls] += n
        # message k of the block goes out in the order of `order` (2 × frame for /can/raw, + 1 for the decoded)
        topics = ["/can/raw"] + [f"/j1939/{rows.name}" for rows in decoded]
        schemas = [RAW_SCHEMA] + [message_schema(rows.name) for rows in decoded]
        order = np.concatenate([2 * plain_rows] + [2 * plain_rows[rows.rows] + 1 for rows in decoded])
        topic = np.concatenate([np.full(len(plain), 0)] + [np.full(len(rows.rows), k) for k, rows in enumerate(decoded, 1)])
        shift = np.cumsum([0, len(raw)] + [len(rows.data) for rows in decoded])
        start = np.concatenate([raw_offsets[:-1]] + [rows.offsets[:-1] + shift[k] for k, rows in enumerate(decoded, 1)])
        end = np.concatenate([raw_offsets[1:]] + [rows.offsets[1:] + shift[k] for k, rows in enumerate(decoded, 1)])
        log_time = (plain.t * 1e9).astype(np.int64)
        log_time = np.concatenate([log_time] + [log_time[rows.rows] for rows in decoded])
        sort = np.argsort(order, kind="stable")
        order, topic, start, end, log_time = order[sort], topic[sort], start[sort], end[sort], log_time[sort]
        present, first = np.unique(topic, return_index=True)
        for k in present[np.argsort(first)].tolist():  # channels in the order of their first message
            if topics[k] not in self._topics:
                self.writer.add_channel(topics[k], schemas[k])
                self._topics.add(topics[k])
        data = b"".join([raw] + [rows.data for rows in decoded])
        # the messages up to each frame that goes frame by frame, or reading, then that one
        events = sorted([(row, 0, k) for k, (row, _) in enumerate(readings)]
                        + [(row, 1, 0) for row in np.flatnonzero(by_frame).tolist()])
        add_columns = self._column_rows(block, order, topic, log_time)
        done = 0
        for row, kind, k in [*events, (len(block), 1, 0)]:
            upto = int(np.searchsorted(order, 2 * row))
            self.writer.write_many(topics, topic[done:upto].tolist(), data, start[done:upto].tolist(),
                                   end[done:upto].tolist(), log_time[done:upto].tolist())
            add_columns(done, upto)
            done = upto
            if kind == 0:
                self.on_flow_reading(readings[k][1])
            elif row < len(block):
                self.on_message_received(block.message(row))

    def _column_rows(self, block: FrameBlock, order: np.ndarray, topic: np.ndarray, log_time: np.ndarray):
        """add(lo, hi): the decoded messages among the block's sorted messages lo..hi (topic > 0) into the
        writer's message columns, as `_record` adds each one (no-op without columns)."""
        columns = self.writer.columns
        if columns is None:
            return lambda lo, hi: None
        decoded = np.flatnonzero(topic > 0)
        frame = order[decoded] // 2
        pgn, sa, da = parse_ids(block.can_id[frame])
        t_ns, length, payload = log_time[decoded], block.dlc[frame], block.data[frame]

        def add(lo: int, hi: int) -> None:
            part = slice(*np.searchsorted(decoded, [lo, hi]).tolist())
            columns.add_messages(t_ns[part], pgn[part], sa[part], da[part], length[part], payload[part])
        return add

    def _record(self, decoded, payload: bytes) -> None:
        if decoded is None:
            return
        self.stats.messages[decoded.name, decoded.sa, tuple(decoded.invalid.items())] += 1
        t_ns = int(decoded.t * 1e9)
        self._write(f"/j1939/{decoded.name}", message_schema(decoded.name), t_ns, decoded.to_record())
        if self.writer.columns is not None:
            self.writer.columns.add_message(t_ns, decoded.pgn, decoded.sa, decoded.da, decoded.tp, bytes(payload))
        vin = decoded.values.get("VIN") if decoded.name == "VI" else None
        if vin and vin != self.vin:
            self.vin = vin
            self.writer.set_metadata({"truck": vin})

    def on_flow_reading(self, reading: FlowReading) -> None:
        self.stats.flow_readings[reading.status] += 1
        t_ns = int(reading.t * 1e9)
        self._write("/flowmeter", FLOWMETER_SCHEMA, t_ns, reading.to_record())
        if self.writer.columns is not None:
            self.writer.columns.add_flow(t_ns, reading.flow_kg_h, reading.volts)
