"""Replay recorded traffic with its original timing: CAN frames onto a python-can bus, a flow-meter capture
onto a pseudo-terminal that the daemon opens like the real meter's serial port.

Every event is due at `start + (t - t0) / speed` on the monotonic clock, an absolute schedule, so lateness
(a frame sent after its due time) never adds up over a long replay; `Lateness` reports how late frames were.
"""
from __future__ import annotations

import errno
import heapq
import itertools
import os
import time
import tty
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator

import can

from fuelid.errors import FuelidError
from fuelid.logger.flowmeter import read_capture
from fuelid.logger.mcap_log import MAGIC, read_messages
from fuelid.logger.readers import read_frames

# Two sources recorded together (a CAN log and the flow-meter capture of the same trip) keep their relative
# timing when their first timestamps are this close [s]; farther apart they are not the same recording,
# and each starts when the replay starts.
SAME_RECORDING_S = 3600.0


def recorded_frames(path: str | Path) -> Iterator[can.Message]:
    """The frames of a CAN recording: any format `logger.readers` reads, or the `/can/raw` channel of an MCAP log."""
    with open(path, "rb") as f:
        is_mcap = f.read(len(MAGIC)) == MAGIC
    if not is_mcap:
        yield from read_frames(path)
        return
    for _, _, r in read_messages(path, "/can/raw"):
        yield can.Message(timestamp=r["t"], arbitration_id=r["id"], is_extended_id=r["extended"], dlc=r["dlc"],
                          data=bytes.fromhex(r["data"]), is_error_frame=r["error"], is_remote_frame=r["remote"],
                          channel=r["channel"])


def chained(paths: list[Path]) -> Iterator[tuple[float, can.Message]]:
    """(time [s], frame) of several recordings played one after another: each file keeps its own inter-frame
    timing and starts where the previous one ended."""
    base = None
    for path in paths:
        first = last = None
        for msg in recorded_frames(path):
            if first is None:
                first = msg.timestamp
                base = first if base is None else base
            last = msg.timestamp
            yield base + msg.timestamp - first, msg
        if first is not None:
            base += last - first


@dataclass
class Lateness:
    """How late events went out against their schedule [s]."""

    events: int = 0
    total_s: float = 0.0
    max_s: float = 0.0
    last_s: float = 0.0

    def add(self, late_s: float) -> None:
        self.events += 1
        self.total_s += late_s
        self.max_s = max(self.max_s, late_s)
        self.last_s = late_s

    @property
    def mean_s(self) -> float:
        return self.total_s / self.events if self.events else 0.0


@dataclass
class ReplayStats:
    frames: int = 0
    skipped_error_frames: int = 0  # error frames are a receiver's report, not something to send
    send_errors: int = 0
    flow_lines: int = 0
    flow_lines_dropped: int = 0  # nobody reading the pty: a serial line drops bytes too
    passes: int = 0
    duration_s: float = 0.0  # wall time of the replay
    lateness: Lateness = None

    def to_dict(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if k != "lateness"}
        d.update(late_max_s=self.lateness.max_s, late_mean_s=self.lateness.mean_s, late_last_s=self.lateness.last_s)
        return d


class PtyMeter:
    """A pseudo-terminal that plays the flow meter's data logger: lines written here come out of `path`,
    which pyserial opens like a real serial device. Raw mode, so `\\r\\n` and bytes pass unchanged."""

    def __init__(self, link: str | Path | None = None):
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)  # the slave end stays open here, so a reader's reconnect finds it
        self.link = Path(link) if link else None
        if self.link:
            self.link.unlink(missing_ok=True)
            self.link.symlink_to(self.path)

    def write_line(self, line: bytes) -> bool:
        """Send one line with its `\\n`; False when the pty buffer is full (nobody reading)."""
        try:
            os.write(self._master, line + b"\n")
            return True
        except BlockingIOError:
            return False
        except OSError as exc:
            if exc.errno == errno.EIO:  # no reader has the slave open: like an unplugged cable
                return False
            raise

    def close(self) -> None:
        if self.link:
            self.link.unlink(missing_ok=True)
        os.close(self._master)
        os.close(self._slave)


def _timeline(can_paths: list[Path], capture: Path | None) -> Iterator[tuple[float, int, object]]:
    """(time from the start [s], kind, item) of one pass: kind 0 a CAN frame, 1 a flow-meter line."""
    sources = []
    if can_paths:
        sources.append(((t, 0, m) for t, m in chained(can_paths)))
    if capture:
        sources.append(((t, 1, line) for t, line in read_capture(capture)))
    firsts, streams = [], []
    for source in sources:
        head = next(source, None)
        if head is not None:
            firsts.append(head[0])
            streams.append(itertools.chain([head], source))
    if not streams:
        return
    same = max(firsts) - min(firsts) <= SAME_RECORDING_S
    offsets = [min(firsts) if same else first for first in firsts]
    shifted = [((t - off, kind, item) for t, kind, item in s) for s, off in zip(streams, offsets)]
    yield from heapq.merge(*shifted, key=lambda e: e[0])


def replay(
    can_paths: Iterable[str | Path] = (),
    bus: can.BusABC | None = None,
    *,
    capture: str | Path | None = None,
    meter: PtyMeter | None = None,
    speed: float = 1.0,
    loop: bool = False,
    should_stop: Callable[[], bool] = lambda: False,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> ReplayStats:
    """Play `can_paths` onto `bus` and the flow-meter `capture` onto `meter`, merged by time, at `speed`
    times the recorded pace; with `loop`, again and again until `should_stop()`."""
    if speed <= 0:
        raise FuelidError("--speed must be > 0")
    can_paths = [Path(p) for p in can_paths]
    capture = Path(capture) if capture else None
    for path in can_paths + ([capture] if capture else []):
        if not path.is_file():
            raise FuelidError(f"no such file: {path}")
    stats = ReplayStats(lateness=Lateness())
    start = clock()
    base = 0.0  # schedule time [s] at which the current pass starts
    while not should_stop():
        end = base
        for t, kind, item in _timeline(can_paths, capture):
            due = start + (base + t) / speed
            wait = due - clock()
            if wait > 0:
                sleep(wait)
            if should_stop():
                break
            stats.lateness.add(max(0.0, clock() - due))
            end = base + t
            if kind == 0:
                _send(bus, item, stats)
            else:
                stats.flow_lines += 1
                stats.flow_lines_dropped += not meter.write_line(item)
        stats.passes += 1
        if not loop or end == base:  # an empty or instant recording would loop at full speed
            break
        base = end
    stats.duration_s = clock() - start
    return stats


def _send(bus: can.BusABC, msg: can.Message, stats: ReplayStats) -> None:
    if msg.is_error_frame:
        stats.skipped_error_frames += 1
        return
    # The recorded channel names the bus it was logged on; socketcan would send to that interface by name.
    msg.channel = None
    try:
        bus.send(msg)
        stats.frames += 1
    except can.CanError:
        stats.send_errors += 1
