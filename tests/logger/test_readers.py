"""Recorded-file readers: every format, malformed lines, truncated files, and real truck recordings."""
import gzip
import statistics
import tempfile
import zlib
from collections import defaultdict
from pathlib import Path

import can
import pytest
from hypothesis import given, settings, strategies as st

from fuelid.errors import FuelidError
from fuelid.logger.decode import Decoder
from fuelid.logger.readers import FORMATS, in_range, one_timeline, open_frames, parse_candump_l, parse_candump_ta, read_frames

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


# -- faults: what a damaged, cut or foreign file gives (issue 18) --

def test_formats_are_a_table_of_sniff_and_read():
    assert list(FORMATS) == ["blf", "mf4", "trc", "asc", "candump-L", "candump-ta"]
    assert all(callable(f.sniff) and callable(f.read) for f in FORMATS.values())


@pytest.mark.parametrize("content", [
    ";Time;Channel;ID;DLC;Data\n0.001;1;18FEF100;8;FF 34 17 03 CC 00 FF FF\n",  # a Vector CSV export
    "; just a comment\n; another\n",
    "hello\n(1700000000.000000) can0 0CF00400#219B9BDD2F000F9B\n",  # candump only further down
])
def test_sniffing_needs_the_formats_real_header(tmp_path, content):
    path = tmp_path / "export.csv"
    path.write_text(content)
    with pytest.raises(FuelidError, match="not a CAN recording fuelid reads") as e:
        open_frames(path)
    assert "\n" not in str(e.value)


def test_trc_v1_0_without_a_version_line_is_still_trc(tmp_path):
    path = tmp_path / "old.trc"
    path.write_text(";##########\n;   Start time: 14.10.2021\n;##########\n"
                    "     1)      1841  0CF00400  8  21 9B 9B DD 2F 00 0F 9B\n")
    source = open_frames(path)
    assert source.format == "trc" and [m.arbitration_id for m in source] == [0x0CF00400]


@pytest.mark.parametrize("bad", [
    "(100000000000000000000.000000) can0 0CF00400#219B9BDD2F000F9B\n",  # time beyond MCAP's range
])
def test_out_of_range_candump_values_are_malformed_lines(tmp_path, bad):
    lines = candump_l(FRAMES).splitlines(keepends=True)
    path = tmp_path / "x.log"
    path.write_text("".join(lines[:5] + [bad] + lines[5:]))
    source = open_frames(path)
    same_frames(list(source))
    assert (source.skipped, source.status) == (1, "complete")


@pytest.mark.parametrize("bad", [
    "     99           nan DT  1 18FEF100 Rx -  8    FF 34 17 03 CC 00 FF FF\n",
    "     99         5.000 DT  1 18FEF1000000000000 Rx -  8    FF 34 17 03 CC 00 FF FF\n",
    "     99          1e30 DT  1 18FEF100 Rx -  8    FF 34 17 03 CC 00 FF FF\n",
    "     99         5.000 DT  1 7FF0 Rx -  8    FF 34 17 03 CC 00 FF FF\n",  # 11-bit id too wide
])
def test_out_of_range_trc_values_are_malformed_lines(tmp_path, bad):
    path = write_with(tmp_path, "x.trc", can.TRCWriter)
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(lines[:-3] + [bad] + lines[-3:]))
    source = open_frames(path)
    same_frames(list(source))
    assert (source.skipped, source.status) == (1, "complete")


def test_a_candump_line_cut_mid_data_is_malformed_not_a_shorter_frame(tmp_path):
    text = candump_l(FRAMES)
    path = tmp_path / "cut.log"
    path.write_text(text[: text.rindex("#") + 5])  # the last line ends 2 data bytes in
    source = open_frames(path)
    read = list(source)
    same_frames(read, FRAMES[:-1])
    assert (source.status, source.position, source.skipped) == ("truncated", f"line {len(FRAMES)}", 1)


def test_trc_error_frames_are_kept_as_error_frames(tmp_path):
    path = write_with(tmp_path, "x.trc", can.TRCWriter)
    lines = path.read_text().splitlines(keepends=True)
    header = sum(ln.startswith(";") for ln in lines)
    er = "     21      5570.544 ER          Rx    04 01 09 01 00\n"
    path.write_text("".join(lines + [er]))
    read = list(open_frames(path))
    same_frames(read[:-1])
    assert read[-1].is_error_frame and bytes(read[-1].data) == bytes.fromhex("0401090100")
    assert read[-1].timestamp - read[0].timestamp == pytest.approx(5.570544, abs=1e-3) and header  # offset [ms]


def test_gzipped_mf4_reads_like_the_plain_file(real_log, tmp_path):
    plain = real_log("css_j1939_truck_idle.MF4")
    zipped = tmp_path / "idle.MF4.gz"
    zipped.write_bytes(gzip.compress(plain.read_bytes(), compresslevel=1))
    a, b = open_frames(plain), open_frames(zipped)
    assert b.format == "mf4"
    first = [(m.timestamp, m.arbitration_id, bytes(m.data)) for m in a]
    assert [(m.timestamp, m.arbitration_id, bytes(m.data)) for m in b] == first
    assert a.status == b.status == "complete" and b.frames == len(first) > 50_000


def _gzip_with_flipped_data(raw: bytes) -> bytes:
    """A gzip of `raw` whose deflate data still decodes, to other bytes: only the CRC at the end tells."""
    for pos in range(len(gzip.compress(raw)) // 2, len(gzip.compress(raw)) - 8):
        blob = bytearray(gzip.compress(raw, mtime=0))
        blob[pos] ^= 0x01
        try:
            gzip.decompress(bytes(blob))
        except gzip.BadGzipFile:
            return bytes(blob)
        except (zlib.error, EOFError):
            continue
    raise AssertionError("no flip that only the CRC catches")


def test_a_gzip_that_fails_its_crc_is_damaged(tmp_path):
    path = tmp_path / "x.log.gz"
    path.write_bytes(_gzip_with_flipped_data(candump_l(FRAMES * 500).encode()))  # more than the sniffed head
    source = open_frames(path)
    list(source)
    assert source.status == "damaged" and "CRC" in source.error


@pytest.mark.parametrize("where", [0.3, 0.5, 0.8])
def test_a_flipped_bit_in_a_blf_is_damage_not_a_clean_end(tmp_path, where):
    path = tmp_path / "x.blf"
    with can.BLFWriter(path) as w:
        for m in FRAMES * 400:
            w.on_message_received(m)
    blob = bytearray(path.read_bytes())
    blob[int(len(blob) * where)] ^= 0x10
    path.write_bytes(bytes(blob))
    source = open_frames(path)
    read = list(source)
    assert len(read) < len(FRAMES) * 400 and source.status == "damaged" and source.position.startswith("byte ")


def test_a_blf_whose_header_size_is_flipped_is_damaged_not_empty(tmp_path):
    path = tmp_path / "x.blf"
    with can.BLFWriter(path) as w:
        for m in FRAMES * 400:
            w.on_message_received(m)
    blob = bytearray(path.read_bytes())
    blob[6] ^= 0x01  # the header length: python-can would skip every object
    path.write_bytes(bytes(blob))
    source = open_frames(path)
    assert list(source) == [] and source.status == "damaged"


def test_a_cut_blf_is_truncated(tmp_path):
    path = tmp_path / "x.blf"
    with can.BLFWriter(path) as w:
        for m in FRAMES * 400:
            w.on_message_received(m)
    blob = path.read_bytes()
    (tmp_path / "cut.blf").write_bytes(blob[: len(blob) // 2])
    source = open_frames(tmp_path / "cut.blf")
    list(source)
    assert source.status == "truncated" and source.position.startswith("byte ")


def test_relative_recordings_are_placed_one_after_another_and_named(tmp_path):
    a, b = tmp_path / "a.log", tmp_path / "b.log"
    a.write_text(candump_ta(FRAMES))
    b.write_text(candump_ta(FRAMES))
    notes = []
    times = [m.timestamp for m in one_timeline([open_frames(a), open_frames(b)], notes)]
    assert times == sorted(times) and len(times) == 2 * len(FRAMES)
    assert times[len(FRAMES)] == pytest.approx(times[len(FRAMES) - 1])
    assert len(notes) == 1 and str(b) in notes[0] and "relative" in notes[0]


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(["candump-L", "trc", "asc"]), st.integers(0, 10_000), st.binary(min_size=1, max_size=6))
def test_a_mutated_line_is_skipped_never_a_crash_nor_out_of_range(fmt, where, garbage):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "x"
        if fmt == "candump-L":
            path.write_text(candump_l(FRAMES))
        else:
            path = write_with(Path(d), f"x.{fmt}", {"trc": can.TRCWriter, "asc": can.ASCWriter}[fmt])
        blob = bytearray(path.read_bytes())
        at = len(blob) // 3 + where % (len(blob) * 2 // 3)  # past the header
        blob[at : at + len(garbage)] = garbage
        path.write_bytes(bytes(blob))
        source = open_frames(path)
        read = list(source)
        assert all(in_range(m) for m in read) and source.status in ("complete", "truncated")
        assert source.frames == len(read) <= len(FRAMES)
