"""J1939 message columns: what a file's decoded channels hold, in a form that reads without JSON.

`fuelid convert` and the logger daemon write, beside the `/j1939/<MESSAGE>` and `/flowmeter` JSON channels,
MCAP attachments named `fuelid.columns` (media type `application/x.fuelid.columns+npz+zstd`, docs/reference/formats.md): each a zstd-compressed
`.npz` of one block of up to `BLOCK_ROWS` rows, every row one message written to those channels, numbered in
write order (`seq`):

    j1939 rows  seq int32, t_ns int64 (both delta-coded), pgn uint32, sa, da, tp uint8
                (0 single frame, 1 BAM, 2 RTS/CTS), length uint16, payload uint8 (max length × rows,
                byte-major, 0xFF-padded): the Decoder's input, from which `Decoder.decode_columns` gives
                exactly the values of the JSON records
    flow rows   flow_seq int32, flow_t_ns int64 (delta-coded), flow_kg_h, volts float64 (NaN = null)

Rows are grouped by (pgn, sa) inside a block (write order kept within a group), which compresses the
payload bytes ~2× better. Attachments sit outside the chunks, so a reader of the columns decompresses
~1 MB per 1.5 h of driving instead of every chunk. They are an addition: every reader of the JSON channels
is unaffected, and files without them (older files, cut files, recovered ones) read through the JSON channels.
"""
from __future__ import annotations

import io
from dataclasses import dataclass
from typing import Callable

import numpy as np
import zstandard

NAME = "fuelid.columns"
MEDIA_TYPE = "application/x.fuelid.columns+npz+zstd"
FORMAT = "fuelid columns v1"
BLOCK_ROWS = 1 << 16
TP_KINDS = {None: 0, "bam": 1, "rts": 2}
_J1939 = ("seq", "t_ns", "pgn", "sa", "da", "tp", "length", "payload")
_FLOW = ("flow_seq", "flow_t_ns", "flow_kg_h", "volts")


@dataclass
class ColumnBlock:
    """One block's rows, as `read_block` returns them (j1939 rows in (pgn, sa) groups, write order within)."""
    seq: np.ndarray
    t_ns: np.ndarray
    pgn: np.ndarray
    sa: np.ndarray
    length: np.ndarray
    payload: np.ndarray  # rows × max length, uint8
    flow_seq: np.ndarray
    flow_t_ns: np.ndarray
    flow_kg_h: np.ndarray  # [kg/h]
    volts: np.ndarray  # [V]

    @property
    def rows(self) -> int:
        return len(self.seq) + len(self.flow_seq)


class ColumnWriter:
    """Collects the rows of the column attachments and hands each full block to `attach(data, log_time_ns)`.
    Rows come one at a time (a tuple appended to a list: the frame-by-frame path) or many at once as arrays
    (`add_messages`: a block of candump frames); the columns are made per block."""

    def __init__(self, attach: Callable[[bytes, int], None]):
        self._attach = attach  # (block data, log time [ns] of its earliest row)
        self._reset()

    def _reset(self) -> None:
        self._rows = 0
        self._messages: list[tuple] = []  # (seq, t_ns, pgn, sa, da, tp kind, payload)
        self._readings: list[tuple] = []  # (seq, t_ns, flow_kg_h, volts)
        self._many: list[tuple] = []  # (seq, t_ns, pgn, sa, da, length, payload matrix) arrays of add_messages

    def add_message(self, t_ns: int, pgn: int, sa: int, da: int, tp: str | None, payload: bytes) -> None:
        """One decoded J1939 message: its log time [ns], identifier fields and the payload it decoded from."""
        self._messages.append((self._rows, t_ns, pgn, sa, da, TP_KINDS[tp], payload))
        self._rows += 1
        if self._rows == BLOCK_ROWS:
            self.flush()

    def add_messages(self, t_ns: np.ndarray, pgn: np.ndarray, sa: np.ndarray, da: np.ndarray, length: np.ndarray,
                     payload: np.ndarray) -> None:
        """`add_message` of many single-frame messages in write order: arrays of their log times [ns],
        identifier fields, payload lengths [bytes] and an (n, width) matrix of the payloads (bytes after each
        length ignored)."""
        done = 0
        while done < len(t_ns):
            take = min(len(t_ns) - done, BLOCK_ROWS - self._rows)
            part = slice(done, done + take)
            self._many.append((self._rows + np.arange(take), t_ns[part], pgn[part], sa[part], da[part],
                               length[part], payload[part]))
            self._rows += take
            done += take
            if self._rows == BLOCK_ROWS:
                self.flush()

    def add_flow(self, t_ns: int, flow_kg_h: float | None, volts: float | None) -> None:
        """One flow-meter reading: log time [ns], flow [kg/h] and voltage [V] (None = null)."""
        self._readings.append((self._rows, t_ns, np.nan if flow_kg_h is None else flow_kg_h,
                               np.nan if volts is None else volts))
        self._rows += 1
        if self._rows == BLOCK_ROWS:
            self.flush()

    def flush(self) -> None:
        """Write the rows collected so far as one attachment (nothing when there are none)."""
        if not self._rows:
            return
        cols = list(zip(*self._messages)) or [()] * 7
        seq, t, pgn, sa, da, tp = (np.array(c, dtype) for c, dtype in
                                   zip(cols, (np.int64, np.int64, np.uint32, np.uint8, np.uint8, np.uint8)))
        length = np.array([len(p) for p in cols[6]], np.int64)
        width = max([int(length.max()) if len(length) else 0] + [p[6].shape[1] for p in self._many])
        payload = np.full((len(length), width), 0xFF, np.uint8)
        row = np.repeat(np.arange(len(length)), length)
        payload[row, np.arange(len(row)) - (np.cumsum(length) - length)[row]] = np.frombuffer(b"".join(cols[6]), np.uint8)
        if self._many:
            many = list(zip(*self._many))
            seq, t, pgn, sa, da, length = (np.concatenate([a, *m]).astype(a.dtype, copy=False)
                                           for a, m in zip((seq, t, pgn, sa, da, length), many))
            tp = np.concatenate([tp, np.zeros(len(seq) - len(tp), np.uint8)])
            wide = np.full((len(seq) - len(payload), width), 0xFF, np.uint8)
            at = 0
            for p in many[6]:
                wide[at : at + len(p), : p.shape[1]] = p
                at += len(p)
            payload = np.concatenate([payload, wide])
            payload[np.arange(width) >= length[:, None]] = 0xFF
        order = np.lexsort((seq, sa, pgn))  # write order within each (pgn, sa) group
        t, seq = t[order], seq[order]
        arrays = dict(zip(_J1939, (np.diff(seq, prepend=0).astype(np.int32), np.diff(t, prepend=0), pgn[order],
                                   sa[order], da[order], tp[order], length[order].astype(np.uint16),
                                   payload[order].T.copy())))
        cols = list(zip(*self._readings)) or [()] * 4
        flow_seq, flow_t, flow, volts = (np.array(c, dtype) for c, dtype in
                                         zip(cols, (np.int64, np.int64, np.float64, np.float64)))
        arrays.update(zip(_FLOW, (np.diff(flow_seq, prepend=0).astype(np.int32), np.diff(flow_t, prepend=0),
                                  flow, volts)))
        arrays["format"] = np.array(FORMAT)
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        self._attach(zstandard.ZstdCompressor(level=3).compress(buf.getvalue()),
                     int(np.concatenate([t, flow_t]).min()))
        self._reset()


def read_block(data: bytes) -> ColumnBlock:
    """The rows of one `fuelid.columns` attachment's data; ValueError when it is not one, or inconsistent."""
    try:
        raw = zstandard.ZstdDecompressor().decompress(data)
        with np.load(io.BytesIO(raw), allow_pickle=False) as z:
            if str(z["format"]) != FORMAT:
                raise ValueError(f"format {str(z['format'])!r}, not {FORMAT!r}")
            a = {k: z[k] for k in _J1939 + _FLOW}
    except (zstandard.ZstdError, OSError, KeyError, EOFError) as exc:
        raise ValueError(f"not a {FORMAT} block ({exc})") from None
    n, m = len(a["seq"]), len(a["flow_seq"])
    seq, flow_seq = np.cumsum(a["seq"], dtype=np.int64), np.cumsum(a["flow_seq"], dtype=np.int64)
    every = np.concatenate([seq, flow_seq])  # each row number once: nothing lost, nothing twice
    if (any(len(a[k]) != n for k in _J1939[:-1]) or a["payload"].shape[1:] != (n,)
            or any(len(a[k]) != m for k in _FLOW) or (n and a["length"].max() > len(a["payload"]))
            or (n + m and (every.min() < 0 or every.max() >= n + m
                           or not (np.bincount(every, minlength=n + m) == 1).all()))):
        raise ValueError(f"inconsistent {FORMAT} block")
    return ColumnBlock(seq, np.cumsum(a["t_ns"]), a["pgn"].astype(np.int64), a["sa"].astype(np.int64),
                       a["length"].astype(np.int64), a["payload"].T, flow_seq, np.cumsum(a["flow_t_ns"]),
                       a["flow_kg_h"], a["volts"])
