"""Identification data from logged J1939/FMS records: paper 000, Section III (preprocessing).

`build_dataset` turns decoded MCAP records (`/j1939/<MESSAGE>` and `/flowmeter`, see docs/reference/formats.md) into a
`Dataset` on a regular grid of Ts seconds (paper: 0.3 s):

inputs   u[:, 0] engine speed [rpm]   = EEC1.EngSpeed (SPN 190)
         u[:, 1] engine torque [Nm]   = EEC1.ActualEngPercentTorque (SPN 513) [%] × EC1.EngReferenceTorque
                                        (SPN 544) [Nm] / 100; [%] (with a warning) when EC1 never arrived
output   y       fuel flow            = /flowmeter flow_kg_h [kg/h] or LFE1.EngFuelRate (SPN 183) [L/h]

Source addresses. Per signal, the values of the preferred source address of its message are used
(logger.j1939.DEFAULT_SOURCE_PREFERENCE: the engine 0x00, the transmission 0x03 for ETC2); only when that
address never sends a valid value of the signal are the values of the other address that sent the most
valid values used. A null (not available / error) is no sample at all, so it never replaces a valid value.

Resampling (no interpolation). The log time is cut into bins [kTs, (k+1)Ts) (multiples of Ts on the log
clock, computed in integer ns so that a sample on a boundary always opens the next bin):
- averaged (mean of the valid samples in the bin): engine speed, torque, fuel flow, vehicle speed — the
  fast, continuous signals the models use (EEC1 comes every 10–50 ms, LFE1/CCVS1/the meter every ~100 ms);
- held (the last valid sample before the bin's end): every other signal ("extras", named MESSAGE.Signal),
  which is exact for states and enumerations (gear, switches) and right for slow broadcasts;
- the fuel signal's samples (LFE1 or the meter) are binned at their log time minus `fuel_lag_s` (default 0): an ECU
  that reports the mean fuel of its last update period sends it one period late, and with the lag given the fuel of
  a bin is the fuel of the same interval as its speed and torque (benchmarks/bench_engine_oracle.py measures it);
- a bin without a sample of an averaged signal holds the previous value if it is at most `max_gap_s` old at
  the bin's end; after a longer gap the samples are NaN and invalid. Extras hold up to
  max(max_gap_s, 3 × their median period) and never decide validity.
A sample is valid when speed, torque and fuel are all finite and the engine runs: a speed below half the idle
speed (`RUNNING_SHARE` of idle_rpm, below) is an engine that is off, cranking or stalling, whose fuel no model of
the running engine describes (real recordings start and end so; the simulator's engines always run). Maximal runs
of valid samples are the segments (identification runs per segment). Stretches with no data for longer than
max_gap_s are not filled with empty rows: the grid keeps one invalid row there and jumps, so `t` is increasing but
not uniform across such breaks (rotated files and several days of logs stay small).

Operating point (paper: idle, 600 rpm). Idle samples are valid samples with |speed − idle_rpm| ≤
idle_tol_rpm and, when CCVS1 is logged, vehicle speed < 2 km/h, in runs lasting at least idle_min_s
(3 s: a settled idle, not a pass through 600 rpm); u0 = (mean speed, mean torque) and y0 =
mean fuel over them. The torque operating point is the torque the engine reports at idle (friction and
accessories, a few % of the reference torque). idle_rpm defaults to EC1.EngSpeedAtIdlePoint1 when logged,
else 600 rpm. `u`, `y` are kept absolute; `du`, `dy` are the deviations the paper identifies on (PolyModel
subtracts its u0, y0 itself).

Reading (bounded memory). A file that `fuelid convert` wrote carries its decoded messages also as message
columns (`logger.columns` attachments: the J1939 payloads with their times and source addresses, the meter
readings): those are read instead, a block at a time, each (PGN, source address) group's payloads decoded at
once (`Decoder.decode_columns`, the very values of the JSON records), no chunk decompressed. Other files (the
daemon's, older ones) are read a batch of verified chunks at a time (`logger.mcap_log.read_chunks`,
/can/raw skipped); /j1939 records laid out alike are parsed column-wise with numpy (each record's keys checked
byte for byte, its numbers parsed as one text), any other record one by one. Each signal's samples per source
address are reduced as they arrive to, per bin: count, sum (added in time order, as np.bincount adds) and the
last sample, plus the counts of its time steps (for the median period) — memory grows with the grid, not the
records. A signal whose samples come out of time order (a log clock that stepped back, files given latest
first) makes the build start again keeping every sample and sorting at the end: the same values, more memory.

Drive cycles (for eq. 20 / Table I). Each segment is cut into consecutive windows of `cycle_s` seconds
(default 1800 s, the paper's 30-minute cycles); a remainder shorter than cycle_s joins the window before
it, and a segment shorter than cycle_s is one cycle. Segments shorter than `min_cycle_s` belong to no
cycle (id −1). Engine-off stops split segments (no traffic), so a cycle never spans a stop.
"""
from __future__ import annotations

import itertools
import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import orjson

from fuelid.errors import FuelidError
from fuelid.logger import columns as message_columns
from fuelid.logger.decode import Decoder, signal_units
from fuelid.logger.j1939 import DEFAULT_SOURCE_PREFERENCE, preferred_source
from fuelid.logger.mcap_log import MAGIC, read_attachments, read_chunks, read_messages
from fuelid.progress import progress

SPEED = "EEC1.EngSpeed"
TORQUE_PCT = "EEC1.ActualEngPercentTorque"
REF_TORQUE = "EC1.EngReferenceTorque"
IDLE_SPEED = "EC1.EngSpeedAtIdlePoint1"
VEHICLE_SPEED = "CCVS1.WheelBasedVehicleSpeed"
FUEL_SIGNALS = {"flowmeter": ("flowmeter.flow_kg_h", "kg/h"), "lfe1": ("LFE1.EngFuelRate", "L/h")}
AVERAGED = {SPEED, TORQUE_PCT, VEHICLE_SPEED, *(name for name, _ in FUEL_SIGNALS.values())}
NOT_SIGNALS = {"t", "pgn", "sa", "da", "invalid", "tp", "device_t", "raw", "status"}
NUMBER_OR_NULL = {int, float, type(None)}
MEDIANS = {REF_TORQUE, IDLE_SPEED}  # signals whose median value is used
# An engine runs from half its idle speed up: a diesel cranks at 100–250 rpm and idles at 500–800 rpm.
RUNNING_SHARE = 0.5


@dataclass
class Dataset:
    """Resampled identification data; see the module docstring for how each field is made.

    Ts [s]; t [s] bin start times on the log clock (N); u (N×2) [rpm, Nm or %]; y (N) [output_unit];
    u0 (2) and y0 the idle operating point in the same units; valid (N) bool; cycle (N) int drive-cycle id
    (−1 = none); extra MESSAGE.Signal → (N) array in the DBC unit; sources signal → source address used;
    notes the warnings raised while building; fuel_lag_s [s] the fuel signal's reporting lag taken out;
    fuel_period_s [s] the median interval between the fuel signal's samples as logged (0: fewer than two).
    """
    Ts: float
    t: np.ndarray
    u: np.ndarray
    y: np.ndarray
    input_names: tuple[str, str]
    input_units: tuple[str, str]
    output_name: str
    output_unit: str
    u0: np.ndarray
    y0: float
    valid: np.ndarray
    cycle: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    sources: dict[str, int | None] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    fuel_lag_s: float = 0.0
    fuel_period_s: float = 0.0

    def __len__(self) -> int:
        return len(self.t)

    @property
    def du(self) -> np.ndarray:
        """Inputs minus the operating point (N×2)."""
        return self.u - self.u0

    @property
    def dy(self) -> np.ndarray:
        """Output minus the operating point (N)."""
        return self.y - self.y0

    def segments(self, min_s: float = 0.0) -> list[slice]:
        """Maximal runs of valid, consecutive samples at least min_s [s] long, as slices."""
        v = self.valid
        jump = np.r_[True, np.abs(np.diff(self.t) - self.Ts) > 0.01 * self.Ts]
        start = v & (jump | ~np.r_[False, v[:-1]])
        last = v & np.r_[start[1:] | ~v[1:], True]
        return [slice(int(a), int(b) + 1) for a, b in zip(np.flatnonzero(start), np.flatnonzero(last))
                if (b + 1 - a) * self.Ts >= min_s]

    def summary(self) -> dict:
        """A JSON-ready description (sizes, units, operating point, sources, warnings)."""
        segs = self.segments()
        return {
            "Ts": self.Ts,
            "fuel_lag_s": self.fuel_lag_s,
            "fuel_period_s": self.fuel_period_s,
            "samples": len(self),
            "valid_samples": int(self.valid.sum()),
            "valid_duration_s": float(self.valid.sum() * self.Ts),
            "segments": len(segs),
            "cycles": sorted(int(c) for c in np.unique(self.cycle[self.cycle >= 0])),
            "inputs": [{"name": n, "unit": u} for n, u in zip(self.input_names, self.input_units)],
            "output": {"name": self.output_name, "unit": self.output_unit},
            "operating_point": {"u0": [float(v) for v in self.u0], "y0": float(self.y0)},
            "sources": self.sources,
            "extra_signals": sorted(self.extra),
            "warnings": list(self.notes),
        }


# ---- reading: MCAP chunks or records → valid samples of each signal from each source address ------------

_BATCH_BYTES = 8 << 20  # uncompressed chunk records parsed at once: a few numpy passes each, memory bounded
_HEAD = 31  # bytes of an MCAP Message record before its data: opcode, length, channel, sequence, two times
_INVALID_KEY = np.frombuffer(b',"invalid":', np.uint8)


@dataclass
class _Found:
    """Valid samples of one signal from one source address in one batch of records, in arrival order."""
    arrival: tuple[int, int]  # (index of the record with the first valid sample, the signal's key position in it)
    name: str
    sa: int | None
    t: np.ndarray  # log times [ns], int64
    v: np.ndarray  # values in the DBC unit


def _message_name(topic: str) -> str | None:
    return "flowmeter" if topic == "/flowmeter" else topic[7:] if topic.startswith("/j1939/") else None


def _found_in_records(records: list[tuple[str, int, dict]], arrival: np.ndarray) -> list[_Found]:
    """_Found of decoded records (topic, log time [ns], record) whose arrival indices are `arrival`.

    Records are grouped by topic and source address, then each signal becomes one column of its group:
    JSON null (not available) is NaN in a float array and dropped, booleans and strings are no samples."""
    by_topic: dict[str, list[int]] = {}
    for n, (topic, _, _) in enumerate(records):
        by_topic.setdefault(topic, []).append(n)
    found = []
    for topic, idx in by_topic.items():
        msg = _message_name(topic)
        if msg is None:
            continue
        recs = [records[i][2] for i in idx]
        sas = [None] * len(recs) if msg == "flowmeter" else [r.get("sa") for r in recs]
        times, order = np.array([records[i][1] for i in idx], dtype=np.int64), arrival[idx]
        for sa in dict.fromkeys(sas):
            sub = [i for i, a in enumerate(sas) if a == sa]
            group = [recs[i] for i in sub]
            for name in set().union(*group) - NOT_SIGNALS:
                col = [r.get(name) for r in group]
                if set(map(type, col)) <= NUMBER_OR_NULL:  # the usual case: numpy makes None NaN
                    values = np.array(col, dtype=float)
                else:
                    values = np.array([v if type(v) in (int, float) else np.nan for v in col], dtype=float)
                keep = ~np.isnan(values)  # JSON has no NaN: NaN here is exactly "no sample"
                if keep.any():
                    first = int(np.argmax(keep))
                    found.append(_Found((int(order[sub[first]]), list(group[first]).index(name)), f"{msg}.{name}",
                                        sa, times[sub][keep], values[keep]))
    return found


def _cut_files(sources) -> str:
    """'; PATH is truncated: N s readable' for each MCAP source cut before its footer (the reason a signal may be
    missing), else ''."""
    paths = [Path(s) for s in ([sources] if isinstance(sources, (str, Path)) else sources) if isinstance(s, (str, Path))]
    notes = []
    for p in paths:
        with open(p, "rb") as f:
            f.seek(max(p.stat().st_size - len(MAGIC), 0))
            if f.read() == MAGIC:
                continue
        times = [t for _, t, _ in read_messages(p, damaged=[])]
        readable = (max(times) - min(times)) / 1e9 if times else 0.0
        notes.append(f"{p} is truncated (cut before its end): {readable:.0f} s readable")
    return "; " + "; ".join(notes) + " (`fuelid recover` rewrites what is left)" if notes else ""


def _u64(arr: np.ndarray, at: np.ndarray) -> np.ndarray:
    """The little-endian uint64 at each offset `at` of the byte array `arr`, as int64."""
    return arr[at[:, None] + np.arange(8)].copy().view("<u8").ravel().astype(np.int64)


def _message_starts(data: bytes, arr: np.ndarray, braces: np.ndarray) -> np.ndarray:
    """Offsets of the Message records among the MCAP records `data` (arr: its bytes, braces: offsets of '{').

    Messages whose JSON starts with {"t": (every fuelid record) are found by that text, 31 bytes after their
    opcode; a run of them counts only where each record ends exactly where the next begins, starting from a
    known record boundary, so a false hit (those bytes inside a header) can never be taken for a record.
    Everything else (schemas, channels, other messages) is walked record by record."""
    c = braces[(braces >= _HEAD) & (braces + 4 < len(arr))]
    c = c[(arr[c + 1] == 34) & (arr[c + 2] == 116) & (arr[c + 3] == 34) & (arr[c + 4] == 58) & (arr[c - _HEAD] == 5)]
    starts = c - _HEAD
    ends = starts + 9 + _u64(arr, starts + 1)
    breaks = np.flatnonzero(ends[:-1] != starts[1:])
    out, pos, size = [], 0, len(data)
    while pos < size:
        i = int(np.searchsorted(starts, pos))
        if i < len(starts) and starts[i] == pos:  # a chained run from here
            b = int(np.searchsorted(breaks, i))
            last = int(breaks[b]) if b < len(breaks) else len(starts) - 1
            out.append(starts[i:last + 1])
            pos = int(ends[last])
        else:
            opcode, length = data[pos], int.from_bytes(data[pos + 1:pos + 9], "little")
            if opcode == 5:
                out.append(np.array([pos], dtype=np.int64))
            pos += 9 + length
    return np.concatenate(out) if out else np.zeros(0, np.int64)


_BYTE_MASK = np.array([(1 << (8 * n)) - 1 for n in range(8)] + [(1 << 64) - 1], dtype=np.uint64)
_SPACES = np.frombuffer(b" " * 8, np.uint64)[0]
_COMMA = np.frombuffer(b",       ", np.uint64)[0]


def _word_view(data: bytes) -> np.ndarray:
    """The 8 bytes from each offset of `data` as a little-endian uint64 (an unaligned view, zero-padded)."""
    return np.ndarray((len(data) + 1,), "<u8", data + bytes(8), 0, (1,))


def _words(words: np.ndarray, at: np.ndarray, n: np.ndarray) -> np.ndarray:
    """words[at] (see _word_view) with the bytes from the n-th on zeroed (all of them, past the data's end)."""
    return words[np.minimum(at, len(words) - 1)] & _BYTE_MASK[np.clip(n, 0, 8)]


class _Layout:
    """The keys of a /j1939 record up to "invalid" as JSON text, to recognise and parse records laid out alike."""

    def __init__(self, record: dict):
        keys = list(record)
        self.keys = keys[:keys.index("invalid")] if "invalid" in keys else keys
        self.ok = ("invalid" in keys and set(keys[keys.index("invalid") + 1:]) <= {"tp"} and "sa" in self.keys
                   and self.keys[0] == "t")
        self.text = [orjson.dumps(k) for k in self.keys]
        self.columns = [i for i, k in enumerate(self.keys) if k not in NOT_SIGNALS or k == "sa"]


def _alike(words, arr, colons, commas, braces, start, end, layout: _Layout) -> tuple | None:
    """(colon, end) byte offsets (records × layout.columns) of the values of the JSON records at
    the records at [start, end) when every one is laid out as `layout`, else None (the caller parses them one by one):
    each record's keys are compared with the layout's, byte for byte; a value runs from its key's colon to
    the next comma."""
    k = len(layout.keys)
    inner = braces[np.searchsorted(braces, end) - 1]  # the "invalid" object opens at the last '{' of a record
    if not (inner > start).all() or not (arr[inner[:, None] - 11 + np.arange(11)] == _INVALID_KEY).all():
        return None
    head_end = inner - 11
    lo, hi = np.searchsorted(colons, start), np.searchsorted(colons, head_end)
    clo, chi = np.searchsorted(commas, start), np.searchsorted(commas, head_end)
    if not ((hi - lo == k).all() and (chi - clo == k - 1).all() and (arr[start] == 123).all()):
        return None
    colon = colons[lo[:, None] + np.arange(k)]
    comma = commas[clo[:, None] + np.arange(k - 1)]
    key_from = np.column_stack([start, comma]) + 1  # first byte of each key's text (its opening quote)
    value_end = np.column_stack([comma, head_end])
    if not (colon + 1 < value_end).all():
        return None
    for j, text in enumerate(layout.text):
        if not (colon[:, j] - key_from[:, j] == len(text)).all():
            return None
        for m in range(0, len(text), 8):
            piece = text[m:m + 8]
            want = np.frombuffer(piece.ljust(8, b"\0"), np.uint64)[0]
            if not (_words(words, key_from[:, j] + m, np.full(len(start), len(piece))) == want).all():
                return None
    return colon[:, layout.columns], value_end[:, layout.columns]


def _numbers(words: np.ndarray, colon: np.ndarray, end: np.ndarray) -> np.ndarray | None:
    """The JSON numbers (null → NaN) at bytes [colon + 1, end) (words: _word_view) for each (colon, end), in that order, parsed by
    numpy as one text of fixed-width fields; None when one is not a number or null."""
    width = int(np.ceil((end - colon - 1).max() / 8))
    field = np.empty((len(colon), width + 1), np.uint64)
    field[:, 0] = _COMMA
    for m in range(width):
        n = end - colon - 1 - 8 * m
        field[:, m + 1] = _words(words, colon + 1 + 8 * m, n) | (_SPACES & ~_BYTE_MASK[np.clip(n, 0, 8)])
    text = field.tobytes()[1:].replace(b"null", b"nan ")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            values = np.fromstring(text, dtype=float, sep=",")
    except (ValueError, DeprecationWarning):  # true, false, a string: not numbers
        return None
    return values if values.size == len(colon) else None


def _found_in_chunks(data: bytes, topics: dict[int, str], first_arrival: int,
                     layouts: dict) -> tuple[list[_Found], int, tuple | None]:
    """_Found of the /j1939 and /flowmeter messages among the MCAP records `data` (whole chunks), their arrival
    indices counted from first_arrival; also how many there were and their (first, last) log time [ns].

    /j1939 records laid out alike are parsed column-wise (_alike, _numbers); the others one by one."""
    arr = np.frombuffer(data, np.uint8)
    braces = np.flatnonzero(arr == 123)
    starts = _message_starts(data, arr, braces)
    channel = arr[starts + 9].astype(np.int64) | arr[starts + 10].astype(np.int64) << 8
    keep = np.isin(channel, list(topics))
    starts, channel = starts[keep], channel[keep]
    if not len(starts):
        return [], 0, None
    log_time = _u64(arr, starts + 15)
    data_end = starts + 9 + _u64(arr, starts + 1)
    arrival = first_arrival + np.arange(len(starts))
    words = _word_view(data)
    scans = (words, arr, np.flatnonzero(arr == 58), np.flatnonzero(arr == 44), braces)
    fast, slow = [], []  # fast: (topic, record indices, layout, value table)
    for ch in np.unique(channel):
        topic, idx = topics[int(ch)], np.flatnonzero(channel == ch)
        begin, end = starts[idx] + _HEAD, data_end[idx]
        layout = layouts.get(topic)
        if layout is None and topic != "/flowmeter":
            layout = layouts[topic] = _Layout(orjson.loads(data[begin[0]:end[0]]))
        spans = _alike(*scans, begin, end, layout) if layout is not None and layout.ok else None
        table = None if spans is None else _numbers(words, spans[0].ravel(), spans[1].ravel())
        if table is None:
            slow.append(idx)
        else:
            fast.append((topic, idx, layout, table.reshape(spans[0].shape)))
    found = []
    for topic, idx, layout, table in fast:
        keys = [layout.keys[i] for i in layout.columns]
        sa_col = table[:, keys.index("sa")]
        if not (sa_col == np.round(sa_col)).all():  # null or not a whole number: as the records say, one by one
            slow.append(idx)
            continue
        for sa in dict.fromkeys(sa_col.tolist()):
            group = np.flatnonzero(sa_col == sa)
            for j, key in enumerate(keys):
                if key in NOT_SIGNALS:
                    continue
                col = table[group, j]
                ok = ~np.isnan(col)
                if ok.any():
                    at = idx[group[int(np.argmax(ok))]]
                    found.append(_Found((int(arrival[at]), layout.columns[j]), f"{_message_name(topic)}.{key}",
                                        int(sa), log_time[idx[group[ok]]], col[ok]))
    if slow:
        slow = np.sort(np.concatenate(slow))
        records = [(topics[int(channel[i])], int(log_time[i]), orjson.loads(data[starts[i] + _HEAD:data_end[i]]))
                   for i in slow]
        found += _found_in_records(records, arrival[slow])
    return found, len(starts), (int(log_time.min()), int(log_time.max()))


_J1939_KEYS = 4  # t, pgn, sa, da come before the signals in a /j1939 record
_FLOW_KEYS = {"volts": 2, "flow_kg_h": 3}  # places in a /flowmeter record (t, device_t first)


def _found_in_columns(block: message_columns.ColumnBlock, first_arrival: int, decoder: Decoder) -> list[_Found]:
    """_Found of one block of message columns (logger.columns), arrival indices counted from first_arrival: the
    payloads of each (PGN, source address) group decoded at once, exactly as the JSON records hold them."""
    found = []
    key = block.pgn << 8 | block.sa
    edges = np.r_[0, np.flatnonzero(np.diff(key)) + 1, len(key)]
    for a, b in zip(edges[:-1], edges[1:]):
        decoded = decoder.decode_columns(int(block.pgn[a]), block.payload[a:b], block.length[a:b])
        if decoded is None:
            raise ValueError(f"PGN {int(block.pgn[a])} is not in the DBC")
        name, values = decoded
        t, arrival = block.t_ns[a:b], first_arrival + block.seq[a:b]
        for j, (signal, v) in enumerate(values.items()):
            keep = ~np.isnan(v)
            if keep.any():
                found.append(_Found((int(arrival[np.argmax(keep)]), _J1939_KEYS + j), f"{name}.{signal}",
                                    int(block.sa[a]), t[keep], v[keep]))
    for signal, place in _FLOW_KEYS.items():
        v = block.flow_kg_h if signal == "flow_kg_h" else block.volts
        keep = ~np.isnan(v)
        if keep.any():
            found.append(_Found((first_arrival + int(block.flow_seq[np.argmax(keep)]), place), f"flowmeter.{signal}",
                                None, block.flow_t_ns[keep], v[keep]))
    return found


def _read_columns(path: Path, topics: list[str], signals: _Signals, arrival: int) -> tuple[int, tuple | None] | None:
    """Add the samples of a file's message columns to `signals` (arrival indices from `arrival`): how many
    messages they held and their (first, last) log time [ns]; None when the file has none (read its JSON)."""
    found = read_attachments(path, message_columns.NAME)
    if found is None:
        return None
    counts, blocks = found
    decoder, rows, first, last = Decoder(), 0, None, None
    for data in blocks:
        try:
            block = message_columns.read_block(data)
            signals.add(_found_in_columns(block, arrival + rows, decoder))
        except ValueError as exc:
            raise FuelidError(f"{path}: damaged {message_columns.NAME} attachment ({exc}); `fuelid recover` "
                              "keeps every intact chunk") from None
        rows += block.rows
        t = np.concatenate([block.t_ns, block.flow_t_ns])
        if len(t):
            first = int(t.min()) if first is None else min(first, int(t.min()))
            last = int(t.max()) if last is None else max(last, int(t.max()))
    messages = sum(counts.get(topic, 0) for topic in topics)
    if rows != messages:
        raise FuelidError(f"{path}: its {message_columns.NAME} attachments hold {rows} messages, its channels "
                          f"{messages}: not written together; `fuelid recover` rewrites the file without them")
    return rows, (first, last)


class _OutOfOrder(Exception):
    """Samples of a signal came earlier than ones already binned: their bins must be summed in time order."""


def _median(values: np.ndarray, counts: np.ndarray) -> float:
    """np.median of the multiset where values[i] (sorted) occurs counts[i] times, from its one or two middle
    elements, so the result is the very float np.median gives on the whole array."""
    n = int(counts.sum())
    cum = np.cumsum(counts)
    middle = [n // 2] if n % 2 else [n // 2 - 1, n // 2]
    return float(np.median(values[np.searchsorted(cum, middle, side="right")]))


class _Column:
    """A 1-D array that grows at its end: one buffer whose capacity doubles when full (the capacity not yet written
    is not resident), so that a signal's bins take a few large allocations, not one small one per chunk of the
    recording. Non-negative integers are kept as int32 while they fit (they do, but for a tiny Ts or a huge one),
    then as int64."""

    def __init__(self, dtype):
        self._a, self.n = np.empty(0, dtype), 0

    def append(self, x: np.ndarray) -> None:
        if self._a.dtype == np.int32 and len(x) and x.max() >= 2**31:
            self._a = self._a.astype(np.int64)
        end = self.n + len(x)
        if end > len(self._a):
            grown = np.empty(max(end, 2 * len(self._a), 1024), self._a.dtype)
            grown[: self.n] = self._a[: self.n]
            self._a = grown
        self._a[self.n : end] = x
        self.n = end

    def values(self) -> np.ndarray:
        return self._a[: self.n]


class _Binned:
    """The valid samples of one signal from one source address, reduced per bin of the absolute grid
    k = t // Ts as they arrive: count, sum (in time order, as np.bincount adds), and the last sample; plus
    how often each time step and (for signals whose median is used) each value occurred."""

    def __init__(self, arrival: tuple[int, int], ts_ns: int, mean: bool, values: bool):
        self.arrival, self._ts, self._mean = arrival, ts_ns, mean
        self.n, self.t_min, self.t_last = 0, None, None
        # per bin with samples: its step from the first bin, its last sample's offset [ns] in the bin and value, and
        # for averaged signals the count and sum of its samples
        self._steps_k, self._offsets, self._last_v = _Column(np.int32), _Column(np.int32), _Column(float)
        self._counts, self._sums = (_Column(np.int32), _Column(float)) if mean else (None, None)
        self._k_first: int | None = None
        self._tail = (np.zeros(0, np.int64), np.zeros(0))  # the samples of the newest bin, still open
        self._steps: dict[int, int] = {}
        self._values: dict[float, int] | None = {} if values else None

    def add(self, t: np.ndarray, v: np.ndarray) -> None:
        """Samples in arrival order; _OutOfOrder when one is earlier than its predecessor."""
        steps = np.diff(t) if self.t_last is None else np.diff(np.concatenate([[self.t_last], t]))
        if (steps < 0).any():
            raise _OutOfOrder
        for counter, new in ((self._steps, steps), (self._values, v)):
            if counter is not None:
                keys, counts = np.unique(new, return_counts=True)
                for x, c in zip(keys.tolist(), counts.tolist()):
                    counter[x] = counter.get(x, 0) + c
        self.n += len(t)
        self.t_min = int(t[0]) if self.t_min is None else self.t_min
        self.t_last = int(t[-1])
        t, v = np.concatenate([self._tail[0], t]), np.concatenate([self._tail[1], v])
        k = t // self._ts
        cut = int(np.searchsorted(k, k[-1]))
        self._close(t[:cut], v[:cut], k[:cut])
        self._tail = (t[cut:], v[cut:])

    def _close(self, t, v, k) -> None:
        # Kept compact (grid-sized memory is the point): bins as int32 steps from the signal's first bin, the
        # last sample's time as its int32 offset [ns] in its bin, counts and sums only for averaged signals.
        if not len(t):
            return
        first = np.concatenate([[0], np.flatnonzero(np.diff(k)) + 1])
        last = np.concatenate([first[1:], [len(k)]]) - 1
        if self._k_first is None:
            self._k_first = int(k[0])
        counts = (last - first + 1) if self._mean else None
        sums = np.bincount(np.repeat(np.arange(len(first)), counts), weights=v) if self._mean else None
        steps, offsets = k[first] - self._k_first, t[last] - k[last] * self._ts
        for column, x in ((self._steps_k, steps), (self._offsets, offsets), (self._last_v, v[last]),
                          (self._counts, counts), (self._sums, sums)):
            if column is not None:
                column.append(x)

    def finish(self) -> None:
        """Bin the samples of the last bin too."""
        t, v = self._tail
        self._close(t, v, t // self._ts)
        self._tail = (t[:0], v[:0])

    def bins(self) -> np.ndarray:
        """The bins k that have samples, increasing."""
        return self._k_first + self._steps_k.values().astype(np.int64)

    def last(self) -> tuple[np.ndarray, np.ndarray]:
        """Per bin with samples: the time [ns] and value of its last sample."""
        k = self.bins()
        return k * self._ts + self._offsets.values(), self._last_v.values()

    def means(self) -> np.ndarray:
        """Per bin with samples: the mean of its samples (averaged signals only)."""
        return self._sums.values() / self._counts.values().astype(np.int64)

    def median_step(self) -> float:
        """Median time between consecutive samples [ns]."""
        keys = np.array(sorted(self._steps))
        return _median(keys, np.array([self._steps[x] for x in keys]))

    def median_value(self) -> float:
        keys = np.array(sorted(self._values))
        return _median(keys, np.array([self._values[x] for x in keys]))


class _Signals:
    """Every signal's _Binned per source address. With `in_order` False the samples are kept whole and
    time-sorted at the end (a recording whose clock stepped back): exact, but memory grows with the records."""

    def __init__(self, ts_ns: int, in_order: bool, lag_ns: dict[str, int] | None = None):
        self._ts, self._in_order, self._lag = ts_ns, in_order, lag_ns or {}
        self.by_key: dict[tuple[str, int | None], _Binned] = {}
        self._kept: dict[tuple, list] = {}

    def add(self, found: list[_Found]) -> None:
        for f in found:
            if f.name in self._lag:
                f.t = f.t - self._lag[f.name]
            key = (f.name, f.sa)
            binned = self.by_key.get(key)
            if binned is None:
                binned = self.by_key[key] = _Binned(f.arrival, self._ts, f.name in AVERAGED, f.name in MEDIANS)
            if self._in_order:
                binned.add(f.t, f.v)
            else:
                self._kept.setdefault(key, []).append((f.t, f.v))

    def finish(self) -> dict[str, dict]:
        """signal name → source address → its finished _Binned, both in the order their first valid sample
        arrived (then the key's place in its record)."""
        for key, parts in self._kept.items():
            t, v = np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
            order = np.argsort(t, kind="stable")
            self.by_key[key].add(t[order], v[order])
        sig: dict[str, dict] = {}
        for (name, sa), binned in sorted(self.by_key.items(), key=lambda item: item[1].arrival):
            binned.finish()
            sig.setdefault(name, {})[sa] = binned
        return sig


def _read(sources, ts_ns: int, damaged: list | None, in_order: bool, lag_ns: dict[str, int]) -> dict[str, dict]:
    """The signals of MCAP paths and/or lists of (topic, log_time_ns, record) records, see _Signals.finish.
    A file is read from its message columns when it has them, else from its JSON channels chunk batch by chunk
    batch (with a progress bar on a terminal). A damaged chunk of a file read so raises FuelidError, or, when a
    `damaged` list is given, is skipped and appended to it."""
    signals = _Signals(ts_ns, in_order, lag_ns)
    spans = {}  # path -> (first, last) log time [ns]: files are parts of one timeline and must not overlap
    arrival = 0
    topics = ["/flowmeter"] + [f"/j1939/{m}" for m in Decoder().message_names()]  # not /can/raw
    for src in sources:
        if not isinstance(src, Path):
            signals.add(_found_in_records(src, arrival + np.arange(len(src))))
            arrival += len(src)
            continue
        count, (first, last) = (_read_columns(src, topics, signals, arrival)
                                or _read_json(src, topics, signals, arrival, damaged))
        arrival += count
        for other, (a, b) in spans.items():
            if first is not None and a is not None and first <= b and a <= last:
                raise FuelidError(f"{src} and {other} overlap in time: they are not parts of one recording; "
                                  "give them to separate runs")
        spans[src] = (first, last)
    return signals.finish()


def _read_json(src: Path, topics: list[str], signals: _Signals, arrival: int,
               damaged: list | None) -> tuple[int, tuple | None]:
    """Add the samples of a file's JSON channels to `signals`, a batch of chunks at a time (with a progress bar
    on a terminal), arrival indices from `arrival`: how many messages there were and their (first, last) log
    time [ns]. Damaged chunks as in `_read`."""
    count, first, last = 0, None, None
    layouts: dict[str, _Layout] = {}
    batch, size = [], 0
    chunks = progress(read_chunks(src, topics, damaged=damaged), desc=src.name, unit="chunk")
    ids: dict[int, str] = {}
    for new_ids, data in itertools.chain(chunks, [(None, None)]):
        if data is not None:
            ids = new_ids
            batch.append(data)
            size += len(data)
            if size < _BATCH_BYTES:
                continue
        if batch:
            found, n, span = _found_in_chunks(b"".join(batch), ids, arrival + count, layouts)
            signals.add(found)
            count += n
            if span is not None:
                first = span[0] if first is None else min(first, span[0])
                last = span[1] if last is None else max(last, span[1])
        batch, size = [], 0
    return count, (first, last)


def _sources(sources) -> list:
    """MCAP paths (checked to exist) and lists of records, from what build_dataset accepts."""
    if isinstance(sources, (str, Path)):
        sources = [sources]
    out, records = [], []
    for src in sources:
        if isinstance(src, (str, Path)):
            if records:
                out.append(records)
                records = []
            p = Path(src)
            if not p.is_file():
                raise FuelidError(f"{p}: no such file")
            out.append(p)
        elif isinstance(src, tuple) and len(src) == 3 and isinstance(src[0], str):
            records.append(src)
        else:
            out.append(list(src))
    if records:
        out.append(records)
    return out


def _choose(sig: dict, preference: dict) -> tuple[dict[str, _Binned], dict]:
    """Per signal the samples of one source address (preferred, else the one with most samples)."""
    chosen, used = {}, {}
    for name, by_sa in sig.items():
        msg = name.split(".", 1)[0]
        pref = None if msg == "flowmeter" else preferred_source(msg, preference)
        sa = pref if pref in by_sa else max(by_sa, key=lambda a: by_sa[a].n)
        chosen[name], used[name] = by_sa[sa], sa
    return chosen, used


def _resample(s: _Binned, k_rows, k0, Ts, hold, mean):
    """One signal on the grid rows k_rows (bin numbers from bin k0): bin mean (or last sample) with a hold of
    at most `hold`; Ts, hold in integer ns, so a sample on a bin boundary always opens the bin."""
    bins = s.bins() - k0
    last_t, last_v = s.last()
    bin_end = (k0 + k_rows + 1) * Ts
    j = np.searchsorted(bins, k_rows, side="right") - 1  # the last bin with samples up to each row
    out = np.full(len(k_rows), np.nan)
    fresh = (j >= 0) & (bin_end - last_t[np.maximum(j, 0)] <= hold)
    out[fresh] = last_v[j[fresh]]
    if mean:
        out[np.searchsorted(k_rows, bins)] = s.means()
    return out


def _union(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.union1d of two increasing arrays without repeats: timsort merges the two runs in one linear pass."""
    both = np.sort(np.concatenate([a, b]), kind="stable")
    return both[np.r_[True, both[1:] != both[:-1]]] if len(both) else both


def _lasting(mask: np.ndarray, n: int) -> np.ndarray:
    """mask restricted to its runs of at least n consecutive True samples."""
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(np.int8), 0]))
    out = np.zeros_like(mask)
    for a, b in zip(edges[::2], edges[1::2]):
        out[a:b] = b - a >= n
    return out


def _cycles(ds_valid_segments: list[slice], n: int, Ts: float, cycle_s: float, min_cycle_s: float) -> np.ndarray:
    cycle = np.full(n, -1, dtype=np.int64)
    cid = 0
    per = max(int(round(cycle_s / Ts)), 1)
    for seg in ds_valid_segments:
        length = seg.stop - seg.start
        if length * Ts < min_cycle_s:
            continue
        windows = max(length // per, 1)
        for w in range(windows):
            a = seg.start + w * per
            b = seg.stop if w == windows - 1 else a + per
            cycle[a:b] = cid
            cid += 1
    return cycle


def build_dataset(
    sources,
    Ts: float = 0.3,
    source_preference: dict[str, int] = DEFAULT_SOURCE_PREFERENCE,
    fuel: str = "auto",
    max_gap_s: float = 1.0,
    idle_rpm: float | None = None,
    idle_tol_rpm: float = 50.0,
    idle_min_s: float = 3.0,
    cycle_s: float = 1800.0,
    min_cycle_s: float = 60.0,
    skip_damaged: bool = False,
    fuel_lag_s: float = 0.0,
) -> Dataset:
    """Build a Dataset from MCAP paths and/or iterables of (topic, log_time_ns, record) records.

    Ts [s] grid step; fuel 'auto' (the flow meter when it has valid readings, else LFE1), 'flowmeter'
    [kg/h] or 'lfe1' [L/h]; max_gap_s [s] the longest stretch a model signal is held; idle_rpm,
    idle_tol_rpm [rpm], idle_min_s [s] the operating point; cycle_s, min_cycle_s [s] the drive cycles; fuel_lag_s
    [s] (≥ 0) the fuel signal's reporting lag, taken out of its samples' times before binning.
    A file's damaged chunk (failing its CRC) raises FuelidError naming the bytes; with skip_damaged it is
    left out (a gap in the data) and noted. Raises FuelidError when engine speed, torque or the fuel
    signal is missing. Method: module docstring.
    """
    if Ts <= 0:
        raise FuelidError(f"sampling interval must be positive, got {Ts} s")
    if fuel not in ("auto", *FUEL_SIGNALS):
        raise FuelidError(f"fuel must be auto, flowmeter or lfe1, got {fuel!r}")
    if not 0 <= fuel_lag_s < Ts:
        raise FuelidError(f"the fuel signal's lag must be at least 0 and below Ts = {Ts:g} s, got {fuel_lag_s} s")
    ts_ns = int(round(Ts * 1e9))
    lag_ns = {name: int(round(fuel_lag_s * 1e9)) for name, _ in FUEL_SIGNALS.values()}
    sources = _sources(sources)
    try:
        damaged = [] if skip_damaged else None
        sig = _read(sources, ts_ns, damaged, in_order=True, lag_ns=lag_ns)
    except _OutOfOrder:
        damaged = [] if skip_damaged else None
        sig = _read(sources, ts_ns, damaged, in_order=False, lag_ns=lag_ns)
    chosen, used = _choose(sig, source_preference)
    del sig  # the other source addresses' samples: only the chosen ones are gridded
    if fuel == "auto":
        fuel = "flowmeter" if FUEL_SIGNALS["flowmeter"][0] in chosen else "lfe1"
    fuel_name, fuel_unit = FUEL_SIGNALS[fuel]
    for name, what in [(SPEED, "engine speed"), (TORQUE_PCT, "engine torque")]:
        if name not in chosen:
            raise FuelidError(f"no {what} ({name}) in the data" + _cut_files(sources))
    if fuel_name not in chosen:
        raise FuelidError(
            f"no fuel flow ({fuel_name}) in the data" + (_cut_files(sources) or (
                "" if fuel == "flowmeter" and FUEL_SIGNALS["lfe1"][0] in chosen
                else ": a gas truck's engine may not send its fuel rate (LFE1); convert its recording with the flow "
                     "meter's capture beside it, `fuelid convert LOG --flowmeter CAPTURE.flow`")))

    k0 = min(s.t_min for s in chosen.values()) // ts_ns  # bins start at multiples of Ts
    occupied = np.zeros(0, np.int64)
    for s in chosen.values():  # one signal's bins at a time
        occupied = _union(occupied, s.bins() - k0)
    span = int(np.ceil(max_gap_s / Ts)) + 2  # hold bins + one invalid row after a gap
    k_rows = np.unique((occupied[:, None] + np.arange(span)).ravel())
    k_rows = k_rows[k_rows <= occupied[-1]]  # nothing held past the end of the data

    def grid(name, hold_s=max_gap_s):  # each signal's binned samples are let go once it is on the grid
        return _resample(chosen.pop(name), k_rows, k0, ts_ns, int(hold_s * 1e9), name in AVERAGED)

    notes = [f"skipped {d}" for d in damaged or ()]
    for note in notes:
        warnings.warn(note, stacklevel=2)
    ref_torque = chosen[REF_TORQUE].median_value() if REF_TORQUE in chosen else None
    if idle_rpm is None:
        idle_rpm = chosen[IDLE_SPEED].median_value() if IDLE_SPEED in chosen else 600.0
    fuel_period_s = chosen[fuel_name].median_step() * 1e-9 if chosen[fuel_name].n > 1 else 0.0
    if fuel_period_s >= 2 * Ts:  # most bins hold an older report: the fuel's faster dynamics are not in the data
        notes.append(f"the fuel signal ({fuel_name}) arrives every {fuel_period_s:.3g} s, slower than the grid's "
                     f"{Ts:g} s: most bins hold an earlier value, so the data say nothing of the fuel's dynamics "
                     f"faster than that; --ts {fuel_period_s:.3g} matches it")
        warnings.warn(notes[-1], stacklevel=2)
    speed, pct, y = grid(SPEED), grid(TORQUE_PCT), grid(fuel_name)
    if ref_torque is not None:
        torque, torque_unit = pct * ref_torque / 100.0, "Nm"
    else:
        torque, torque_unit = pct, "%"
        notes.append("EC1 (engine reference torque) never arrived: torque kept in % of reference torque")
        warnings.warn(notes[-1], stacklevel=2)
    u = np.column_stack([speed, torque])
    valid = np.isfinite(u).all(axis=1) & np.isfinite(y)
    running_rpm = RUNNING_SHARE * idle_rpm
    stopped = valid & (speed < running_rpm)
    if stopped.any():
        valid &= ~stopped
        if not valid.any():
            raise FuelidError(f"the engine is off throughout these data: engine speed stays below {running_rpm:g} "
                              "rpm, half its idle speed")
        notes.append(f"{stopped.sum() * Ts:.0f} s with the engine off or starting (below {running_rpm:g} rpm) left out")
        warnings.warn(notes[-1], stacklevel=2)

    extra = {}
    for name in list(chosen):
        s = chosen[name]
        period = s.median_step() * 1e-9 if s.n > 1 else 0.0
        extra[name] = grid(name, max(max_gap_s, 3 * period))

    idle = valid & (np.abs(speed - idle_rpm) <= idle_tol_rpm)
    if VEHICLE_SPEED in extra:
        idle &= extra[VEHICLE_SPEED] < 2.0
    idle = _lasting(idle, int(np.ceil(idle_min_s / Ts)))
    if idle.any():
        u0, y0 = u[idle].mean(axis=0), float(y[idle].mean())
    else:
        u0, y0 = np.array([idle_rpm, 0.0]), 0.0
        notes.append(f"no idle samples near {idle_rpm:g} rpm: operating point set to ({idle_rpm:g} rpm, 0, 0)")
        warnings.warn(notes[-1], stacklevel=2)

    ds = Dataset(
        Ts=float(Ts), t=(k0 * ts_ns + k_rows * ts_ns) * 1e-9, u=u, y=y,
        input_names=(SPEED, "EngTorque"), input_units=("rpm", torque_unit),
        output_name=fuel_name, output_unit=fuel_unit, u0=u0, y0=y0, valid=valid,
        cycle=np.full(len(k_rows), -1, dtype=np.int64), extra=extra, sources=used, notes=notes,
        fuel_lag_s=float(fuel_lag_s), fuel_period_s=float(fuel_period_s),
    )
    ds.cycle = _cycles(ds.segments(), len(ds), Ts, cycle_s, min_cycle_s)
    return ds


# ---- export / import ---------------------------------------------------------------------------------

def _meta(ds: Dataset) -> dict:
    return {
        "format": "fuelid dataset v1", "Ts": ds.Ts,
        "input_names": list(ds.input_names), "input_units": list(ds.input_units),
        "output_name": ds.output_name, "output_unit": ds.output_unit,
        "u0": [float(v) for v in ds.u0], "y0": ds.y0, "sources": ds.sources, "notes": ds.notes,
        "extra": list(ds.extra), "fuel_lag_s": ds.fuel_lag_s, "fuel_period_s": ds.fuel_period_s,
    }


def _columns(ds: Dataset) -> dict[str, np.ndarray]:
    cols = {"t": ds.t, "valid": ds.valid.astype(float), "cycle": ds.cycle.astype(float),
            ds.input_names[0]: ds.u[:, 0], ds.input_names[1]: ds.u[:, 1], ds.output_name: ds.y}
    cols.update(ds.extra)
    return cols


def csv_sidecar(path) -> Path:
    """The metadata file beside a dataset CSV, named as CSV on the Web (W3C CSVW) names it: DATA.csv-metadata.json."""
    path = Path(path)
    return path.with_name(path.name + "-metadata.json")


def _csv_units(ds: Dataset) -> dict[str, str]:
    """Column name → unit of every column the CSV writes (time_utc, valid and cycle have none)."""
    units = {"time_s": "s", ds.input_names[0]: ds.input_units[0], ds.input_names[1]: ds.input_units[1],
             ds.output_name: ds.output_unit}
    dbc = signal_units()
    units.update({name: dbc[name] for name in ds.extra if name in dbc})
    return units


CSV_CHUNK_ROWS = 1 << 16  # rows formatted at once: the writer's memory is bounded whatever the data's length


def _csv_chunk(first: np.ndarray, ms: np.ndarray, columns: list[np.ndarray]) -> bytes:
    """CSV rows (no header) by pyarrow's writer: `first`, the times ms [ms since 1970] as ISO 8601 UTC to the
    millisecond ('2023-11-14T22:13:20.300Z'), then `columns`; numbers in their shortest round-trip form (whole
    numbers as integers), NaN as an empty field."""
    import pyarrow as pa  # heavy to load: only this writer needs it
    import pyarrow.compute as pc
    import pyarrow.csv as pacsv

    stamps = pc.cast(pa.array(ms, pa.timestamp("ms")), pa.string())  # '2023-11-14 22:13:20.300'
    iso = pc.binary_join_element_wise(pc.replace_substring(stamps, " ", "T"), "Z", "")

    def number(x):
        whole = np.isfinite(x).all() and np.all(x == np.round(x)) and np.abs(x).max(initial=0) < 2 ** 53
        return pa.array(x.astype(np.int64)) if whole else pa.array(x, from_pandas=True)  # from_pandas: NaN → null

    arrays = [number(first), iso] + [number(c) for c in columns]
    sink = pa.BufferOutputStream()
    pacsv.write_csv(pa.table(arrays, names=[str(k) for k in range(len(arrays))]), sink,
                    pacsv.WriteOptions(include_header=False, quoting_style="none"))
    return sink.getvalue().to_pybytes()


def _write_rows(path: Path, t: np.ndarray, columns: list[np.ndarray]) -> None:
    """Append the rows of `_csv_chunk` (columns[0], t [s since 1970] as ISO time, columns[1:]) to the CSV at
    path, CSV_CHUNK_ROWS at a time."""
    ms = np.round(np.asarray(t, float) * 1e3).astype(np.int64)
    with open(path, "ab") as f:
        for a in range(0, len(t), CSV_CHUNK_ROWS):
            p = slice(a, a + CSV_CHUNK_ROWS)
            f.write(_csv_chunk(columns[0][p], ms[p], [c[p] for c in columns[1:]]))


def _write_csv(ds: Dataset, path: Path) -> None:
    """A plain CSV a spreadsheet opens (one header row, 'name [unit]'; time as seconds since the first sample
    and as ISO 8601 UTC), and its CSVW metadata sidecar with the units, the start time and fuelid's metadata."""
    cols = _columns(ds)
    t0 = float(ds.t[0]) if len(ds.t) else 0.0
    units = _csv_units(ds)
    cols = {"time_s": ds.t - t0, **{k: v for k, v in cols.items() if k != "t"}}
    names = list(cols)
    header = ["time_s [s]", "time_utc"] + [f"{n} [{units[n]}]" if n in units else n for n in names[1:]]
    with open(path, "w", newline="") as f:
        f.write(",".join(header) + "\n")
    _write_rows(path, ds.t, [np.asarray(v, float) for v in cols.values()])
    columns = [{"name": "time_s", "titles": header[0], "datatype": "number", "schema:unitText": "s",
                "dc:description": "time since the first sample"},
               {"name": "time_utc", "titles": "time_utc", "datatype": "dateTime",
                "dc:description": "bin start time, UTC (the log clock)"}]
    columns += [{"name": n, "titles": title, "datatype": "number", **({"schema:unitText": units[n]} if n in units else {})}
                for n, title in zip(names[1:], header[2:])]
    sidecar = {"@context": "http://www.w3.org/ns/csvw", "url": path.name,
               "tableSchema": {"columns": columns}, "fuelid": {**_meta(ds), "t0": t0}}
    csv_sidecar(path).write_text(json.dumps(sidecar, indent=1) + "\n")


def _read_csv(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    """The metadata and the columns (t on the log clock) of a CSV written by _write_csv."""
    sidecar = csv_sidecar(path)
    try:
        meta = json.loads(sidecar.read_text())["fuelid"]
    except FileNotFoundError:
        raise FuelidError(f"{path}: its metadata file {sidecar.name} is missing beside it") from None
    except (ValueError, KeyError, TypeError) as e:
        raise FuelidError(f"{sidecar}: not a fuelid dataset metadata file ({e})") from None
    with open(path) as f:
        titles = f.readline().rstrip("\n").split(",")
    names = [title.split(" [", 1)[0] for title in titles]
    data = np.genfromtxt(path, delimiter=",", skip_header=1, ndmin=2,
                         usecols=[i for i, n in enumerate(names) if n != "time_utc"])
    cols = dict(zip([n for n in names if n != "time_utc"], data.T))
    cols["t"] = float(meta["t0"]) + cols.pop("time_s")
    return meta, cols


def save_dataset(ds: Dataset, path) -> Path:
    """Write ds to .csv (a header row of 'name [unit]', then one row per sample, NaN empty; time as time_s
    since the first sample and time_utc in ISO 8601; the metadata in the CSVW sidecar DATA.csv-metadata.json)
    or .mat (scipy.io.savemat: Ts, t, u, y, u0, y0, valid, cycle, names, units and a struct `extra` whose
    field names are the signal names with '.' → '_')."""
    path = Path(path)
    if path.suffix == ".csv":
        _write_csv(ds, path)
    elif path.suffix == ".mat":
        from scipy.io import savemat  # imported for .mat only: every command would pay for it

        meta = _meta(ds)
        savemat(path, {
            "Ts": ds.Ts, "t": ds.t, "u": ds.u, "y": ds.y, "u0": ds.u0, "y0": ds.y0,
            "valid": ds.valid, "cycle": ds.cycle,
            "input_names": np.array(ds.input_names, dtype=object),
            "input_units": np.array(ds.input_units, dtype=object),
            "output_name": ds.output_name, "output_unit": ds.output_unit,
            "meta_json": json.dumps(meta),
            "extra": {k.replace(".", "_"): v for k, v in ds.extra.items()},
        }, oned_as="column")
    else:
        raise FuelidError(f"{path}: output must end in .csv or .mat")
    return path


def load_dataset(path) -> Dataset:
    """Read back a file written by save_dataset (.csv with its sidecar, or .mat)."""
    path = Path(path)
    if path.suffix == ".csv":
        meta, cols = _read_csv(path)
    elif path.suffix == ".mat":
        from scipy.io import loadmat

        m = loadmat(path, squeeze_me=True, chars_as_strings=True)
        meta = json.loads(str(m["meta_json"]))
        ex = m["extra"]
        extra_mat = {n: np.atleast_1d(ex[n].item()).astype(float) for n in (ex.dtype.names or ())}
        cols = {"t": np.atleast_1d(m["t"]), "valid": np.atleast_1d(m["valid"]), "cycle": np.atleast_1d(m["cycle"]),
                meta["input_names"][0]: np.atleast_2d(m["u"])[:, 0], meta["input_names"][1]: np.atleast_2d(m["u"])[:, 1],
                meta["output_name"]: np.atleast_1d(m["y"])}
        cols.update({k: extra_mat[k.replace(".", "_")] for k in meta["extra"]})
    else:
        raise FuelidError(f"{path}: dataset files end in .csv or .mat")
    fixed = {"t", "valid", "cycle", *meta["input_names"], meta["output_name"]}
    return Dataset(
        Ts=float(meta["Ts"]), t=np.asarray(cols["t"], float),
        u=np.column_stack([cols[n] for n in meta["input_names"]]).astype(float),
        y=np.asarray(cols[meta["output_name"]], float),
        input_names=tuple(meta["input_names"]), input_units=tuple(meta["input_units"]),
        output_name=meta["output_name"], output_unit=meta["output_unit"],
        u0=np.asarray(meta["u0"], float), y0=float(meta["y0"]),
        valid=np.asarray(cols["valid"]).astype(bool), cycle=np.asarray(cols["cycle"]).astype(np.int64),
        extra={k: np.asarray(v, float) for k, v in cols.items() if k not in fixed},
        sources=meta["sources"], notes=meta["notes"], fuel_lag_s=float(meta.get("fuel_lag_s", 0.0)),
        fuel_period_s=float(meta.get("fuel_period_s", 0.0)),
    )
