"""The flow-meter path: line parser, stream splitting, capture files and the pyserial reader."""
import math
import os
import threading
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fuelid.logger.flowmeter import (
    MAX_LINE,
    Calibration,
    CaptureWriter,
    LineSplitter,
    SerialFlowMeter,
    capture_readings,
    escape,
    parse_line,
    read_capture,
    unescape,
)
from fuelid.logger.mcap_log import FLOWMETER_SCHEMA

CAL = Calibration()


@pytest.mark.parametrize(
    "line, status, flow",
    [
        (b"0.2", "ok", 2.5),  # 2.5 kg/h: the meter's lowest measurable flow
        (b"0.19", "below_range", None),
        (b"0", "below_range", None),
        (b"-0.5", "below_range", None),
        (b"10", "ok", 125.0),
        (b"10.001", "over_range", None),
        (b"3.217", "ok", 12.5 * 3.217),
        (b"12.250,3.217", "ok", 12.5 * 3.217),
        (b" 12.250 , 3.217 ", "ok", 12.5 * 3.217),
    ],
)
def test_status_boundaries(line, status, flow):
    r = parse_line(line, 5.0, CAL)
    assert r.status == status
    assert r.volts == float(line.split(b",")[-1])
    assert r.flow_kg_h == pytest.approx(flow) if flow is not None else r.flow_kg_h is None


def test_calibration_offset_and_range():
    cal = Calibration(gain_kg_h_per_v=10.0, offset_kg_h=-5.0, min_kg_h=0.0, max_kg_h=80.0, max_volts=9.0)
    assert parse_line(b"1.0", 0, cal).flow_kg_h == pytest.approx(5.0)
    assert parse_line(b"0.4", 0, cal).status == "below_range"  # -1 kg/h
    assert parse_line(b"8.6", 0, cal).status == "over_range"  # 81 kg/h, under max_volts
    assert parse_line(b"8.5", 0, cal).status == "ok"  # 80 kg/h exactly
    assert parse_line(b"10.5", 0, Calibration(max_kg_h=1e3)).status == "over_range"  # 131 kg/h but > 10 V



@pytest.mark.parametrize(
    "line",
    [b"", b"abc", b"3.2.1", b"1,2,3", b"nan", b"inf", b"1e3", b"3,", b",3", b"3 2", b"\x003.2", b"3.2\xff",
     b"\r", b"0x10", b"1" * (MAX_LINE + 1)],
)
def test_invalid_lines_carry_no_number(line):
    r = parse_line(line, 1.0, CAL)
    assert (r.status, r.device_t, r.volts, r.flow_kg_h) == ("invalid", None, None, None)
    assert unescape(r.raw) == line


def test_record_matches_schema():
    record = parse_line(b"1.5,3.0", 100.0, CAL).to_record()
    assert set(record) == set(FLOWMETER_SCHEMA["properties"]) == set(FLOWMETER_SCHEMA["required"])
    assert record == {"t": 100.0, "device_t": 1.5, "volts": 3.0, "flow_kg_h": 37.5, "status": "ok", "raw": "1.5,3.0"}


@given(st.binary(max_size=300))
def test_parser_never_raises_and_numbers_come_only_from_numbers(raw):
    r = parse_line(raw, 0.0, CAL)
    assert unescape(r.raw) == raw
    if r.status == "invalid":
        assert r.volts is None and r.flow_kg_h is None and r.device_t is None
    else:
        assert len(raw) <= MAX_LINE and set(raw) <= set(b"0123456789.,+- \t")
        assert r.volts == float(raw.split(b",")[-1]) and math.isfinite(r.volts)


@given(st.floats(-1e6, 1e6), st.floats(-20, 20))
def test_parser_reads_what_a_logger_prints(device_t, volts):
    r = parse_line(b"%.3f,%.4f" % (device_t, volts), 0.0, CAL)
    assert r.device_t == float("%.3f" % device_t) and r.volts == float("%.4f" % volts)
    assert r.status != "invalid"


# Streams made of realistic lines, garbage and over-long lines, with \n or \r\n endings.
_lines = st.one_of(
    st.builds(lambda t, v: b"%.3f,%.3f" % (t, v), st.floats(0, 1e5), st.floats(-1, 12)),
    st.binary(max_size=40).map(lambda b: b.replace(b"\n", b"")),
    st.integers(MAX_LINE - 2, 2 * MAX_LINE).map(lambda n: b"7" * n),
)
_streams = st.lists(st.tuples(_lines, st.sampled_from([b"\n", b"\r\n"])), max_size=12).map(
    lambda items: b"".join(line + end for line, end in items)
)


def _split(data: bytes, cuts) -> list[bytes]:
    splitter, lines, last = LineSplitter(), [], 0
    for cut in sorted(c % (len(data) + 1) for c in cuts) + [len(data)]:
        lines += splitter.feed(data[last:cut])
        last = cut
        assert len(splitter._buffer) <= MAX_LINE + 1  # memory stays bounded
    return lines


@given(_streams, st.lists(st.integers(0, 10_000), max_size=20), st.binary(max_size=50))
def test_splitting_anywhere_gives_the_same_lines(data, cuts, tail):
    data += tail  # a partial last line stays pending
    whole = _split(data, [])
    assert _split(data, cuts) == whole
    assert _split(data, range(len(data))) == whole  # byte by byte, as a slow serial port delivers


@given(st.integers(MAX_LINE + 1, 3 * MAX_LINE), st.sampled_from([b"\n", b"\r\n"]))
def test_over_long_line_is_cut_and_invalid(n, end):
    splitter = LineSplitter()
    lines = splitter.feed(b"9" * n + end + b"3.0\n")
    assert [parse_line(line, 0, CAL).status for line in lines] == ["invalid", "ok"]
    assert len(lines[0]) == MAX_LINE + 1
    assert splitter.dropped_bytes == n - MAX_LINE - 1


def test_lines_keep_everything_but_the_terminator():
    assert LineSplitter().feed(b"1.0\r\n\r\n\n2.0\r\r\nab") == [b"1.0", b"", b"", b"2.0\r"]


@settings(max_examples=50)
@given(st.lists(st.tuples(st.floats(0, 2e9), st.binary(max_size=60)), max_size=30), st.booleans())
def test_capture_round_trip_of_arbitrary_bytes(tmp_path_factory, items, gz):
    path = tmp_path_factory.mktemp("cap") / ("c.flow.gz" if gz else "c.flow")
    with CaptureWriter(path) as w:
        w.comment("connected /dev/ttyUSB0\nwith a newline")
        for t, line in items:
            w.write(t, line)
    back = read_capture(path)
    got = list(back)
    assert [line for _, line in got] == [line for _, line in items]
    assert all(abs(a - t) <= 1e-6 for (a, _), (t, _) in zip(got, items))
    assert back.skipped == 0 and not back.truncated


def test_capture_format_is_the_documented_one(tmp_path):
    path = tmp_path / "c.flow"
    with CaptureWriter(path) as w:
        w.write(1700000000.123456, b"12.250,3.217")
        w.write(1700000000.2, b"\x00\\\xff")
    assert path.read_bytes() == (
        b"# fuelid flowmeter capture v1\n(1700000000.123456) 12.250,3.217\n(1700000000.200000) \\x00\\x5c\\xff\n"
    )


def test_malformed_capture_lines_are_skipped_and_counted(tmp_path):
    path = tmp_path / "c.flow"
    path.write_bytes(b"# comment\n(1.5) 3.0\n1.5 3.0\n(x) 3.0\n(2.0) bad\\q\n(2.5)3.0\n(3.0) \xff\n(4.0) 4.0\n(5.0) 5.")
    reader = read_capture(path)
    assert list(reader) == [(1.5, b"3.0"), (4.0, b"4.0")]
    assert reader.skipped == 6  # including the last line, cut before its newline


def test_truncated_gzip_capture_ends_cleanly(tmp_path):
    path = tmp_path / "c.flow.gz"
    lines = [b"%d.0,%.3f" % (i, i % 10 / 3) for i in range(5000)]
    with CaptureWriter(path) as w:
        for i, line in enumerate(lines):
            w.write(1e9 + i, line)
    data = path.read_bytes()
    for cut in (10, 30, len(data) // 3, len(data) // 2, len(data) - 9):
        cut_path = tmp_path / "cut.flow.gz"
        cut_path.write_bytes(data[:cut])
        reader = read_capture(cut_path)
        got = [line for _, line in reader]
        assert got == lines[: len(got)]
        assert reader.truncated
    cut_path.write_bytes(data[:-1])
    assert len(list(read_capture(cut_path))) == len(lines)


def test_capture_readings_replay(tmp_path):
    path = tmp_path / "c.flow"
    with CaptureWriter(path) as w:
        w.write(1.0, b"1.0,2.0")
        w.write(2.0, b"junk")
    assert [r.status for r in capture_readings(path)] == ["ok", "invalid"]


class _Pty:
    """A pseudo-terminal standing in for the data logger, reached through a stable link (like udev's
    /dev/serial/by-id/...), so unplugging and plugging back in gives the reader the same port name."""

    def __init__(self, link):
        self.link = link
        self.master = None

    def plug(self):
        self.master, slave = os.openpty()
        name = os.ttyname(slave)
        os.close(slave)
        if os.path.lexists(self.link):
            os.remove(self.link)
        os.symlink(name, self.link)

    def unplug(self):
        os.close(self.master)
        os.remove(self.link)

    def send(self, data):
        os.write(self.master, data)


def _wait_for(condition, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_serial_reader_survives_unplug_and_reconnects(tmp_path):
    device = _Pty(str(tmp_path / "ttyFLOW"))
    device.plug()
    capture = CaptureWriter(tmp_path / "meter.flow", flush_s=0)
    meter = SerialFlowMeter(device.link, capture=capture, read_timeout_s=0.02, reconnect_s=(0.02, 0.1))
    readings = []
    thread = threading.Thread(target=lambda: readings.extend(meter.readings()))
    thread.start()
    try:
        _wait_for(lambda: meter.state == "connected")
        device.send(b"217\r\n1.0,3.2\r\n2.0,ab\n3.0,0.1\n4.0,11")
        _wait_for(lambda: meter.counts.lines == 4)
        device.send(b".0\n5.0,4.")  # the unplug cuts "5.0,4."
        _wait_for(lambda: meter.counts.lines == 5)
        device.unplug()
        _wait_for(lambda: meter.state == "disconnected")
        time.sleep(0.1)  # a few failed re-opens while the device is away
        device.plug()
        _wait_for(lambda: meter.state == "connected")
        device.send(b"\n6.0,8.0\n")
        _wait_for(lambda: meter.counts.lines == 8)
    finally:
        meter.close()
        thread.join(5)
        capture.close()
    assert not thread.is_alive() and meter.state == "closed"
    assert [(r.raw, r.status) for r in readings] == [
        ("217", "invalid"),  # first line after opening: may be the tail of a reading
        ("1.0,3.2", "ok"),
        ("2.0,ab", "invalid"),
        ("3.0,0.1", "below_range"),
        ("4.0,11.0", "over_range"),
        ("5.0,4.", "invalid"),  # cut by the unplug
        ("", "invalid"),  # first line after the reconnect
        ("6.0,8.0", "ok"),
    ]
    assert readings[1].flow_kg_h == pytest.approx(40.0) and readings[1].device_t == 1.0
    c = meter.counts
    assert (c.lines, c.ok, c.invalid, c.below_range, c.over_range, c.partial) == (8, 2, 4, 1, 1, 3)
    assert (c.disconnects, c.reconnects) == (1, 1)
    # The capture replays exactly the trusted lines; the untrusted ones are comments.
    assert [r.raw for r in capture_readings(tmp_path / "meter.flow")] == [
        "1.0,3.2", "2.0,ab", "3.0,0.1", "4.0,11.0", "6.0,8.0"
    ]


def test_serial_reader_waits_for_a_device_that_is_not_there_yet(tmp_path):
    meter = SerialFlowMeter(str(tmp_path / "nothing"), read_timeout_s=0.02, reconnect_s=(0.01, 0.05))
    thread = threading.Thread(target=lambda: list(meter.readings()))
    thread.start()
    _wait_for(lambda: meter.last_error is not None)
    meter.close()
    thread.join(5)
    assert meter.counts.disconnects == meter.counts.reconnects == 0


def test_escape_is_printable_and_reversible():
    data = bytes(range(256))
    text = escape(data)
    assert text.isascii() and text.isprintable()
    assert unescape(text) == data
    with pytest.raises(ValueError):
        unescape("a\\b")
