"""The gas-flow meter: its serial line protocol, calibration, reader and capture files.

A thermal mass-flow meter (2.5–125 kg/h, ±2 % of full scale, 0–10 V output) feeds an ADC data logger that
sends one ASCII reading per line over a serial port (docs/reference/formats.md, "Flow-meter serial line protocol"):

    [<device_time_s>,]<volts>

`parse_line` turns one received line into a `FlowReading`; `LineSplitter` cuts the byte stream into lines;
`SerialFlowMeter` reads a port with pyserial and survives the device vanishing; `CaptureWriter` and
`read_capture` store and replay a received stream with host timestamps (`*.flow`, `*.flow.gz`).
"""
from __future__ import annotations

import dataclasses
import gzip
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Callable, Iterator

#: Longest line [bytes, terminator excluded] the protocol allows; longer ones are cut and invalid.
MAX_LINE = 256

CAPTURE_HEADER = b"# fuelid flowmeter capture v1"

# A plain decimal number (no exponent, no nan/inf), spaces or tabs allowed around it.
_NUMBER = rb"[ \t]*([+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+))[ \t]*"
_LINE = re.compile(rb"(?:" + _NUMBER + rb",)?" + _NUMBER)

# Printable ASCII except the backslash stays as is; every other byte becomes \xHH.
_UNSAFE = re.compile(rb"[^\x20-\x5b\x5d-\x7e]")
_ESCAPED = re.compile(r"(?:[\x20-\x5b\x5d-\x7e]|\\x[0-9a-fA-F]{2})*")
_CAPTURE_LINE = re.compile(rb"\(([+-]?[0-9]+(?:\.[0-9]*)?)\) (.*)")


def escape(line: bytes) -> str:
    """The received bytes as printable ASCII: bytes outside 0x20–0x7E and the backslash become `\\xHH`."""
    return _UNSAFE.sub(lambda m: b"\\x%02x" % m[0][0], line).decode("ascii")


def unescape(text: str) -> bytes:
    """Inverse of `escape`; ValueError for text `escape` cannot have produced."""
    if not _ESCAPED.fullmatch(text):
        raise ValueError(f"not an escaped line: {text!r}")
    return re.sub(r"\\x([0-9a-fA-F]{2})", lambda m: chr(int(m[1], 16)), text).encode("latin-1")


@dataclass(frozen=True)
class Calibration:
    """Linear calibration of the meter: flow [kg/h] = gain [kg/h/V] × volts [V] + offset [kg/h].

    The default maps the 0–10 V output onto 0–125 kg/h. `min_kg_h`/`max_kg_h` bound the meter's measurable
    range [kg/h], `max_volts` the analog output [V].
    """

    gain_kg_h_per_v: float = 12.5
    offset_kg_h: float = 0.0
    min_kg_h: float = 2.5
    max_kg_h: float = 125.0
    max_volts: float = 10.0


@dataclass(frozen=True, slots=True)
class FlowReading:
    """One received line. `t` host time [s]; `device_t` the data logger's clock [s]; `volts` [V];
    `flow_kg_h` [kg/h], None unless status is "ok"; `raw` the line as received, escaped (see `escape`)."""

    t: float
    device_t: float | None
    volts: float | None
    flow_kg_h: float | None
    status: str
    raw: str

    def to_record(self) -> dict:
        """The `/flowmeter` MCAP message (docs/reference/formats.md)."""
        return dataclasses.asdict(self)


def invalid_reading(raw: bytes, host_t: float) -> FlowReading:
    """A reading that carries no number: garbage, a partial line, an over-long line."""
    return FlowReading(host_t, None, None, None, "invalid", escape(raw))


def parse_line(raw: bytes, host_t: float, calibration: Calibration = Calibration()) -> FlowReading:
    """Parse one line (terminator removed) received at host time `host_t` [s]. Never raises."""
    match = _LINE.fullmatch(raw) if len(raw) <= MAX_LINE else None
    if match is None:
        return invalid_reading(raw, host_t)
    device_t = None if match[1] is None else float(match[1])
    volts = float(match[2])
    flow = calibration.gain_kg_h_per_v * volts + calibration.offset_kg_h
    if volts > calibration.max_volts or flow > calibration.max_kg_h:
        status = "over_range"
    elif flow < calibration.min_kg_h:
        status = "below_range"
    else:
        status = "ok"
    return FlowReading(host_t, device_t, volts, flow if status == "ok" else None, status, escape(raw))


class LineSplitter:
    """Cuts a byte stream delivered in arbitrary chunks into lines ending in `\\n` or `\\r\\n`.

    A partial line is kept until its terminator arrives. A line longer than MAX_LINE is cut to its first
    MAX_LINE + 1 bytes (so `parse_line` reports it invalid) and the rest of it, up to the next `\\n`, is
    dropped and counted in `dropped_bytes`: memory stays bounded whatever the device sends. The lines come
    out the same however the stream is split into chunks.
    """

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._discarding = False  # inside the dropped tail of an over-long line
        self.dropped_bytes = 0

    def feed(self, chunk: bytes) -> list[bytes]:
        """Add received bytes; return the lines they complete, terminators removed."""
        lines = []
        start = 0
        while True:
            end = chunk.find(b"\n", start)
            piece = chunk[start:] if end < 0 else chunk[start:end]
            if self._discarding:
                self.dropped_bytes += len(piece)
            else:
                self._buffer += piece
                if end >= 0:
                    line = bytes(self._buffer)
                    line = line[:-1] if line.endswith(b"\r") else line
                    if len(line) > MAX_LINE:
                        self.dropped_bytes += len(line) - MAX_LINE - 1
                        line = line[: MAX_LINE + 1]
                    lines.append(line)
                    self._buffer.clear()
                # MAX_LINE + 2 rather than + 1: the byte after MAX_LINE may still be the `\r` of `\r\n`.
                elif len(self._buffer) >= MAX_LINE + 2:
                    lines.append(bytes(self._buffer[: MAX_LINE + 1]))
                    self.dropped_bytes += len(self._buffer) - MAX_LINE - 1
                    self._buffer.clear()
                    self._discarding = True
            if end < 0:
                return lines
            self._discarding = False
            start = end + 1

    def reset(self) -> bytes:
        """Forget the partial line (e.g. the device vanished mid-line) and return it."""
        partial = bytes(self._buffer)
        self._buffer.clear()
        self._discarding = False
        return partial


class CaptureWriter:
    """Writes a flow-meter capture file (`*.flow`, gzip-compressed when the name ends in `.gz`).

    Buffered data is flushed to the OS at least every `flush_s` [s] of wall time, on a write.
    """

    def __init__(self, path: str | Path, *, flush_s: float = 1.0):
        self.path = Path(path)
        self._file: IO[bytes] = gzip.open(self.path, "wb") if self.path.suffix == ".gz" else open(self.path, "wb")
        self._flush_s = flush_s
        self._flushed_at = time.monotonic()
        self._file.write(CAPTURE_HEADER + b"\n")

    def write(self, host_t: float, line: bytes) -> None:
        """Record one received line (terminator removed) with its host time [s, Unix]."""
        self._file.write(b"(%.6f) %s\n" % (host_t, escape(line).encode("ascii")))
        self._maybe_flush()

    def comment(self, text: str | bytes) -> None:
        """Record an event (e.g. the device vanished) as a `#` comment line, which readers skip."""
        text = text.encode("utf-8") if isinstance(text, str) else text
        self._file.write(b"# %s\n" % escape(text).encode("ascii"))
        self._maybe_flush()

    def _maybe_flush(self) -> None:
        now = time.monotonic()
        if now - self._flushed_at >= self._flush_s:
            self._file.flush()
            self._flushed_at = now

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> CaptureWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class CaptureReader:
    """Iterator over (host_t [s], line bytes) of a capture file, plain or gzip (recognised by content).

    Malformed lines, and a last line without its newline (a file cut while being written), are skipped
    and counted in `skipped`; a truncated or corrupt gzip stream ends the iteration and sets `truncated`.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.skipped = 0
        self.truncated = False
        self._lines = self._read()

    def __iter__(self) -> CaptureReader:
        return self

    def __next__(self) -> tuple[float, bytes]:
        return next(self._lines)

    def _read(self) -> Iterator[tuple[float, bytes]]:
        with open(self.path, "rb") as raw:
            gzipped = raw.read(2) == b"\x1f\x8b"
        opener = gzip.open if gzipped else open
        with opener(self.path, "rb") as f:
            try:
                for line in f:
                    item = self._parse(line)
                    if item is not None:
                        yield item
            except (EOFError, OSError, gzip.zlib.error):  # cut or damaged gzip stream: keep what came before
                self.truncated = True

    def _parse(self, line: bytes) -> tuple[float, bytes] | None:
        if line.startswith(b"#"):
            return None
        if line.endswith(b"\n"):
            line = line[:-2] if line.endswith(b"\r\n") else line[:-1]
            match = _CAPTURE_LINE.fullmatch(line)
            if match is not None:
                try:
                    return float(match[1]), unescape(match[2].decode("ascii"))
                except (ValueError, UnicodeDecodeError):
                    pass
        self.skipped += 1
        return None


def read_capture(path: str | Path) -> CaptureReader:
    """Iterate over (host_t [s], line bytes) of a capture file; see `CaptureReader` for the counters."""
    return CaptureReader(path)


def capture_readings(path: str | Path, calibration: Calibration = Calibration()) -> Iterator[FlowReading]:
    """The readings of a recorded stream, as the live reader would have produced them."""
    for host_t, line in read_capture(path):
        yield parse_line(line, host_t, calibration)


@dataclass
class FlowMeterCounts:
    """What a `SerialFlowMeter` has seen. `partial` lines (cut by a (re)connect or an unplug) are also
    counted in `invalid`."""

    lines: int = 0
    ok: int = 0
    invalid: int = 0
    below_range: int = 0
    over_range: int = 0
    partial: int = 0
    disconnects: int = 0
    reconnects: int = 0


class SerialFlowMeter:
    """Reads the flow meter's data logger on a serial port and yields `FlowReading`s with host times.

    `port` is anything `serial.serial_for_url` opens: a device (`/dev/ttyUSB0`, better a stable
    `/dev/serial/by-id/...` link), `loop://`, `socket://host:port`. When the device vanishes (read error),
    `state` becomes "disconnected", the disconnect is counted, and the port is re-opened by name with
    exponential backoff from `reconnect_s[0]` to `reconnect_s[1]` [s] until it comes back.

    The first line after each (re)open and the unfinished line at an unplug may be fragments of a reading
    ("217" of "3.217"), so they are reported invalid and counted as `partial`; in the capture file they
    appear as comments, so a replay yields exactly the readings that were trusted.

    Iterate `readings()` in one thread; `close()` from any thread ends it within `read_timeout_s` [s].
    """

    def __init__(
        self,
        port: str,
        baudrate: int = 9600,
        calibration: Calibration = Calibration(),
        *,
        capture: CaptureWriter | None = None,
        read_timeout_s: float = 0.1,
        reconnect_s: tuple[float, float] = (0.5, 10.0),
        clock: Callable[[], float] = time.time,
    ):
        self.port = port
        self.baudrate = baudrate
        self.calibration = calibration
        self.capture = capture
        self.read_timeout_s = read_timeout_s
        self.reconnect_s = reconnect_s
        self.clock = clock
        self.counts = FlowMeterCounts()
        self.state = "closed"  # "connected", "disconnected" (retrying) or "closed"
        self.last_error: str | None = None
        self._serial = None
        self._splitter = LineSplitter()
        self._line_trusted = False  # False until the first line after an open has ended
        self._stop = threading.Event()

    def readings(self) -> Iterator[FlowReading]:
        """Yield readings as lines arrive, until `close()`; never raises for device trouble."""
        import serial  # pyserial; imported here so parsing and capture replay do not need it

        # The backoff grows on every failed open and every read error, and falls back only once data
        # arrives, so a port that opens but cannot be read does not spin.
        delay = self.reconnect_s[0]
        while not self._stop.is_set():
            if self._serial is None:
                try:
                    self._open(serial)
                except (serial.SerialException, OSError, ValueError) as exc:
                    self.state, self.last_error = "disconnected", str(exc)
                    self._stop.wait(delay)
                    delay = min(2 * delay, self.reconnect_s[1])
                    continue
            try:
                chunk = self._serial.read(self._serial.in_waiting or 1)
            except (serial.SerialException, OSError) as exc:
                self.last_error = str(exc)
                yield from self._disconnect()
                self._stop.wait(delay)
                delay = min(2 * delay, self.reconnect_s[1])
                continue
            if chunk:
                delay = self.reconnect_s[0]
                host_t = self.clock()
                for line in self._splitter.feed(chunk):
                    yield self._reading(line, host_t)
        self._close_port()
        self.state = "closed"

    def close(self) -> None:
        """Stop `readings()` (from any thread)."""
        self._stop.set()

    def _open(self, serial) -> None:
        self._serial = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=self.read_timeout_s)
        if self.state == "disconnected" and self.counts.disconnects:
            self.counts.reconnects += 1
        self.state = "connected"
        self._line_trusted = False
        if self.capture:
            self.capture.comment(f"connected {self.port}")

    def _disconnect(self) -> Iterator[FlowReading]:
        self.counts.disconnects += 1
        self.state = "disconnected"
        self._close_port()
        partial = self._splitter.reset()
        if self.capture:
            self.capture.comment(f"disconnected {self.port}: {self.last_error}")
        if partial:
            yield self._partial(partial, self.clock())

    def _close_port(self) -> None:
        if self._serial is not None:
            try:
                self._serial.close()
            except OSError:
                pass
            self._serial = None

    def _reading(self, line: bytes, host_t: float) -> FlowReading:
        if not self._line_trusted:
            self._line_trusted = True
            return self._partial(line, host_t)
        if self.capture:
            self.capture.write(host_t, line)
        reading = parse_line(line, host_t, self.calibration)
        self._count(reading)
        return reading

    def _partial(self, line: bytes, host_t: float) -> FlowReading:
        if self.capture:
            self.capture.comment(b"partial (%.6f) %s" % (host_t, line))
        self.counts.partial += 1
        reading = invalid_reading(line, host_t)
        self._count(reading)
        return reading

    def _count(self, reading: FlowReading) -> None:
        self.counts.lines += 1
        setattr(self.counts, reading.status, getattr(self.counts, reading.status) + 1)
