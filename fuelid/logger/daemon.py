"""The in-cab logger daemon: a CAN bus and the flow meter in, rotated crash-safe MCAP files out, for months
unattended with the power cut without warning.

The parts, each doing one thing:
- `LogFiles`: the output folder: names, `.part` files while open, renaming on close, recovering orphans, and
  the `on_file_closed` callbacks run with every finished file (e.g. an upload queue).
- `LogSink`: the python-can listener in front of the `Recorder`; rotates files without losing a frame and
  stops writing (dropping, counted) while the disk is full.
- `Estimator`: what the daemon needs of an online estimator, passed in by the command line (`fuelid log
  --identify` wires in fuelid.ident.live.LiveEstimator; this package imports nothing from fuelid.ident).
- `IdentifyingRecorder`: with an estimator, the Recorder that also feeds it every decoded record and writes
  the records it returns (/ident/*) into the same file.
- `BusLink`: the `can.Bus` and its `can.Notifier`, reopened with backoff after an error (interface down,
  bus-off, adapter unplugged).
- `FlowInput`: the serial flow meter in a thread (`SerialFlowMeter` reconnects by itself).
- `Faults`: each kind of fault logged once when it starts and once when it clears, with counts.
- `Daemon`: the main loop: polls the parts, rotates, writes the status file once a second.
"""
from __future__ import annotations

import errno
import json
import logging
import math
import os
import shutil
import socket
import subprocess
import threading
import time
from collections import Counter
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Protocol

import can

from fuelid.logger.config import LoggerConfig
from fuelid.logger.durable import fsync_path
from fuelid.logger.flowmeter import Calibration, SerialFlowMeter
from fuelid.logger.mcap_log import MAGIC, recover
from fuelid.logger.recorder import Recorder, open_writer
from fuelid.logger.relabel import relabel
from fuelid.logger.upload import UploadQueue

log = logging.getLogger("fuelid.log")

PART = ".part"  # suffix of a file being written; a file without it was closed cleanly
RECOVERING = ".recovering"  # suffix of a recovered copy being written; left over only by a crash meanwhile
# The MCAP SDK reports a failed write (disk full, I/O error) as RuntimeError, the fsync after it as OSError.
STORAGE_ERRORS = (OSError, RuntimeError)
TICK_S = 0.2  # main-loop period [s]: wall-time chunk flushes and rotation checks run this often
STATUS_S = 1.0  # status file period [s]

# Keyword arguments that put a python-can interface in listen-only mode, where it has one.
# socketcan is set with `ip link` instead (see BusLink._configure_socketcan).
LISTEN_ONLY = {
    "slcan": {"listen_only": True},
    "vector": {"listen_only": True},
    "nixnet": {"listen_only": True},
    "cantact": {"monitor": True},
    "kvaser": {"driver_mode": False},  # DRIVER_MODE_SILENT
    "pcan": {"state": can.BusState.PASSIVE},
}


class Faults:
    """Counts faults by kind; logs a kind once when it starts and once when it clears, never per occurrence."""

    def __init__(self):
        self.counts: Counter = Counter()
        self.active: dict[str, str] = {}  # kind -> first message of the current episode
        self._lock = threading.Lock()

    def occur(self, kind: str, detail: str) -> None:
        with self._lock:
            self.counts[kind] += 1
            if kind in self.active:
                return
            self.active[kind] = detail
        log.warning("%s: %s (further occurrences counted, not logged)", kind, detail)

    def clear(self, kind: str, detail: str = "") -> None:
        with self._lock:
            if self.active.pop(kind, None) is None:
                return
            total = self.counts[kind]
        log.info("%s cleared%s (%d occurrences so far)", kind, f": {detail}" if detail else "", total)


class LogFiles:
    """The output folder. A file is written as `NAME.mcap.part` and renamed to `NAME.mcap` once closed,
    so a `.part` file found at start-up is an orphan of a crash or power cut, to recover.

    Every callback in `on_file_closed` is called with the path of each file once it is final (closed and
    renamed, or recovered); a callback that raises is counted as a "file_closed" fault, never stops logging."""

    def __init__(self, directory: Path, faults: Faults | None = None):
        self.dir = directory
        self.dir.mkdir(parents=True, exist_ok=True)
        self.faults = faults or Faults()
        self.on_file_closed: list[Callable[[Path], None]] = []
        self.postponed: dict[Path, int] = {}  # orphans whose recovery the disk stopped -> their size [bytes]

    def _closed(self, final: Path) -> None:
        for callback in self.on_file_closed:
            try:
                callback(final)
            except Exception as exc:  # a hook (upload queue, ...) must not stop the logging
                self.faults.occur("file_closed", f"{getattr(callback, '__name__', callback)}({final.name}): "
                                  f"{type(exc).__name__}: {exc}")

    def new_path(self) -> Path:
        # Names sort in time order: UTC to the millisecond, then _1, _2... (after ".") in the same millisecond.
        now = datetime.now(timezone.utc)
        stamp = now.strftime("%Y%m%dT%H%M%S") + f".{now.microsecond // 1000:03d}Z"
        for n in range(1000):
            name = f"fuelid-{stamp}" + (f"_{n}" if n else "") + ".mcap"
            if not (self.dir / name).exists() and not (self.dir / (name + PART)).exists():
                return self.dir / (name + PART)
        raise FileExistsError(f"no free file name in {self.dir}")

    def finish(self, part: Path) -> Path:
        """Rename a closed `.part` file to its final name, durably."""
        final = part.with_name(part.name[: -len(PART)])
        os.replace(part, final)
        fsync_path(self.dir)
        self._closed(final)
        return final

    def recover_orphans(self, writing: Path | None = None, free_bytes: float = math.inf) -> list[str]:
        """Make every `.part` file but `writing` a valid closed file (what a crash or a full disk left); one line
        each. A recovery the disk stops (full, I/O error) leaves the `.part` as it was, is a "recovery" fault
        until it succeeds, and is tried again once `free_bytes` would hold a copy of it; a file that is not
        recoverable is kept as `.bad` and not tried again."""
        for debris in self.dir.glob("*.mcap" + RECOVERING):  # a copy a crash cut short; its .part is still here
            debris.unlink(missing_ok=True)
        done = []
        for part in sorted(self.dir.glob("*.mcap" + PART)):
            if part == writing or self.postponed.get(part, 0) > free_bytes:
                continue
            final = part.with_name(part.name[: -len(PART)])
            size = part.stat().st_size
            if size <= len(MAGIC):  # cut before anything was written
                part.unlink()
                done.append(f"removed empty {part.name}")
                continue
            tmp = final.with_name(final.name + RECOVERING)
            try:
                stats = recover(part, tmp)
                os.replace(tmp, final)
                part.unlink()
                fsync_path(self.dir)
            except OSError as exc:  # the disk, not the file: keep it as it is, try again when there is room
                tmp.unlink(missing_ok=True)
                self.postponed[part] = size
                self.faults.occur("recovery", f"{part.name}: {exc}; kept, tried again when there is room")
                done.append(f"recovery of {part.name} postponed: {exc}")
                continue
            except Exception as exc:  # not recoverable: keep the bytes, stop retrying it
                tmp.unlink(missing_ok=True)
                part.rename(part.with_name(part.name + ".bad"))
                self.postponed.pop(part, None)
                done.append(f"{part.name} unreadable ({exc}), kept as .bad")
                continue
            if self.postponed.pop(part, None) is not None and not self.postponed:
                self.faults.clear("recovery", "every postponed file recovered")
            lost = "" if stats.complete else (f", {stats.bytes_lost} bytes lost"
                                              + (f" ({len(stats.damaged)} damaged chunks skipped)" if stats.damaged else ""))
            done.append(f"recovered {final.name}: {sum(stats.messages.values())} messages{lost}")
            self._closed(final)
        return done


class Estimator(Protocol):
    """An online estimator run on the logged stream (fuelid.ident.live.LiveEstimator is one)."""

    schemas: dict[str, dict]  # topic -> JSON schema of the records `feed` returns, registered in each file
    snapshot_path: Path | None  # where `snapshot` writes the current model

    def prepare(self) -> None:
        """Load what the first record would need (compiled code) before frames arrive."""

    def feed(self, topic: str, t: float, record: dict) -> list[tuple[str, float, dict]]:
        """One decoded record received at t [s]; returns the records to log: (topic, receive time [s], record)."""

    def snapshot(self) -> bool:
        """Write the current model to snapshot_path; False while there is none yet."""

    def status(self) -> dict:
        """The estimator's entry in the status file: {"state": ..., ...}."""


class IdentifyingRecorder(Recorder):
    """A Recorder that feeds every decoded record (/j1939/*, /flowmeter) to an `Estimator` and writes the
    records it returns, with their schemas (registered in each new file, as every channel).

    An exception from the estimator is counted in `errors` and as an "identify" fault (logged once); the
    record that caused it is logged all the same and the estimator keeps getting the next ones."""

    def __init__(self, writer, live: Estimator, faults: Faults):
        self.live, self.faults, self.errors = live, faults, 0
        self._schemas = live.schemas
        super().__init__(writer)

    def _write(self, topic: str, schema: dict, log_time_ns: int, record: dict) -> None:
        super()._write(topic, schema, log_time_ns, record)
        if topic == "/can/raw" or topic in self._schemas:
            return
        try:
            out = self.live.feed(topic, log_time_ns * 1e-9, record)
        except Exception as exc:
            self.errors += 1
            self.faults.occur("identify", f"{type(exc).__name__}: {exc}")
            return
        for ident_topic, t, rec in out:
            super()._write(ident_topic, self._schemas[ident_topic], int(t * 1e9), rec)


class LogSink(can.Listener):
    """Feeds frames and meter readings to a `Recorder`, from the notifier's and the meter's threads.

    While no file is open (disk full), everything is dropped and counted in `dropped`. A storage error
    abandons the current file (left as `.part`, recovered when space returns) instead of stopping the bus.
    With an Estimator `live`, the recorder is an IdentifyingRecorder.
    """

    def __init__(self, config: LoggerConfig, files: LogFiles, faults: Faults, live: Estimator | None = None):
        self.config = config
        self.files = files
        self.faults = faults
        self.live = live
        self.lock = threading.Lock()
        self.recorder: Recorder | None = None
        self.part: Path | None = None  # the file being written
        self.opened_at = 0.0  # [s, monotonic]
        self.dropped = 0
        self.record_errors = 0
        self.closed_files = 0
        self.unlabelled: set[str] = set()  # files closed before the VIN was seen, naming the configured truck

    # --- the notifier's and the meter's threads

    def on_message_received(self, msg: can.Message) -> None:
        with self.lock:
            self._feed(Recorder.on_message_received, msg)

    def on_flow_reading(self, reading) -> None:
        with self.lock:
            self._feed(Recorder.on_flow_reading, reading)

    def _feed(self, method, item) -> None:
        if self.part is None:
            self.dropped += 1
            return
        try:
            method(self.recorder, item)
        except STORAGE_ERRORS as exc:
            self.dropped += 1
            self._abandon(exc)
        except Exception as exc:  # a frame the decoder chokes on must not stop the logging of the others
            self.record_errors += 1
            self.faults.occur("decode", f"{type(exc).__name__}: {exc}")

    # --- the main thread

    def _open_writer(self):
        truck = (self.recorder.vin if self.recorder else None) or self.config.truck
        part = self.files.new_path()
        writer = open_writer(part, truck=truck, source=f"{self.config.interface}:{self.config.channel}")
        writer.set_metadata({"source_preference": self.config.source_preference})
        return part, writer

    def open(self) -> bool:
        """Start writing (at start-up and when space returns); False while the disk still refuses."""
        try:
            part, writer = self._open_writer()
        except STORAGE_ERRORS as exc:
            self.faults.occur("storage", f"cannot open a new file in {self.files.dir}: {exc}")
            return False
        with self.lock:
            if self.recorder is None:
                self.recorder = IdentifyingRecorder(writer, self.live, self.faults) if self.live else Recorder(writer)
            else:
                self.recorder.rotate(writer)
            self.part, self.opened_at = part, time.monotonic()
        log.info("writing %s", part)
        return True

    def rotate(self) -> None:
        """Close the current file and continue in a new one; frames arriving meanwhile wait on the lock."""
        try:
            part, writer = self._open_writer()  # before taking the lock: opening takes a moment
        except STORAGE_ERRORS as exc:
            self.faults.occur("storage", f"cannot open a new file in {self.files.dir}: {exc}")
            return
        with self.lock:
            old_part, old = self.part, self.recorder.rotate(writer)
            self.part, self.opened_at = part, time.monotonic()
        self._finish(old_part, old)
        log.info("rotated to %s", part)

    def stop_writing(self) -> None:
        """Close the current file cleanly (shutdown, or the disk getting full); frames are dropped after."""
        with self.lock:
            part, self.part = self.part, None
            writer = self.recorder.writer if part else None
        if part:
            self._finish(part, writer)

    def _finish(self, part: Path, writer) -> None:
        try:
            writer.close()
            final = self.files.finish(part)
        except STORAGE_ERRORS as exc:  # the file stays .part; recover_orphans makes it whole later
            self.faults.occur("storage", f"closing {part.name}: {exc}")
            return
        self.closed_files += 1
        if self.recorder.vin is None:
            self.unlabelled.add(str(final.resolve()))
        log.info("closed %s", final)

    def _abandon(self, exc: Exception) -> None:
        # Called with the lock held: the writer is broken, so do not try to close it; keep its .part.
        self.faults.occur("storage", f"writing {self.part.name}: {exc}")
        self.part = None

    def tick(self) -> None:
        """Wall-time flushes on a quiet bus, and rotation by age and size."""
        with self.lock:
            if self.part is None:
                return
            try:
                self.recorder.writer.flush_if_due()
            except STORAGE_ERRORS as exc:
                self._abandon(exc)
                return
            part, age = self.part, time.monotonic() - self.opened_at
        try:
            size = part.stat().st_size
        except OSError:
            size = 0
        if age >= self.config.rotate_s or size >= self.config.rotate_mb * 1e6:
            self.rotate()


class BusWatch(can.Listener):
    """Tells the daemon that the notifier's bus failed, and whether frames arrive."""

    def __init__(self):
        self.failed: Exception | None = None
        self.received = False

    def on_message_received(self, msg: can.Message) -> None:
        self.received = True

    def on_error(self, exc: Exception) -> None:
        self.failed = self.failed or exc


class BusLink:
    """The bus and its notifier; after an error both are dropped and the bus is reopened with backoff
    (doubling from `backoff_s[0]` to `backoff_s[1]`, back to the start once frames flow again)."""

    def __init__(self, config: LoggerConfig, listener: can.Listener, faults: Faults,
                 backoff_s: tuple[float, float] = (0.5, 5.0)):
        self.config = config
        self.listener = listener
        self.faults = faults
        self.backoff_s = backoff_s
        self.state = "connecting"  # "up", "down" (waiting to reopen)
        self.connects = 0
        self.last_error: str | None = None
        self.bus: can.BusABC | None = None
        self._notifier: can.Notifier | None = None
        self._watch = BusWatch()
        self._delay = backoff_s[0]
        self._retry_at = 0.0

    def poll(self, now: float) -> None:
        if self._notifier is None:
            if now >= self._retry_at:
                self._open(now)
            return
        if self._watch.received:
            self._delay = self.backoff_s[0]
            self.faults.clear("bus", f"{self.config.channel} receiving again")
        if self._watch.failed is not None:
            self._fail(now, self._watch.failed)

    def _open(self, now: float) -> None:
        cfg = self.config
        options = dict(cfg.bus_options)
        if cfg.bitrate:
            options["bitrate"] = cfg.bitrate
        if cfg.listen_only:
            options.update(LISTEN_ONLY.get(cfg.interface, {}))
        try:
            if cfg.interface == "socketcan":
                if cfg.bitrate or cfg.listen_only:
                    self._configure_socketcan()
                _require_link_up(cfg.channel)
            self.bus = can.Bus(interface=cfg.interface, channel=cfg.channel, **options)
        except Exception as exc:  # any interface's failure to open: retry later
            self._fail(now, exc)
            return
        _enlarge_receive_buffer(self.bus)
        self._watch = BusWatch()
        self._notifier = can.Notifier(self.bus, [self.listener, self._watch], timeout=0.5)
        self.connects += 1
        self.state = "up"
        log.info("listening on %s %s", cfg.interface, cfg.channel)

    def _configure_socketcan(self) -> None:
        # Bitrate and listen-only of a real CAN interface are link settings; restart-ms restarts it after bus-off.
        ch = self.config.channel
        args = ["type", "can", "restart-ms", "100"]
        if self.config.bitrate:
            args += ["bitrate", str(self.config.bitrate)]
        args += ["listen-only", "on" if self.config.listen_only else "off"]
        for cmd in (["down"], args, ["up"]):
            subprocess.run(["ip", "link", "set", ch, *cmd], check=True, capture_output=True, timeout=5)

    def _fail(self, now: float, exc: Exception) -> None:
        self.last_error = f"{type(exc).__name__}: {exc}"
        self.faults.occur("bus", f"{self.config.interface} {self.config.channel}: {self.last_error}")
        self.close()
        self.state = "down"
        self._retry_at = now + self._delay
        self._delay = min(2 * self._delay, self.backoff_s[1])

    def close(self) -> None:
        if self._notifier is not None:
            self._notifier.stop(timeout=2)
            self._notifier = None
        if self.bus is not None:
            try:
                self.bus.shutdown()
            except Exception:  # a bus that already failed may fail to close too; it is dropped either way
                pass
            self.bus = None


def _require_link_up(channel: str) -> None:
    # Binding to a down interface succeeds (the error comes with the first receive), so look first.
    flags = Path(f"/sys/class/net/{channel}/flags")
    if flags.exists() and not int(flags.read_text(), 16) & 0x1:  # IFF_UP
        raise OSError(errno.ENETDOWN, f"interface {channel} is down")


def _enlarge_receive_buffer(bus: can.BusABC, size: int = 1 << 22) -> None:
    # A socketcan socket buffers ~200 frames by default: too few to ride out a slow disk or a rotation.
    sock = getattr(bus, "socket", None)
    if sock is not None:
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
        except OSError:
            pass


class FlowInput:
    """The serial flow meter, read in a thread; readings go to `sink`."""

    def __init__(self, config: LoggerConfig, sink: LogSink):
        calibration = Calibration(gain_kg_h_per_v=config.flow_gain, offset_kg_h=config.flow_offset)
        self.meter = SerialFlowMeter(config.serial_port, config.serial_baudrate, calibration)
        self._thread = threading.Thread(target=self._run, args=(sink,), name="flowmeter", daemon=True)
        self._thread.start()

    def _run(self, sink: LogSink) -> None:
        for reading in self.meter.readings():
            sink.on_flow_reading(reading)

    def close(self) -> None:
        self.meter.close()
        self._thread.join(timeout=2)


class Daemon:
    """Runs until `stop()` (SIGTERM/SIGINT in `fuelid log`), then closes the open file cleanly; with an
    `estimator`, runs it on the logged stream (the command line makes it from the identify settings)."""

    def __init__(self, config: LoggerConfig, estimator: Estimator | None = None):
        self.config = config
        self.faults = Faults()
        self.files = LogFiles(config.output_dir, self.faults)
        self.live = estimator
        self.uploads = None
        if config.upload_server:
            config.upload_token()  # no token at all: refuse to start (FuelidError); later it is re-read per upload
            self.uploads = UploadQueue(config.output_dir, config.upload_server, config.upload_token, None,
                                       delete_after_upload=config.delete_after_upload, prepare=self._name_truck,
                                       start=False)
            self.files.on_file_closed.append(self.uploads.enqueue)
        self.sink = LogSink(config, self.files, self.faults, self.live)
        self.bus: BusLink | None = None
        self.flow: FlowInput | None = None
        self._stop = threading.Event()
        self._vin_known = False  # for the upload queue: the files closed before the VIN were queued again
        self._started = time.time()
        self._rate = (time.monotonic(), 0)  # (when, frames) of the last status, for frames/s

    def stop(self) -> None:
        self._stop.set()

    def run(self) -> None:
        for line in self.files.recover_orphans():
            log.info("%s", line)
        if self.uploads:
            self.uploads.start()
        if self.live:
            self.live.prepare()  # compile or load the estimator's loop before frames arrive
        self.sink.open()
        self.bus = BusLink(self.config, self.sink, self.faults)
        if self.config.serial_port:
            self.flow = FlowInput(self.config, self.sink)
        next_status = 0.0
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                self.bus.poll(now)
                self.sink.tick()
                if now >= next_status:
                    self._check_disk()
                    self._check_serial()
                    self._check_identity()
                    self.write_status()
                    next_status = now + STATUS_S
                self._stop.wait(TICK_S)
        finally:
            self.bus.close()
            if self.flow:
                self.flow.close()
            self.sink.stop_writing()
            self._final_snapshot()
            if self.uploads:
                self.uploads.stop()  # what is still queued stays in the journal for the next start
            self.write_status(state="stopped")

    def _final_snapshot(self) -> None:
        if not self.live:
            return
        try:
            with self.sink.lock:
                if self.live.snapshot():
                    log.info("wrote %s", self.live.snapshot_path)
        except Exception as exc:  # a failed snapshot must not hide the clean close of the log files
            self.faults.occur("identify", f"model snapshot: {type(exc).__name__}: {exc}")

    def _check_disk(self) -> None:
        """Stop writing cleanly while free space is short; recover what a failed write left and resume once
        there is twice as much again. An orphan whose recovery the disk stopped is tried again once there is
        room for its copy beside that margin."""
        try:
            free = shutil.disk_usage(self.files.dir).free
        except OSError:
            return
        free_mb = free / 1e6
        if self.sink.part is not None and free_mb < self.config.min_free_mb:
            self.faults.occur("storage", f"{free_mb:.1f} MB free in {self.files.dir}: stopped writing")
            self.sink.stop_writing()
        elif self.sink.part is None and free_mb >= 2 * self.config.min_free_mb:
            self._recover_orphans(free)
            if self.sink.open():
                self.faults.clear("storage", f"{free_mb:.1f} MB free, writing again")
        elif self.files.postponed:
            self._recover_orphans(free)

    def _recover_orphans(self, free: int) -> None:
        room = free - 2 * self.config.min_free_mb * 1e6
        for line in self.files.recover_orphans(writing=self.sink.part, free_bytes=room):
            log.info("%s", line)

    def _check_identity(self) -> None:
        """Once the VIN is first seen, the files closed before it (refused by the VIN's token) go again."""
        if self.uploads and self.sink.unlabelled and self.sink.recorder.vin and not self._vin_known:
            self._vin_known = True
            self.uploads.retry(self.sink.unlabelled)

    def _name_truck(self, path: str) -> None:
        """Run by the upload queue just before it sends `path`: a file of this session closed before the VIN
        was seen gets the VIN as its truck (relabelled), once the VIN is known."""
        vin = self.sink.recorder.vin if self.sink.recorder else None
        if not vin or path not in self.sink.unlabelled:
            return
        try:
            relabel(path, {"truck": vin})  # an OSError (disk full) propagates: the queue tries again later
            log.info("relabelled %s with the truck's VIN %s", Path(path).name, vin)
        except OSError:
            raise
        except Exception as exc:  # a damaged file: sent as it is, for the server to judge
            self.faults.occur("relabel", f"{Path(path).name}: {type(exc).__name__}: {exc}")
        self.sink.unlabelled.discard(path)

    def _check_serial(self) -> None:
        if self.flow is None:
            return
        meter = self.flow.meter
        if meter.state == "disconnected":
            self.faults.occur("serial", f"{self.config.serial_port}: {meter.last_error}")
        elif meter.state == "connected":
            self.faults.clear("serial", f"{self.config.serial_port} connected")

    def status(self, state: str = "running") -> dict:
        rec = self.sink.recorder
        stats = rec.stats if rec else None
        frames = stats.frames if stats else 0
        now = time.monotonic()
        then, frames_then = self._rate
        self._rate = (now, frames)
        decoder = rec.decoder.counters() if rec else {}
        tp = rec.reassembler.counters() if rec else {}
        meter = self.flow.meter if self.flow else None
        bus = self.bus
        return {
            "state": state,
            "pid": os.getpid(),
            "updated": time.time(),
            "started": self._started,
            "uptime_s": round(time.time() - self._started, 1),
            "bus": {
                "interface": self.config.interface,
                "channel": self.config.channel,
                "state": bus.state if bus else "connecting",
                "connects": bus.connects if bus else 0,
                "last_error": bus.last_error if bus else None,
            },
            "frames": frames,
            "frames_per_s": round((frames - frames_then) / (now - then), 1) if now > then else 0.0,
            "drops": self.sink.dropped,
            "decode_errors": decoder.get("short_frames", 0) + tp.get("discarded", 0) + self.sink.record_errors,
            "error_frames": stats.error_frames if stats else 0,
            "file": str(self.sink.part) if self.sink.part else None,
            "files_closed": self.sink.closed_files,
            "serial": None if meter is None else {
                "port": self.config.serial_port,
                "state": meter.state,
                "lines": meter.counts.lines,
                "invalid": meter.counts.invalid,
                "disconnects": meter.counts.disconnects,
            },
            "vin": rec.vin if rec else None,
            "truck": (rec.vin if rec else None) or self.config.truck,
            "identify": self._identify_status(),
            "upload": self.uploads.status() if self.uploads else None,
            "faults": dict(self.faults.counts),
            "faults_active": dict(self.faults.active),
        }

    def _identify_status(self) -> dict | None:
        """The online estimator's status, with the errors it raised (counted by the recorder)."""
        if self.live is None:
            return None
        rec = self.sink.recorder
        status = self.live.status()
        return {"state": status.pop("state"), "errors": rec.errors if isinstance(rec, IdentifyingRecorder) else 0,
                **status}

    def write_status(self, state: str = "running") -> None:
        """Replace the status file atomically, so a reader never sees half of it."""
        path = self.config.status_file
        tmp = path.with_name(path.name + ".tmp")
        try:
            tmp.write_text(json.dumps(self.status(state), indent=1))
            os.replace(tmp, path)
        except OSError as exc:  # a full disk must not stop the logging of the bus
            self.faults.occur("status", f"writing {path}: {exc}")


def read_status(path: str | Path) -> dict:
    """The daemon's last status, with `age_s` since it was written."""
    status = json.loads(Path(path).read_text())
    status["age_s"] = round(time.time() - status["updated"], 1)
    return status
