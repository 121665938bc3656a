"""SAE J1939-21 transport protocol: reassembling messages longer than 8 bytes from observed frames.

Hand-written rather than taken from a J1939 stack because fuelid only listens: it must follow BAM
broadcasts and other nodes' RTS/CTS connections passively, on recorded timestamps, and it must never
deliver a wrong payload (a public stack delivered corrupted data on a duplicated TP.DT).

TP.CM (PGN 60416) byte 1 is the control byte: 32 BAM, 16 RTS, 17 CTS, 19 EndOfMsgAck, 255 Abort;
bytes 2-3 total size [bytes] (9..1785), byte 4 number of packets (= ceil(size / 7)), bytes 6-8 the PGN
carried. TP.DT (PGN 60160) byte 1 is the sequence number 1..n, bytes 2-8 data, the last packet padded
with 0xFF.

Rules applied (a session is keyed by (source, destination); a BAM's destination is 255):

- Packets are accepted strictly in sequence. An identical copy of a packet already received is ignored;
  a gap, a differing copy, a packet outside the CTS window or a short packet discards the whole message.
- Connection mode: a CTS (sent by the receiver) opens a window of packets starting at its "next packet"
  number; a CTS asking again for packets already received drops them and takes the retransmission. The
  message is delivered on the receiver's EndOfMsgAck, when every packet is in.
- A BAM is delivered when its last packet arrives.
- Timeouts are measured on frame timestamps, so a replay behaves like the live bus: T1 = 0.75 s between
  BAM packets, T2/T3 = 1.25 s while a connection waits for data, CTS or EndOfMsgAck.
- A new BAM or RTS for a busy (source, destination) replaces the unfinished session; Abort ends one.
"""
from dataclasses import asdict, dataclass
from typing import NamedTuple

import can

from fuelid.logger.j1939 import GLOBAL_ADDRESS, PGN_TP_CM, PGN_TP_DT, make_id, parse_id

BAM, RTS, CTS, EOMA, ABORT = 32, 16, 17, 19, 255
MIN_SIZE, MAX_SIZE = 9, 1785
"""Transport protocol message sizes [bytes]."""


class Reassembled(NamedTuple):
    """A complete transport-protocol message."""

    t: float
    """Time of the frame that completed it [s]."""
    pgn: int
    sa: int
    da: int
    """Destination, 255 for BAM."""
    payload: bytes
    kind: str
    """``"bam"`` or ``"rts"``."""


@dataclass
class TPStats:
    """Session counters for the conversion summary."""

    started: int = 0
    completed: int = 0
    aborted: int = 0
    timed_out: int = 0
    replaced: int = 0
    """Unfinished sessions replaced by a new BAM/RTS from the same source to the same destination."""
    sequence_errors: int = 0
    """Sessions discarded for a gap, a differing duplicate, a packet outside the CTS window or a short
    packet."""
    duplicates: int = 0
    """Identical repeated packets, ignored."""
    invalid_cm: int = 0
    """TP.CM frames ignored: unknown control byte, size outside 9..1785, packet count != ceil(size/7)."""
    orphan_frames: int = 0
    """TP.DT, CTS or EndOfMsgAck frames with no open session to belong to."""

    @property
    def discarded(self) -> int:
        """Sessions that ended without delivering a payload."""
        return self.aborted + self.timed_out + self.replaced + self.sequence_errors


class _Session:
    __slots__ = ("pgn", "size", "packets", "kind", "buf", "window_end", "last_t")

    def __init__(self, pgn: int, size: int, packets: int, kind: str, t: float):
        self.pgn, self.size, self.packets, self.kind, self.last_t = pgn, size, packets, kind, t
        self.buf = bytearray()  # packets 1..k, 7 bytes each, so the next expected is k + 1
        # BAM: every packet may come; connection mode: none until the receiver's CTS
        self.window_end = packets + 1 if kind == "bam" else 1

    @property
    def next_seq(self) -> int:
        return len(self.buf) // 7 + 1


class TransportReassembler:
    """Follows BAM and RTS/CTS sessions on the bus and returns each complete payload once.

    `t1_s` [s]: longest silence between BAM packets (J1939-21 T1). `t2_s` [s]: longest wait in a
    connection-mode session (T2/T3).
    """

    def __init__(self, t1_s: float = 0.75, t2_s: float = 1.25):
        self.t1_s = t1_s
        self.t2_s = t2_s
        self.stats = TPStats()
        self._sessions: dict[tuple[int, int], _Session] = {}

    def counters(self) -> dict[str, int]:
        """`stats` as a flat dict, with the total `discarded`."""
        return {**asdict(self.stats), "discarded": self.stats.discarded}

    def feed(self, msg: can.Message) -> list[Reassembled]:
        """Take one frame (any frame; non-TP frames are ignored cheaply) and return the messages it
        completes (none or one)."""
        if not msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
            return []
        pf = (msg.arbitration_id >> 16) & 0xFF
        if pf != PGN_TP_CM >> 8 and pf != PGN_TP_DT >> 8:
            return []
        ident = parse_id(msg.arbitration_id)
        if ident.pgn == PGN_TP_CM:
            return self._connection_management(msg.timestamp, ident.sa, ident.da, bytes(msg.data))
        if ident.pgn == PGN_TP_DT:
            return self._data(msg.timestamp, ident.sa, ident.da, bytes(msg.data))
        return []

    @staticmethod
    def takes(can_id):
        """Which of the 29-bit identifiers (a numpy array) `feed` does not ignore: TP.CM's and TP.DT's PDU format."""
        pf = can_id >> 16 & 0xFF
        return (pf == PGN_TP_CM >> 8) | (pf == PGN_TP_DT >> 8)

    def expire(self, t: float) -> None:
        """Drop sessions silent for longer than their timeout at time `t` [s]; ``expire(math.inf)``
        at the end of a recording counts the unfinished ones as timed out."""
        for key, s in list(self._sessions.items()):
            if self._expired(s, t):
                del self._sessions[key]
                self.stats.timed_out += 1

    def _expired(self, s: _Session, t: float) -> bool:
        return t - s.last_t > (self.t1_s if s.kind == "bam" else self.t2_s)

    def _connection_management(self, t: float, sa: int, da: int, d: bytes) -> list[Reassembled]:
        self.expire(t)
        if len(d) < 8:
            self.stats.invalid_cm += 1
            return []
        control, size, packets, pgn = d[0], d[1] | d[2] << 8, d[3], int.from_bytes(d[5:8], "little")
        if control in (BAM, RTS):
            broadcast = da == GLOBAL_ADDRESS
            if broadcast != (control == BAM) or not MIN_SIZE <= size <= MAX_SIZE \
                    or packets != (size + 6) // 7:
                self.stats.invalid_cm += 1
                return []
            if self._sessions.pop((sa, da), None) is not None:
                self.stats.replaced += 1
            self._sessions[(sa, da)] = _Session(pgn, size, packets, "bam" if control == BAM else "rts", t)
            self.stats.started += 1
            return []
        if control == ABORT:
            # sent by either end: the session is (sa, da) or (da, sa), told apart by the PGN
            for key in ((sa, da), (da, sa)):
                s = self._sessions.get(key)
                if s is not None and s.pgn == pgn:
                    del self._sessions[key]
                    self.stats.aborted += 1
                    break
            return []
        if control not in (CTS, EOMA):
            self.stats.invalid_cm += 1
            return []
        # CTS and EndOfMsgAck come from the receiver: the session is (their destination, their source)
        s = self._sessions.get((da, sa))
        if s is None or s.kind != "rts" or s.pgn != pgn:
            self.stats.orphan_frames += 1
            return []
        s.last_t = t
        if control == EOMA:
            del self._sessions[(da, sa)]
            if s.next_seq <= s.packets:  # the receiver acknowledged data we did not see whole
                self.stats.sequence_errors += 1
                return []
            self.stats.completed += 1
            return [Reassembled(t, s.pgn, da, sa, bytes(s.buf[:s.size]), "rts")]
        count, first = d[1], d[2]
        if count and (first < 1 or first > s.next_seq or first + count - 1 > s.packets):
            del self._sessions[(da, sa)]  # asks for packets after a gap we did not see, or past the end
            self.stats.sequence_errors += 1
            return []
        if count:
            del s.buf[(first - 1) * 7:]  # retransmission requested from `first` on
            s.window_end = first + count
        else:
            s.window_end = s.next_seq  # hold: no packets until the next CTS
        return []

    def _data(self, t: float, sa: int, da: int, d: bytes) -> list[Reassembled]:
        key = (sa, da)
        s = self._sessions.get(key)
        if s is not None and self._expired(s, t):
            del self._sessions[key]
            self.stats.timed_out += 1
            s = None
        if s is None:
            self.stats.orphan_frames += 1
            return []
        s.last_t = t
        seq = d[0] if d else 0
        expected = s.next_seq
        chunk = d[1:8]
        if 1 <= seq < expected and s.buf[(seq - 1) * 7:seq * 7] == chunk.ljust(7, b"\xff"):
            self.stats.duplicates += 1  # identical repetition: harmless, ignore
            return []
        if seq != expected or seq >= s.window_end or len(chunk) < min(7, s.size - (seq - 1) * 7):
            del self._sessions[key]
            self.stats.sequence_errors += 1
            return []
        s.buf += chunk.ljust(7, b"\xff")
        if s.kind == "bam" and seq == s.packets:
            del self._sessions[key]
            self.stats.completed += 1
            return [Reassembled(t, s.pgn, sa, da, bytes(s.buf[:s.size]), "bam")]
        return []


def _cm(t: float, sa: int, da: int, priority: int, *data: int) -> can.Message:
    return can.Message(timestamp=t, arbitration_id=make_id(PGN_TP_CM, sa, da, priority),
                       is_extended_id=True, data=bytes(data))


def _dt(t: float, sa: int, da: int, priority: int, seq: int, payload: bytes) -> can.Message:
    chunk = payload[(seq - 1) * 7:seq * 7].ljust(7, b"\xff")
    return can.Message(timestamp=t, arbitration_id=make_id(PGN_TP_DT, sa, da, priority),
                       is_extended_id=True, data=bytes([seq]) + chunk)


def _check_size(payload: bytes) -> int:
    if not MIN_SIZE <= len(payload) <= MAX_SIZE:
        raise ValueError(f"TP payload must be {MIN_SIZE}..{MAX_SIZE} bytes, not {len(payload)}")
    return (len(payload) + 6) // 7


def bam_frames(pgn: int, sa: int, payload: bytes, t0: float = 0.0, gap_s: float = 0.05,
               priority: int = 7) -> list[can.Message]:
    """The frames of a BAM broadcast of `payload` from `sa`: TP.CM at `t0` [s], then one TP.DT every
    `gap_s` [s]; the last packet padded with 0xFF."""
    n = _check_size(payload)
    size, p = len(payload), pgn.to_bytes(3, "little")
    frames = [_cm(t0, sa, GLOBAL_ADDRESS, priority, BAM, size & 0xFF, size >> 8, n, 0xFF, *p)]
    frames += [_dt(t0 + k * gap_s, sa, GLOBAL_ADDRESS, priority, k, payload) for k in range(1, n + 1)]
    return frames


def rts_cts_frames(pgn: int, sa: int, da: int, payload: bytes, t0: float = 0.0,
                   gap_s: float = 0.01, priority: int = 7,
                   packets_per_cts: int = 255) -> list[can.Message]:
    """Both directions of a connection-mode transfer of `payload` from `sa` to `da`: RTS, then per
    window a CTS from `da` allowing up to `packets_per_cts` packets and the TP.DT packets, then
    EndOfMsgAck from `da`. Frames are `gap_s` [s] apart from `t0` [s]."""
    n = _check_size(payload)
    size, p = len(payload), pgn.to_bytes(3, "little")
    frames = [_cm(t0, sa, da, priority, RTS, size & 0xFF, size >> 8, n, packets_per_cts, *p)]
    for first in range(1, n + 1, packets_per_cts):
        count = min(packets_per_cts, n - first + 1)
        frames.append(_cm(t0 + len(frames) * gap_s, da, sa, priority, CTS, count, first, 0xFF, 0xFF, *p))
        frames += [_dt(t0 + (len(frames) + k) * gap_s, sa, da, priority, first + k, payload)
                   for k in range(count)]
    frames.append(_cm(t0 + len(frames) * gap_s, da, sa, priority, EOMA, size & 0xFF, size >> 8, n, 0xFF, *p))
    return frames
