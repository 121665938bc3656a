"""Replay: every format onto a python-can bus, the absolute schedule and --speed, the flow meter on a pty."""
import json
import threading

import can
import pytest

from fuelid.cli import main
from fuelid.logger.flowmeter import SerialFlowMeter, read_capture
from fuelid.logger.recorder import Recorder, open_writer
from fuelid.logger.replay import PtyMeter, recorded_frames, replay
from tests.logger import traffic


class FakeClock:
    """A clock whose sleep advances time exactly (plus `oversleep_s`), so schedules can be checked exactly."""

    def __init__(self, oversleep_s=0.0):
        self.now = 100.0
        self.oversleep_s = oversleep_s

    def __call__(self):
        return self.now

    def sleep(self, s):
        self.now += s + self.oversleep_s


class Sent:
    def __init__(self, clock):
        self.clock, self.frames = clock, []

    def send(self, msg):
        self.frames.append((self.clock(), msg))


def _key(msg):
    return msg.arbitration_id, bytes(msg.data), msg.is_extended_id


@pytest.fixture
def drive(tmp_path):
    path = tmp_path / "drive.log"
    return path, traffic.write_candump(path, 2.0)


def _write(writer_cls, path, msgs):
    with writer_cls(str(path)) as w:
        for m in msgs:
            w.on_message_received(m)


@pytest.mark.parametrize("fmt", ["log", "asc", "blf", "trc", "mcap"])
def test_every_format_replays_its_frames(tmp_path, drive, fmt):
    _, msgs = drive
    path = tmp_path / f"drive.{fmt}"
    if fmt == "log":
        path = drive[0]
    elif fmt == "mcap":
        writer = open_writer(path)
        recorder = Recorder(writer)
        for m in msgs:
            recorder.on_message_received(m)
        writer.close()
    else:
        _write({"asc": can.ASCWriter, "blf": can.BLFWriter, "trc": can.TRCWriter}[fmt], path, msgs)
    assert [_key(m) for m in recorded_frames(path)] == [_key(m) for m in msgs]
    clock = FakeClock()
    bus = Sent(clock)
    stats = replay([path], bus, clock=clock, sleep=clock.sleep)
    assert stats.frames == len(msgs) and stats.send_errors == 0
    assert [_key(m) for _, m in bus.frames] == [_key(m) for m in msgs]


@pytest.mark.parametrize("speed", [1.0, 4.0, 0.5])
def test_original_timing_scaled_by_speed(drive, speed):
    path, msgs = drive
    clock = FakeClock()
    bus = Sent(clock)
    replay([path], bus, speed=speed, clock=clock, sleep=clock.sleep)
    start, t0 = bus.frames[0][0], msgs[0].timestamp
    for (sent_at, _), m in zip(bus.frames, msgs):
        assert sent_at - start == pytest.approx((m.timestamp - t0) / speed, abs=1e-5)


def test_lateness_does_not_accumulate(drive):
    path, msgs = drive
    clock = FakeClock(oversleep_s=0.002)  # every sleep 2 ms too long, as an OS would
    bus = Sent(clock)
    stats = replay([path], bus, clock=clock, sleep=clock.sleep)
    # against an absolute schedule each frame is at most one oversleep late, however many came before
    assert stats.lateness.max_s == pytest.approx(0.002)
    assert bus.frames[-1][0] - bus.frames[0][0] == pytest.approx(msgs[-1].timestamp - msgs[0].timestamp, abs=0.0021)


def test_files_play_back_to_back_and_loop(drive):
    path, msgs = drive
    clock = FakeClock()
    bus = Sent(clock)
    span = msgs[-1].timestamp - msgs[0].timestamp
    stats = replay([path, path], bus, loop=True, clock=clock, sleep=clock.sleep,
                   should_stop=lambda: len(bus.frames) >= 6 * len(msgs))
    assert stats.passes == 3 and stats.frames == 6 * len(msgs)
    assert bus.frames[-1][0] - bus.frames[0][0] == pytest.approx(6 * span, abs=1e-6)


def test_replay_command_on_virtual_bus(drive, capsys):
    path, msgs = drive
    rx = can.Bus(interface="virtual", channel="replay-test")
    try:
        assert main(["replay", str(path), "--interface", "virtual", "--channel", "replay-test", "--speed", "20", "--json"]) == 0
        report = json.loads(capsys.readouterr().out)
        received = [rx.recv(0) for _ in msgs]
    finally:
        rx.shutdown()
    assert report["frames"] == len(msgs) and report["late_max_s"] >= 0 and "late_mean_s" in report
    assert [_key(m) for m in received] == [_key(m) for m in msgs]


def test_replay_command_errors_are_one_line(tmp_path, capsys):
    assert main(["replay", str(tmp_path / "missing.log"), "--interface", "virtual", "--channel", "x"]) == 1
    assert "no such file" in capsys.readouterr().err
    assert main(["replay"]) == 1


def test_flowmeter_capture_through_a_pty(tmp_path):
    capture = tmp_path / "meter.flow"
    traffic.write_capture(capture, 1.0)
    lines = [line for _, line in read_capture(capture)]
    meter = PtyMeter(tmp_path / "meter.pty")
    reader = SerialFlowMeter(str(tmp_path / "meter.pty"))
    got = []

    def read():
        for reading in reader.readings():
            got.append(reading)

    thread = threading.Thread(target=read)
    thread.start()
    try:
        while reader.state != "connected":
            threading.Event().wait(0.01)
        stats = replay(capture=capture, meter=meter, speed=5)
        threading.Event().wait(0.3)
    finally:
        reader.close()
        thread.join()
        meter.close()
    assert stats.flow_lines == len(lines) and stats.flow_lines_dropped == 0
    # the first line after opening may be a fragment, so the reader reports it invalid (partial)
    assert len(got) == len(lines)
    assert [r.volts for r in got[1:] if r.status == "ok"] == [
        float(line.split(b",")[1]) for line in lines[1:] if b"garbage" not in line]
    assert not (tmp_path / "meter.pty").exists()
