"""`fuelid convert` end to end: recorded logs in, MCAP out, read back the way the identifier reads it."""
import gzip
import itertools
import json
import statistics
from pathlib import Path

import can
import pytest
from mcap.reader import NonSeekingReader, make_reader

from fuelid.cli import main
from fuelid.ident.dataset import build_dataset
from fuelid.logger.flowmeter import CaptureWriter
from fuelid.logger.mcap_log import read_messages, read_metadata
from fuelid.logger.readers import read_frames
from fuelid.logger.recorder import Recorder, open_writer


def convert(capsys, *args):
    code = main(["convert", *map(str, args), "--json"])
    out, err = capsys.readouterr()
    return code, (json.loads(out) if code == 0 else None), err


def values(path, topic, signal, sa=0x00):
    return [r[signal] for t, _, r in read_messages(path, [topic]) if r["sa"] == sa and r[signal] is not None]


def test_css_idle_truck_decodes_to_its_known_values(real_log, tmp_path, capsys):
    out = tmp_path / "idle.mcap"
    code, summary, _ = convert(capsys, real_log("css_j1939_truck_idle.MF4"), "-o", out)
    assert code == 0
    assert summary["frames"] == summary["inputs"][0]["frames"] > 50_000
    assert statistics.median(values(out, "/j1939/EEC1", "EngSpeed")) == pytest.approx(650, abs=15)
    fuel = values(out, "/j1939/LFE1", "EngFuelRate")
    assert 2.45 <= min(fuel) and max(fuel) <= 2.85
    assert statistics.median(values(out, "/j1939/ET1", "EngCoolantTemp")) == pytest.approx(71, abs=1.5)
    assert statistics.median(values(out, "/j1939/AMB", "AmbientAirTemp")) == pytest.approx(13.6, abs=0.3)
    assert summary["transport_protocol"]["completed"] > 0 and values(out, "/j1939/EC1", "EngReferenceTorque")


@pytest.mark.parametrize("name", ["systemscyber_truck_drive_normal.log", "systemscyber_truck_drive_tsc1.log"])
def test_systemscyber_drives_use_the_engines_own_source_address(real_log, tmp_path, capsys, name):
    out = tmp_path / "drive.mcap"
    code, summary, _ = convert(capsys, real_log(name), "-o", out)
    assert code == 0
    assert set(summary["messages"]["CCVS1"]) == {"0x00", "0x31"}  # two ECUs send it, kept apart
    ds = build_dataset([out])
    for signal in ("EEC1.EngSpeed", "EEC1.ActualEngPercentTorque", "LFE1.EngFuelRate", "CCVS1.WheelBasedVehicleSpeed"):
        assert ds.sources[signal] == 0x00, signal
    assert ds.sources["ETC2.TransCurrentGear"] == 0x03


def test_vin_from_bam_names_the_truck(real_log, tmp_path, capsys):
    out = tmp_path / "kw.mcap"
    code, summary, _ = convert(capsys, real_log("kenworth_free_rev.txt"), "-o", out)
    assert code == 0 and summary["truck"] == "2NKHHM6X2EM406412"
    assert read_metadata(out)["fuelid"]["truck"] == "2NKHHM6X2EM406412"


def test_flow_meter_capture_is_merged_by_time(tmp_path, capsys):
    log = tmp_path / "gas.log"
    with can.CanutilsLogWriter(log) as writer:
        for i in range(50):
            writer.on_message_received(can.Message(timestamp=100 + i * 0.02, arbitration_id=0x0CF00400, data=bytes([0, 125, 135, 0x40, 0x1F, 0, 0, 125])))
    capture = tmp_path / "gas.flow"
    with CaptureWriter(capture) as meter:
        meter.write(100.10, b"1.000,2.000")  # 25 kg/h
        meter.write(100.20, b"\xff\xfe garbage")
        meter.write(100.30, b"0.100")  # 1.25 kg/h: below the meter's 2.5 kg/h
    out = tmp_path / "gas.mcap"
    code, summary, _ = convert(capsys, log, "-o", out, "--flowmeter", capture)
    assert code == 0 and summary["flowmeter_readings"] == {"ok": 1, "invalid": 1, "below_range": 1}
    readings = [r for _, _, r in read_messages(out, ["/flowmeter"])]
    assert [r["flow_kg_h"] for r in readings] == [25.0, None, None]
    times = [t for _, t, _ in read_messages(out)]
    assert times == sorted(times)
    assert values(out, "/j1939/EEC1", "EngSpeed")[0] == 1000.0


@pytest.mark.parametrize("content", [b"", b"\x00\x01garbage\xff" * 100, b"not a can log\n"])
def test_unreadable_input_is_one_line_error(tmp_path, capsys, content):
    bad = tmp_path / "bad.log"
    bad.write_bytes(content)
    code, _, err = convert(capsys, bad, "-o", tmp_path / "out.mcap")
    assert code != 0 and err.count("\n") == 1 and err.startswith("fuelid convert: error:")


def test_missing_input_and_overwriting_input_are_refused(tmp_path, capsys):
    code, _, err = convert(capsys, tmp_path / "nope.log", "-o", tmp_path / "out.mcap")
    assert code == 1 and "no such file" in err
    log = tmp_path / "a.log"
    log.write_text("(1.0) can0 0CF00400#0000000000000000\n")
    code, _, err = convert(capsys, log, "-o", log)
    assert code == 1 and "overwrite" in err and log.read_text().startswith("(1.0)")


# -- each input's outcome (issue 18) --

def _candump(path, n=200, t0=1_700_000_000.0):
    path.write_text("".join(f"({t0 + i * 0.01:.6f}) can0 0CF00400#00{i % 250:02X}8700401F0000\n"
                            for i in range(n)))
    return path


def convert_text(capsys, *args):
    code = main(["convert", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def test_a_complete_input_says_so(tmp_path, capsys):
    code, summary, _ = convert(capsys, _candump(tmp_path / "a.log"), "-o", tmp_path / "a.mcap")
    assert code == 0 and summary["inputs"][0]["status"] == "complete" and summary["inputs"][0]["position"] is None
    code, out, _ = convert_text(capsys, tmp_path / "a.log", "-o", tmp_path / "b.mcap")
    assert "a.log [candump-L]: complete, 200 frames" in out


def test_a_truncated_input_says_where_and_keeps_what_was_read(tmp_path, capsys):
    log = _candump(tmp_path / "a.log")
    log.write_text(log.read_text()[:-9])  # the last line cut mid-data
    code, summary, _ = convert(capsys, log, "-o", tmp_path / "a.mcap")
    inp = summary["inputs"][0]
    assert code == 0 and (inp["status"], inp["position"], inp["frames"]) == ("truncated", "line 200", 199)
    code, out, _ = convert_text(capsys, log, "-o", tmp_path / "b.mcap")
    assert "truncated at line 200" in out


def test_damaged_input_exits_non_zero_unless_asked_to_keep_what_can_be_read(tmp_path, capsys):
    blf = tmp_path / "x.blf"
    with can.BLFWriter(blf) as w:
        for i in range(20_000):  # several containers
            w.on_message_received(can.Message(timestamp=1_700_000_000 + i * 0.01, arbitration_id=0x0CF00400,
                                              data=bytes([0, 125, 135, 0x40, 0x1F, 0, 0, i % 256])))
    blob = bytearray(blf.read_bytes())
    blob[len(blob) * 4 // 5] ^= 0x08
    blf.write_bytes(bytes(blob))
    out = tmp_path / "x.mcap"
    code, out_text, err = convert_text(capsys, blf, "-o", out)
    assert code == 1 and err.count("\n") == 1 and "damaged" in err and "--keep-damaged" in err
    assert "x.blf [blf]: damaged at byte" in out_text and not out.exists()
    code = main(["convert", str(blf), "-o", str(out), "--json", "--keep-damaged"])
    summary = json.loads(capsys.readouterr().out)
    assert code == 0 and summary["inputs"][0]["status"] == "damaged" and out.exists()
    assert 0 < summary["frames"] < 20_000 and len(list(read_messages(out, ["/can/raw"]))) == summary["frames"]


def test_a_foreign_file_starting_with_a_semicolon_is_refused(tmp_path, capsys):
    csv = tmp_path / "export.csv"
    csv.write_text(";Time;Channel;ID;DLC;Data\n0.001;1;18FEF100;8;FF 34 17 03 CC 00 FF FF\n")
    code, _, err = convert(capsys, csv, "-o", tmp_path / "out.mcap")
    assert code == 1 and "not a CAN recording" in err and err.count("\n") == 1
    assert not (tmp_path / "out.mcap").exists()


def test_an_out_of_range_line_is_skipped_not_an_abort(tmp_path, capsys):
    log = _candump(tmp_path / "a.log")
    lines = log.read_text().splitlines(keepends=True)
    log.write_text("".join(lines[:50] + ["(100000000000000000000.000000) can0 0CF00400#0000000000000000\n"]
                           + lines[50:]))
    code, summary, err = convert(capsys, log, "-o", tmp_path / "a.mcap")
    assert code == 0 and summary["inputs"][0]["skipped_lines"] == 1 and summary["frames"] == 200


def test_relative_time_recordings_follow_each_other_with_a_warning(tmp_path, capsys):
    a, b = _candump(tmp_path / "a.log", t0=5.0), _candump(tmp_path / "b.log", t0=3.0)
    out = tmp_path / "ab.mcap"
    code, summary, _ = convert(capsys, a, b, "-o", out)
    assert code == 0 and len(summary["warnings"]) == 1 and "b.log" in summary["warnings"][0]
    times = [t for _, t, _ in read_messages(out, ["/can/raw"])]
    assert times == sorted(times) and len(times) == 400


def test_a_recording_without_j1939_traffic_is_an_error_unless_raw_frames_are_asked_for(tmp_path, capsys):
    """An 11-bit OBD-II log decodes to nothing fuelid can use: a one-line error and no output, or with --raw-only
    an MCAP holding the frames in /can/raw."""
    log = tmp_path / "obd.log"
    log.write_text("".join(f"({1700000000 + i * 0.01:.6f}) can0 7E8#0441{i % 256:02X}0C1A000000\n"
                           for i in range(50)))
    out = tmp_path / "obd.mcap"
    assert main(["convert", str(log), "-o", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "no J1939/FMS message fuelid decodes in 50 frames (50 with 11-bit" in err
    assert not out.exists()
    assert main(["convert", str(log), "-o", str(out), "--raw-only", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 50 and summary["messages"] == {} and out.exists()


SAMPLE = Path(__file__).resolve().parents[1] / "replay_logs" / "sample_diesel_1min.log.gz"
OLD_FILES = Path(__file__).resolve().parent / "logger" / "data"


def _plain_reader_messages(path):
    """The messages as mcap's SeekingReader reads them, checked against its NonSeekingReader."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary().statistics.message_count > 0
        seeking = [(c.topic, m.log_time, json.loads(m.data)) for _, c, m in reader.iter_messages(log_time_order=False)]
    with open(path, "rb") as f:
        stream = [(c.topic, m.log_time, json.loads(m.data)) for _, c, m in NonSeekingReader(f).iter_messages()]
    assert stream == seeking
    return seeking


# convert_v0.1.0.mcap: fuelid 0.1.0's conversion (one-second chunks, message and chunk indexes);
# convert_chunk_index_only.mcap: the next one's (4 MB chunks, a chunk index without message indexes, which
# @mcap/core's indexed reader refuses), written by commit fb57282
@pytest.mark.parametrize("old_file", ["convert_v0.1.0.mcap", "convert_chunk_index_only.mcap"])
def test_a_file_converted_by_an_earlier_version_reads_as_todays_conversion(tmp_path, capsys, old_file):
    """Both hold the first 800 lines of the sample trip; today's conversion of the same lines holds the
    same messages."""
    old = OLD_FILES / old_file
    src = tmp_path / "first.log"
    with gzip.open(SAMPLE, "rt") as f:
        src.write_text("".join(itertools.islice(f, 800)))
    out = tmp_path / "today.mcap"
    code, summary, _ = convert(capsys, src, "-o", out)
    assert code == 0 and summary["frames"] == 800
    today = list(read_messages(out))
    assert len(today) == 1591 and list(read_messages(old)) == today
    assert _plain_reader_messages(old) == _plain_reader_messages(out) == today
    assert read_metadata(old)["fuelid"]["truck"] == read_metadata(out)["fuelid"]["truck"] == "YS2R4X20007105543"


def test_a_converted_file_is_less_than_half_a_live_log_of_the_same_frames(tmp_path, capsys):
    out, live = tmp_path / "converted.mcap", tmp_path / "live.mcap"
    code, summary, _ = convert(capsys, SAMPLE, "-o", out)
    assert code == 0
    writer = open_writer(live)
    recorder = Recorder(writer)
    for msg in read_frames(SAMPLE):
        recorder.on_message_received(msg)
    writer.close()
    assert list(read_messages(out)) == list(read_messages(live))
    assert _plain_reader_messages(out) == _plain_reader_messages(live)
    assert out.stat().st_size < 0.5 * live.stat().st_size


def test_meter_readings_go_where_a_merge_by_time_of_single_frames_puts_them(tmp_path, capsys):
    """Readings between frames, at a frame's time (after it) and after the last frame, among candump blocks."""
    import heapq
    from fuelid.logger.flowmeter import capture_readings

    log = _candump(tmp_path / "a.log", n=3000)
    capture = tmp_path / "m.flow"
    with CaptureWriter(capture) as meter:
        for k in range(0, 3100, 7):
            meter.write(1_700_000_000.0 + k * 0.01 + (0.003 if k % 2 else 0), b"%.3f" % (k % 10))
    out = tmp_path / "blocks.mcap"
    assert convert(capsys, log, "-o", out, "--flowmeter", capture)[0] == 0
    reference = tmp_path / "merged.mcap"
    writer = open_writer(reference, live=False)
    recorder = Recorder(writer)
    frames = ((m.timestamp, 0, m) for m in read_frames(log))
    for _, kind, item in heapq.merge(frames, ((r.t, 1, r) for r in capture_readings(capture)), key=lambda e: e[0]):
        recorder.on_message_received(item) if kind == 0 else recorder.on_flow_reading(item)
    writer.close()
    assert _plain_reader_messages(out) == _plain_reader_messages(reference)
    assert sum(topic == "/flowmeter" for topic, _, _ in _plain_reader_messages(out)) == len(range(0, 3100, 7))
