"""Many CAN frames as columns (numpy arrays), and candump -L text parsed into them without a Python object per
line: how `fuelid convert` reads a candump at the speed of the writer.

A `FrameBlock` holds only ordinary frames: extended (29-bit) data frames, not error, not remote, classic CAN
(at most 8 data bytes), with a receive time below `MAX_BLOCK_TIME_S`. `candump_l_items` splits a piece of
candump -L text into FrameBlocks of such lines and, for every other line, what `parse_candump_l` makes of it
(a `can.Message`, or None for a malformed line), in the order of the lines, so a reader gives exactly the frames
the line-by-line parse gives.
"""
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace

import can
import numpy as np

MAX_BLOCK_TIME_S = 9e9
"""Receive times [s] a FrameBlock holds: below it, the time in nanoseconds fits a signed 64-bit integer."""

MAX_LINE_BYTES = 80
"""Longer lines (FD frames, trailing fields) are parsed one by one."""

_HEX = np.full(256, -1, np.int8)
for _i, _c in enumerate(b"0123456789abcdef"):
    _HEX[_c] = _i
for _i, _c in enumerate(b"ABCDEF"):
    _HEX[_c] = 10 + _i
_TIME, _CHANNEL, _HEXDIGIT = 1, 2, 4
_CLASS = np.zeros(256, np.uint8)  # which fields a byte may be part of
_CLASS[list(b"0123456789.")] |= _TIME
_CLASS[0x21:0x7F] |= _CHANNEL  # printable ASCII that JSON writes as itself
_CLASS[[ord('"'), ord("\\")]] &= ~np.uint8(_CHANNEL)
_CLASS[list(b"0123456789abcdefABCDEF")] |= _HEXDIGIT


@dataclass(frozen=True)
class FrameBlock:
    """Ordinary frames (see the module docstring) as columns, in recorded order."""

    t: np.ndarray
    """Receive time [s], float64."""
    can_id: np.ndarray
    """29-bit arbitration id, int64."""
    dlc: np.ndarray
    """Data length [bytes] 0..8, int64."""
    data: np.ndarray
    """Data bytes, uint8 (n, 8), zero after `dlc`."""
    channel: np.ndarray
    """Index into `channels` per frame, int64."""
    channels: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.t)

    def shifted(self, shift_s: float) -> "FrameBlock":
        """The same frames `shift_s` [s] later."""
        return replace(self, t=self.t + shift_s)

    def rows(self, mask: np.ndarray) -> "FrameBlock":
        """The frames where `mask` is true."""
        return replace(self, t=self.t[mask], can_id=self.can_id[mask], dlc=self.dlc[mask], data=self.data[mask],
                       channel=self.channel[mask])

    def message(self, i: int) -> can.Message:
        """Frame `i` as a `can.Message`, as the line-by-line reader makes it."""
        n = int(self.dlc[i])
        return can.Message(timestamp=float(self.t[i]), channel=self.channels[self.channel[i]],
                           arbitration_id=int(self.can_id[i]), is_extended_id=True, dlc=n,
                           data=self.data[i, :n].tobytes())


def _first(found: np.ndarray) -> np.ndarray:
    """Per row the column of the first true of `found`, the row's width where there is none."""
    return np.where(found.any(axis=1), found.argmax(axis=1), found.shape[1])


def _take(matrix: np.ndarray, first: np.ndarray, length: np.ndarray, width: int) -> np.ndarray:
    """Per row matrix[row, first : first + length] as an (n, width) matrix, zero-padded."""
    cols = np.arange(width)
    taken = np.take_along_axis(matrix, np.minimum(first[:, None] + cols, matrix.shape[1] - 1), axis=1)
    taken[cols >= length[:, None]] = 0
    return taken


def candump_l_items(text: bytes, parse: Callable[[str], can.Message | None]
                    ) -> Iterator[FrameBlock | can.Message | None]:
    """The lines of `text` (complete lines, each ending in a newline, newlines already universal): runs of
    ordinary ``(time) channel IIIIIIII#hexdata`` lines as FrameBlocks; every other non-blank line as
    `parse` makes it of the line (latin-1): a can.Message, or None when malformed."""
    buf = np.frombuffer(text, np.uint8)
    end = np.flatnonzero(buf == ord("\n"))
    if not len(end):
        return
    start = np.concatenate(([0], end[:-1] + 1))
    length = end - start
    width = min(int(length.max()), MAX_LINE_BYTES)
    cols = np.arange(width)
    lines = buf[np.minimum(start[:, None] + cols, len(buf) - 1)]
    lines[cols >= length[:, None]] = 0
    cls = _CLASS[lines]
    close = _first(lines == ord(")"))
    space = _first((lines == ord(" ")) & (cols > close[:, None] + 1))
    hash_at = space + 9
    data_len = length - hash_at - 1
    ok = ((length <= width) & (lines[:, 0] == ord("(")) & (close >= 4) & (space > close + 2) & (hash_at < length)
          & (data_len <= 16) & (data_len % 2 == 0))
    at = np.minimum(np.stack([close + 1, hash_at, close - 1, np.ones_like(close)], axis=1), width - 1)
    after_close, at_hash, before_close, after_open = np.take_along_axis(lines, at, axis=1).T
    ok &= (after_close == ord(" ")) & (at_hash == ord("#")) & (before_close != ord(".")) & (after_open != ord("."))
    c = cols[None, :]
    in_time = (c >= 1) & (c < close[:, None])
    in_channel = (c >= close[:, None] + 2) & (c < space[:, None])
    in_hex = (c > space[:, None]) & (c < length[:, None]) & (c != hash_at[:, None])
    bad = (in_time & (cls & _TIME == 0)) | (in_channel & (cls & _CHANNEL == 0)) | (in_hex & (cls & _HEXDIGIT == 0))
    ok &= ~bad.any(axis=1) & (((lines == ord(".")) & in_time).sum(axis=1) == 1)
    ok &= np.take_along_axis(lines, np.minimum(space + 1, width - 1)[:, None], axis=1)[:, 0] <= ord("1")  # 29 bits
    t = np.zeros(len(start))
    if ok.any():
        digits = close[ok] - 1
        w = int(digits.max())
        t[ok] = _take(lines[ok], np.ones_like(digits), digits, w).view(f"S{w}").ravel().astype(np.float64)
        ok &= t < MAX_BLOCK_TIME_S
    previous = 0
    for i in np.flatnonzero(~ok & (length > 0)).tolist() + [len(start)]:  # blank lines inside a run: dropped
        run = np.arange(previous, i)[ok[previous:i]]
        if len(run):
            yield _block(lines[run], t[run], close[run], space[run], data_len[run])
        if i < len(start):
            line = text[start[i] : end[i] + 1].decode("latin-1")
            if line.strip():
                yield parse(line)
        previous = i + 1


def _block(lines, t, close, space, data_len) -> FrameBlock:
    nibbles = _HEX[_take(lines, space + 1, np.full_like(space, 8), 8)].astype(np.int64)
    can_id = (nibbles << (4 * np.arange(7, -1, -1))).sum(axis=1)
    hexdata = _HEX[_take(lines, space + 10, data_len, 16)].astype(np.uint8)
    hexdata[hexdata == 255] = 0  # the zero padding
    data = hexdata[:, 0::2] << 4 | hexdata[:, 1::2]
    chan_len = space - close - 2
    w = int(chan_len.max())
    names, channel = np.unique(_take(lines, close + 2, chan_len, w).view(f"S{w}").ravel(), return_inverse=True)
    return FrameBlock(t=t, can_id=can_id, dlc=data_len // 2, data=data, channel=channel.ravel(),
                      channels=tuple(c.decode("ascii") for c in names.tolist()))
