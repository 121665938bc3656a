"""Recorded-file readers: every format, malformed lines, truncated files, and real truck recordings."""
import gzip
import statistics
from collections import defaultdict

import can
import pytest

from fuelid.errors import FuelidError
from fuelid.logger.decode import Decoder
from fuelid.logger.readers import open_frames, parse_candump_l, parse_candump_ta, read_frames

FRAMES = [
    can.Message(timestamp=1700000000.0 + k * 0.01, arbitration_id=aid, is_extended_id=True,
                data=bytes.fromhex(data), channel=0)
    for k, (aid, data) in enumerate([(0x0CF00400, "219B9BDD2F000F9B"), (0x18FEF100, "FF341703CC00FFFF"),
                                     (0x18FEF131, "F7FFFFC7CCFFFFFF"), (0x18EA00F9, "ECFE00")] * 5)
]


def same_frames(read, sent=FRAMES):
    assert [(m.arbitration_id, m.is_extended_id, bytes(m.data)) for m in read] == \
        [(m.arbitration_id, m.is_extended_id, bytes(m.data)) for m in sent]
    assert [m.timestamp - read[0].timestamp for m in read] == \
        pytest.approx([m.timestamp - sent[0].timestamp for m in sent], abs=1e-5)


def candump_l(msgs):
    return "".join(f"({m.timestamp:.6f}) can0 {m.arbitration_id:08X}#{bytes(m.data).hex().upper()}\n" for m in msgs)


def candump_ta(msgs):
    return "".join(f" ({m.timestamp - msgs[0].timestamp:010.6f})  can0  {m.arbitration_id:08X}   [{m.dlc}]  "
                   f"{' '.join(f'{b:02X}' for b in m.data)}\n" for m in msgs)


def test_candump_line_parsers():
    m = parse_candump_l("(1543532003.571000) can1 18F00131#FFFFFF3F00FFFFFF")
    assert (m.timestamp, m.channel, m.arbitration_id, m.is_extended_id, m.dlc) == \
        (1543532003.571, "can1", 0x18F00131, True, 8)
    assert parse_candump_l("(1.0) can0 123#R").is_remote_frame
    assert not parse_candump_l("(1.0) can0 123#").is_extended_id
    assert parse_candump_l("(1.0) can0 20000080#0000000000000000").is_error_frame
    m = parse_candump_ta(" (000.005001)  can0  18FEDF00   [8]  8A A0 28 7D 7D FF FF F5")
    assert (m.timestamp, m.arbitration_id, bytes(m.data)) == (0.005001, 0x18FEDF00, bytes.fromhex("8AA0287D7DFFFFF5"))
    assert parse_candump_ta(" (000.040000)  can0  18EA00F9   [3]  EC FE 00").dlc == 3
    for bad in ["(1543532003.737843) can1 18FEBF", "(1.0) can0 18FEF100#FFF", "garbage", "(1.0) can0 1#00",
                "(1.0) can0 18FEF100#" + "00" * 9]:
        assert parse_candump_l(bad) is None, bad
    for bad in [" (000.1)  can0  0CF00331   [8] ", " (000.1)  can0  0CF00331   [8]  FF FF",
                " (000.1)  can0  0CF00331   [2]  FF FF FF", " (000.1)  can0  0CF00331   [8]  FF F"]:
        assert parse_candump_ta(bad) is None, bad


@pytest.mark.parametrize("fmt, write", [("candump-L", candump_l), ("candump-ta", candump_ta)])
def test_candump_text_with_malformed_lines(tmp_path, fmt, write):
    lines = write(FRAMES).splitlines(keepends=True)
    text = "".join(lines[:10]) + "(1543532003.737843) can1 18FEBF\n\n" + "".join(lines[10:]) + "@@@\n"
    path = tmp_path / "drive.log"
    path.write_text(text)
    source = open_frames(path)
    read = list(source)
    assert source.format == fmt
    same_frames(read)
    assert (source.frames, source.skipped, source.truncated) == (len(FRAMES), 2, False)


@pytest.mark.parametrize("write", [candump_l, candump_ta])
def test_gzip_and_truncated_gzip(tmp_path, write):
    many = FRAMES * 200
    blob = gzip.compress(write(many).encode())
    (tmp_path / "a.log.gz").write_bytes(blob)
    same_frames(list(read_frames(tmp_path / "a.log.gz")), many)
    (tmp_path / "cut.log.gz").write_bytes(blob[: len(blob) // 2])
    source = open_frames(tmp_path / "cut.log.gz")
    read = list(source)
    assert 0 < len(read) < len(many) and source.truncated and source.error
    same_frames(read[:-1], many[: len(read) - 1])  # the last line may itself be cut


def write_with(tmp_path, name, writer_cls):
    path = tmp_path / name
    with writer_cls(path) as w:
        for m in FRAMES:
            w.on_message_received(m)
    return path


@pytest.mark.parametrize("name, writer, fmt", [("x.asc", can.ASCWriter, "asc"), ("x.trc", can.TRCWriter, "trc"),
                                               ("x.blf", can.BLFWriter, "blf")])
def test_python_can_formats(tmp_path, name, writer, fmt):
    path = write_with(tmp_path, name, writer)
    source = open_frames(path)
    assert source.format == fmt
    same_frames(list(source))
    renamed = path.rename(tmp_path / "no_suffix.bin")  # recognised by content, not by name
    assert open_frames(renamed).format == fmt
    zipped = tmp_path / (name + ".gz")
    zipped.write_bytes(gzip.compress(renamed.read_bytes()))
    same_frames(list(read_frames(zipped)))


@pytest.mark.parametrize("name, writer, bad", [
    ("x.asc", can.ASCWriter, "   1.000000 1  18FEF100x       Rx   d 8 ZZ 34 17 03 CC 00 FF FF\n"),
    ("x.trc", can.TRCWriter, "     99         5.000 DT  1 18FEF100 Rx -  8    ZZ 34 17 03 CC 00 FF FF\n"),
])
def test_malformed_line_in_asc_and_trc_is_skipped_and_counted(tmp_path, name, writer, bad):
    path = write_with(tmp_path, name, writer)
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(lines[:-3] + [bad] + lines[-3:]))
    source = open_frames(path)
    same_frames(list(source))
    assert source.skipped == 1


def test_truncated_blf_keeps_what_was_read(tmp_path):
    path = tmp_path / "x.blf"
    with can.BLFWriter(path) as w:
        for m in FRAMES * 400:
            w.on_message_received(m)
    blob = path.read_bytes()
    for cut in (200, len(blob) // 2, len(blob) - 7):
        (tmp_path / "cut.blf").write_bytes(blob[:cut])
        source = open_frames(tmp_path / "cut.blf")
        read = list(source)  # never raises
        assert len(read) <= len(FRAMES) * 400
        if read:
            same_frames(read, (FRAMES * 400)[: len(read)])


def test_unknown_format_and_missing_file_are_one_line_errors(tmp_path):
    (tmp_path / "notes.txt").write_text("hello\nworld\n")
    (tmp_path / "empty.log").write_text("")
    (tmp_path / "random.bin").write_bytes(bytes(range(256)) * 10)
    for name in ("notes.txt", "empty.log", "random.bin", "missing.log"):
        with pytest.raises(FuelidError) as e:
            open_frames(tmp_path / name)
        assert "\n" not in str(e.value)
    with pytest.raises(FuelidError):
        open_frames(tmp_path)


# -- real truck recordings (skipped when ../shared/real_logs is absent) --

def decoded_by_name(frames):
    decoder, out = Decoder(), defaultdict(list)
    for msg in frames:
        d = decoder.decode(msg)
        if d is not None:
            out[d.name, d.sa].append(d)
    return out


def series(decoded, name, signal, sa=0x00):
    return [v for d in decoded[name, sa] if (v := d.values[signal]) is not None]


def test_css_idle_truck_mf4(real_log):
    source = open_frames(real_log("css_j1939_truck_idle.MF4"))
    assert source.format == "mf4"
    decoded = decoded_by_name(source)
    rpm = series(decoded, "EEC1", "EngSpeed")
    assert len(rpm) > 10_000 and statistics.median(rpm) == pytest.approx(650, abs=15)
    fuel = series(decoded, "LFE1", "EngFuelRate")
    assert len(fuel) > 1000 and all(2.45 <= f <= 2.85 for f in fuel)
    assert statistics.median(series(decoded, "ET1", "EngCoolantTemp")) == pytest.approx(71, abs=1.5)
    assert statistics.median(series(decoded, "AMB", "AmbientAirTemp")) == pytest.approx(13.6, abs=0.3)
    assert statistics.median(series(decoded, "EEC1", "ActualEngPercentTorque")) == pytest.approx(7, abs=2)
    assert statistics.median(series(decoded, "EEC3", "NominalFrictionPercentTorque")) == pytest.approx(5, abs=2)


@pytest.mark.parametrize("name", ["systemscyber_truck_drive_normal.log", "systemscyber_truck_drive_tsc1.log"])
def test_systemscyber_drives_keep_ccvs1_sources_apart(real_log, name):
    source = open_frames(real_log(name))
    assert source.format == "candump-ta"
    decoded = decoded_by_name(source)
    assert source.skipped == 0
    engine = series(decoded, "CCVS1", "WheelBasedVehicleSpeed", sa=0x00)
    assert len(engine) > 100 and 15 < max(engine) < 60
    # the cab controller (0x31) sends CCVS1 too, without a speed: its nulls stay its own
    cab = decoded["CCVS1", 0x31]
    assert cab and all(d.values["WheelBasedVehicleSpeed"] is None for d in cab)
    assert all(d.sa == 0x00 for d in decoded["CCVS1", 0x00])
    assert max(series(decoded, "EEC1", "EngSpeed")) > 1000


def test_pcan_trc_and_candump_l_read(real_log):
    trc = open_frames(real_log("paccar_mx_pcanview.trc"))
    assert trc.format == "trc"
    decoded = decoded_by_name(trc)
    assert trc.frames > 20_000 and len(decoded["EEC1", 0x00]) > 1000
    log = open_frames(real_log("kenworth_candump_short.log"))
    assert log.format == "candump-L"
    assert len(list(log)) == 103 and log.skipped == 0


def test_kenworth_free_rev_text(real_log):
    decoded = decoded_by_name(read_frames(real_log("kenworth_free_rev.txt")))
    assert max(series(decoded, "EEC1", "EngSpeed")) == pytest.approx(2061, abs=30)
