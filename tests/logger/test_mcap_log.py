"""Crash-safe MCAP: files the plain mcap reader opens, truncated files read and recovered, timely flushes."""
import io
import json
import random
import time

import can
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import NonSeekingReader, make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk
from mcap.writer import Writer

from fuelid.errors import FuelidError
from fuelid.logger.flowmeter import parse_line
from fuelid.logger.mcap_log import (
    FLOWMETER_SCHEMA,
    RAW_SCHEMA,
    McapLogWriter,
    chunks_located,
    damaged_chunks,
    raw_record,
    read_messages,
    read_metadata,
    recover,
)

T0 = 1_700_000_000_000_000_000  # log time origin [ns]
VIN = "YS2R4X20005399401"


def _write_log(path, n=400, **kwargs):
    """A log with frames every 50 ms of log time, a flow reading every 100 ms, and the VIN found halfway:
    1 s of log time per chunk gives ~20 chunks. Returns the messages written, in order."""
    written = []
    with McapLogWriter(path, metadata={"truck": "unknown", "source": ["trip.log"]}, fsync=False, **kwargs) as w:
        w.add_channel("/can/raw", RAW_SCHEMA)
        w.add_channel("/flowmeter", FLOWMETER_SCHEMA)
        for i in range(n):
            t_ns = T0 + i * 50_000_000
            frame = can.Message(timestamp=t_ns / 1e9, arbitration_id=0x0CF00400, data=bytes([i % 256] * 8), channel="can0")
            items = [("/can/raw", raw_record(frame))]
            if i % 2:
                items.append(("/flowmeter", parse_line(b"%d,%.3f" % (i, i % 100 / 10), t_ns / 1e9).to_record()))
            for topic, record in items:
                w.write(topic, t_ns, record)
                written.append((topic, t_ns, record))
            if i == n // 2:
                w.set_metadata({"truck": VIN})
    return written


# the daemon's files (one-second chunks, message indexes) and converted ones (chunks by size, no message
# indexes; a small size here to get many chunks) must read, cut, recover and refuse damage alike
WRITERS = {"live": {}, "compact": {"chunk_flush_s": None, "chunk_size": 2048, "message_indexes": False}}


@pytest.fixture(scope="module", params=list(WRITERS))
def log(tmp_path_factory, request):
    path = tmp_path_factory.mktemp("mcap") / "trip.mcap"
    return path, _write_log(path, **WRITERS[request.param])


def test_plain_mcap_reader_opens_the_file_with_schemas(log):
    path, written = log
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        messages = list(reader.iter_messages(log_time_order=False))
        metadata = list(reader.iter_metadata())
    assert summary.statistics.chunk_count >= 15
    schemas = {s.name: json.loads(s.data) for s in summary.schemas.values()}
    assert schemas == {"fuelid.can.raw": RAW_SCHEMA, "fuelid.flowmeter": FLOWMETER_SCHEMA}
    assert all(s.encoding == "jsonschema" for s in summary.schemas.values())
    assert [(c.topic, c.message_encoding) for c in summary.channels.values()] == [("/can/raw", "json"), ("/flowmeter", "json")]
    assert [(ch.topic, m.log_time, json.loads(m.data)) for _, ch, m in messages] == written
    assert [m.metadata["truck"] for m in metadata] == ["unknown", VIN]


def test_read_messages_and_metadata_of_a_complete_file(log):
    path, written = log
    assert list(read_messages(path)) == written
    assert list(read_messages(path, topics=["/flowmeter"])) == [w for w in written if w[0] == "/flowmeter"]
    meta = read_metadata(path)["fuelid"]
    assert meta["truck"] == VIN and json.loads(meta["source"]) == ["trip.log"] and meta["logger_version"]


def _data_section(data: bytes) -> list[tuple[int, int, int]]:
    """(opcode, start, end offset) of the top-level records of a complete file's data section, walked by their
    length fields (a converted file has no chunk index)."""
    records, pos = [], 8
    while data[pos] != Opcode.DATA_END:
        end = pos + 9 + int.from_bytes(data[pos + 1 : pos + 9], "little")
        records.append((data[pos], pos, end))
        pos = end
    return records


def _chunk_ends(data: bytes) -> list[tuple[int, int, int]]:
    """(end offset, message count, start offset) of each chunk of a complete file."""
    ends = []
    for opcode, start, end in _data_section(data):
        if opcode == Opcode.CHUNK:
            chunk = Chunk.read(ReadDataStream(io.BytesIO(data[start + 9 : end])))
            ends.append((end, sum(isinstance(r, Message) for r in breakup_chunk(chunk)), start))
    return ends


def test_truncated_file_gives_every_complete_chunk(log, tmp_path):
    path, written = log
    data = path.read_bytes()
    ends = _chunk_ends(data)
    rng = random.Random(7)
    cuts = {e + d for e, *_ in ends for d in (-1, 0, 1)} | {rng.randrange(8, len(data)) for _ in range(40)}
    cut_path, fixed = tmp_path / "cut.mcap", tmp_path / "fixed.mcap"
    for cut in sorted(cuts):
        cut_path.write_bytes(data[:cut])
        expected = written[: sum(n for end, n, _ in ends if end <= cut)]
        assert list(read_messages(cut_path)) == expected, cut
        stats = recover(cut_path, fixed)
        assert sum(stats.messages.values()) == len(expected)
        with open(fixed, "rb") as f:  # the plain reader reads the recovered file through its index
            reader = make_reader(f)
            assert reader.get_summary() is not None
            got = [(ch.topic, m.log_time, json.loads(m.data)) for _, ch, m in reader.iter_messages(log_time_order=False)]
        assert got == expected, cut
        assert read_metadata(fixed)["fuelid"]["truck"] in ("unknown", VIN)


def test_truncated_file_still_names_its_truck(log, tmp_path):
    path, written = log
    data = path.read_bytes()
    cut_path = tmp_path / "cut.mcap"
    cut_path.write_bytes(data[: len(data) * 3 // 4])
    assert read_metadata(cut_path)["fuelid"]["truck"] == VIN
    cut_path.write_bytes(data[:200])
    assert read_metadata(cut_path)["fuelid"]["truck"] == "unknown"


def test_plain_reader_alone_gets_nothing_from_a_cut_file(log, tmp_path):
    """Why the project ships its own reader path: if this starts passing, mcap learned to read cut files."""
    path, _ = log
    cut_path = tmp_path / "cut.mcap"
    cut_path.write_bytes(path.read_bytes()[:-100])
    with open(cut_path, "rb") as f, pytest.raises(Exception):
        list(make_reader(f).iter_messages())


def test_recover_reports_what_it_kept(log, tmp_path):
    path, written = log
    data = path.read_bytes()
    ends = _chunk_ends(data)
    cut_path = tmp_path / "cut.mcap"
    cut_path.write_bytes(data[: ends[4][0] + 10])
    stats = recover(cut_path, tmp_path / "fixed.mcap")
    kept = written[: sum(n for _, n, _ in ends[:5])]
    assert dict(stats.messages) == {t: sum(1 for w in kept if w[0] == t) for t in ("/can/raw", "/flowmeter")}
    assert not stats.complete and stats.bytes_total == len(data[: ends[4][0] + 10])
    assert 10 <= stats.bytes_lost < 100  # the 10 bytes cut off, plus the message indexes' bytes after them
    full = recover(path, tmp_path / "again.mcap")
    assert full.complete and full.bytes_lost == 0 and sum(full.messages.values()) == len(written)
    with pytest.raises(FuelidError):
        recover(path, path)


@pytest.mark.parametrize("content", [b"", b"\x89MCA", b"hello, not an mcap file at all\n" * 10, bytes(range(256))])
def test_garbage_is_a_clear_error(tmp_path, content):
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    with pytest.raises(FuelidError, match="not an MCAP file"):
        list(read_messages(path))
    with pytest.raises(FuelidError, match="not an MCAP file"):
        recover(path, tmp_path / "out.mcap")


_CHUNK_DATA = 9 + 8 + 8 + 8 + 4 + 4 + 4 + 8  # opcode, length, times, sizes, crc, "zstd", records length


def _flipped(data: bytes, chunk: tuple[int, int, int], fraction: float, mask: int) -> tuple[bytes, int]:
    """`data` with one byte inside the compressed records of `chunk` (end, count, start) xor-ed with `mask`."""
    end, _, start = chunk
    pos = start + _CHUNK_DATA + int((end - start - _CHUNK_DATA) * fraction)
    out = bytearray(data)
    out[pos] ^= mask
    return bytes(out), pos


FLIPS = [(f, m) for f in (0.0, 0.1, 0.37, 0.5, 0.73, 0.99) for m in (0x01, 0x10, 0x80, 0xFF)]


@pytest.mark.parametrize("fraction, mask", FLIPS)
def test_a_flipped_byte_in_a_chunk_is_an_error_naming_the_file_and_bytes(log, tmp_path, fraction, mask):
    path, written = log
    data = path.read_bytes()
    ends = _chunk_ends(data)
    bad = tmp_path / "bad.mcap"
    flipped, _ = _flipped(data, ends[3], fraction, mask)
    bad.write_bytes(flipped)
    end, lost, start = ends[3]
    with pytest.raises(FuelidError, match=rf"{bad}: damaged chunk at bytes {start}-{end}"):
        list(read_messages(bad))
    damaged = []  # asked for: the damaged chunk is skipped and reported, every other chunk read
    got = list(read_messages(bad, damaged=damaged))
    before = sum(n for _, n, _ in ends[:3])
    assert got == written[:before] + written[before + lost:]
    assert [(d.start, d.end) for d in damaged] == [(start, end)]
    assert damaged_chunks(bad) == damaged and damaged_chunks(path) == []


@pytest.mark.parametrize("fraction, mask", FLIPS[::3])
def test_a_cut_file_with_a_damaged_chunk_is_an_error_too(log, tmp_path, fraction, mask):
    path, written = log
    data = path.read_bytes()
    ends = _chunk_ends(data)
    flipped, _ = _flipped(data[:-50], ends[2], fraction, mask)  # no footer: sequential scan
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(flipped)
    end, lost, start = ends[2]
    with pytest.raises(FuelidError, match=rf"damaged chunk at bytes {start}-{end}"):
        list(read_messages(bad))
    damaged = []
    got = list(read_messages(bad, damaged=damaged))
    before = sum(n for _, n, _ in ends[:2])
    assert got == written[:before] + written[before + lost:]
    assert [(d.start, d.end) for d in damaged] == [(start, end)]


@pytest.mark.parametrize("cut_footer", [False, True])
@pytest.mark.parametrize("fraction", [0.2, 0.4, 0.8])
def test_recover_skips_a_damaged_middle_chunk_and_keeps_the_rest(log, tmp_path, fraction, cut_footer):
    path, written = log
    data = path.read_bytes()
    ends = _chunk_ends(data)
    k = int(len(ends) * fraction)
    flipped, _ = _flipped(data[:-50] if cut_footer else data, ends[k], 0.5, 0x04)
    bad, fixed = tmp_path / "bad.mcap", tmp_path / "fixed.mcap"
    bad.write_bytes(flipped)
    stats = recover(bad, fixed)
    end, lost, start = ends[k]
    before = sum(n for _, n, _ in ends[:k])
    kept = written[:before] + written[before + lost:]
    assert list(read_messages(fixed)) == kept
    assert [(d.start, d.end) for d in stats.damaged] == [(start, end)]
    assert sum(stats.messages.values()) == len(kept)
    assert stats.bytes_lost >= end - start
    if not cut_footer:  # the index says how many messages the chunk held
        assert stats.messages_lost == lost
    assert not stats.complete


def test_damage_to_a_chunk_length_is_skipped_to_the_next_intact_chunk(log, tmp_path):
    path, written = log
    ends = _chunk_ends(path.read_bytes())
    data = bytearray(path.read_bytes()[:-50])
    end, lost, start = ends[5]
    data[start + 3] ^= 0x40  # the record length: the scan must find the next chunk by itself
    bad, fixed = tmp_path / "bad.mcap", tmp_path / "fixed.mcap"
    bad.write_bytes(bytes(data))
    stats = recover(bad, fixed)
    before = sum(n for _, n, _ in ends[:5])
    assert list(read_messages(fixed)) == written[:before] + written[before + lost:]
    assert len(stats.damaged) == 1 and stats.damaged[0].start == start and stats.damaged[0].end <= ends[6][2]


def test_damaged_summary_index_falls_back_to_verified_chunks(log, tmp_path):
    """A flip in the index (no CRC of its own but the footer's summary CRC) must not drop a chunk."""
    path, written = log
    data = bytearray(path.read_bytes())
    summary_start = make_reader(io.BytesIO(bytes(data))).get_summary() and _summary_start(bytes(data))
    data[summary_start + 40] ^= 0x01
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    assert list(read_messages(bad)) == written


def _summary_start(data: bytes) -> int:
    # footer: opcode, length, summary_start, summary_offset_start, summary_crc, then the magic
    return int.from_bytes(data[-8 - 20 : -8 - 12], "little")


def test_chunks_close_every_second_of_log_time(tmp_path):
    path = tmp_path / "t.mcap"
    with McapLogWriter(path, metadata={}, fsync=False) as w:
        w.add_channel("/can/raw", RAW_SCHEMA)
        for i in range(50):  # 10 s of log time at 5 Hz
            w.write("/can/raw", T0 + i * 200_000_000, {"t": i})
    with open(path, "rb") as f:
        assert 9 <= make_reader(f).get_summary().statistics.chunk_count <= 11


def test_both_reference_python_readers_and_fuelid_read_the_same(log):
    """mcap's SeekingReader reads a file without a chunk index (converted) as its NonSeekingReader does."""
    path, written = log
    with open(path, "rb") as f:
        seeking = [(c.topic, m.log_time, json.loads(m.data)) for _, c, m in make_reader(f).iter_messages()]
    with open(path, "rb") as f:
        stream = [(c.topic, m.log_time, json.loads(m.data)) for _, c, m in NonSeekingReader(f).iter_messages()]
    assert seeking == stream == list(read_messages(path)) == written
    assert chunks_located(path)


def test_messages_outside_chunks_are_read_by_the_scan_not_located(tmp_path):
    """The walk of a file without a chunk index vouches only for chunked messages: others must not be skipped."""
    path = tmp_path / "unchunked.mcap"
    with open(path, "wb") as f:
        w = Writer(f, use_chunking=False)
        w.start()
        channel = w.register_channel("/flowmeter", "json", w.register_schema("s", "jsonschema", b"{}"))
        for i in range(3):
            w.add_message(channel, T0 + i, b'{"i": %d}' % i, T0 + i)
        w.finish()
    assert not chunks_located(path)
    assert [r["i"] for _, _, r in read_messages(path)] == [0, 1, 2]


def test_compact_writing_has_no_indexes_and_chunks_by_size(tmp_path):
    path = tmp_path / "t.mcap"
    with McapLogWriter(path, metadata={}, chunk_flush_s=None, chunk_size=1 << 17, message_indexes=False) as w:
        w.add_channel("/can/raw", RAW_SCHEMA)
        for i in range(2000):  # 400 s of log time, ~80 kB of records
            w.write("/can/raw", T0 + i * 200_000_000, {"t": i})
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary.statistics.chunk_count == 1
    # @mcap/core's indexed reader (Foxglove) refuses a chunk index without message indexes: neither is written
    assert not summary.chunk_indexes
    assert Opcode.MESSAGE_INDEX not in {opcode for opcode, _, _ in _data_section(path.read_bytes())}
    assert [r["t"] for _, _, r in read_messages(path)] == list(range(2000))


def test_data_reaches_disk_within_a_second_of_wall_time(tmp_path):
    path = tmp_path / "live.mcap"
    w = McapLogWriter(path, metadata={"truck": "unknown"}, chunk_flush_s=0.3)
    w.add_channel("/flowmeter", FLOWMETER_SCHEMA)
    try:
        for i in range(5):  # log times 1 ms apart: only wall time can trigger the flush
            w.write("/flowmeter", T0 + i * 1_000_000, {"i": i})
        time.sleep(0.35)
        w.write("/flowmeter", T0 + 5_000_000, {"i": 5})  # a write after the deadline flushes
        assert [r["i"] for _, _, r in read_messages(path)] == list(range(6))
        w.write("/flowmeter", T0 + 6_000_000, {"i": 6})
        time.sleep(0.35)
        w.flush_if_due()  # a quiet bus: the idle loop flushes
        assert [r["i"] for _, _, r in read_messages(path)] == list(range(7))
    finally:
        w.close()
    assert len(list(read_messages(path))) == 7


_FILL_UP = """
import json, logging, resource, signal, sys
from fuelid.logger.mcap_log import RAW_SCHEMA, McapLogWriter
logged = []
handler = logging.Handler()
handler.emit = lambda record: logged.append(record.getMessage())
logging.getLogger().addHandler(handler)
w = McapLogWriter(sys.argv[1], metadata={"truck": "T"}, fsync=False, chunk_size=4096)
w.add_channel("/can/raw", RAW_SCHEMA)
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, resource.RLIM_INFINITY))  # no file grows past 100 kB
written, error = 0, None
for k in range(20_000):  # 1 us of log time apart: chunks written when full, within a write
    try:
        w.write("/can/raw", 10**18 + k * 10**3, {"t": k, "data": "%016x" % (k * 7919)})
        written += 1
    except Exception as exc:
        error = error or [type(exc).__name__, getattr(exc, "errno", None)]
print(json.dumps({"written": written, "error": error, "logged": logged}))
"""


def test_a_failed_write_raises_at_once_and_logs_nothing(tmp_path):
    """The Foxglove SDK reports a failed message write only as a log warning, per message; the writer
    raises it (OSError with the errno) from the first write that failed, and the log stays quiet."""
    import errno
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _FILL_UP, str(tmp_path / "full.mcap")], capture_output=True,
                         text=True, timeout=120)
    result = json.loads(out.stdout)
    assert result["error"] == ["OSError", errno.EFBIG], result["error"]
    assert 100 < result["written"] < 20_000  # the chunks that fitted were written, none after the failure
    assert result["logged"] == []


def test_raw_record_matches_schema():
    frame = can.Message(timestamp=12.5, arbitration_id=0x18FEF100, data=b"\x01\xff", is_extended_id=True, channel=0)
    record = raw_record(frame)
    assert set(record) == set(RAW_SCHEMA["properties"]) == set(RAW_SCHEMA["required"])
    assert record == {"t": 12.5, "id": 0x18FEF100, "extended": True, "dlc": 2, "data": "01ff",
                      "error": False, "remote": False, "channel": 0}


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(where=st.floats(0, 1, exclude_max=True), mask=st.integers(1, 255), cut=st.booleans())
def test_a_flipped_byte_anywhere_is_refused_or_harmless_never_silently_wrong(log, tmp_path, where, mask, cut):
    path, written = log
    data = path.read_bytes()[: -50 if cut else None]
    expected = written if not cut else None
    if cut:
        (tmp_path / "cut.mcap").write_bytes(data)
        expected = list(read_messages(tmp_path / "cut.mcap"))
    blob = bytearray(data)
    blob[int(where * len(blob))] ^= mask
    (tmp_path / "bad.mcap").write_bytes(bytes(blob))
    try:
        got = list(read_messages(tmp_path / "bad.mcap"))
    except FuelidError:
        return
    assert got == expected


def test_recover_keeps_the_rest_when_the_chunk_holding_the_channels_is_damaged(log, tmp_path):
    """The first chunk holds the schema and channel records; the summary has them too."""
    path, written = log
    data = path.read_bytes()
    ends = _chunk_ends(data)
    flipped, _ = _flipped(data, ends[0], 0.5, 0x04)
    bad, fixed = tmp_path / "bad.mcap", tmp_path / "fixed.mcap"
    bad.write_bytes(flipped)
    stats = recover(bad, fixed)
    assert list(read_messages(fixed)) == written[ends[0][1]:] and stats.messages_lost == ends[0][1]


@pytest.mark.parametrize("offset", [10, 11])  # the header record's length field
def test_a_garbled_record_length_does_not_swallow_what_follows(log, tmp_path, offset):
    path, written = log
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x10
    bad, fixed = tmp_path / "bad.mcap", tmp_path / "fixed.mcap"
    bad.write_bytes(bytes(data))
    recover(bad, fixed)
    assert list(read_messages(fixed)) == written


@pytest.mark.parametrize("which", [0, -2])
def test_a_chunk_whose_opcode_became_another_records_is_damage_not_skipped(log, tmp_path, which):
    """A chunk's opcode byte with one bit flipped (CHUNK 0x06 → MESSAGE_INDEX 0x07) in a cut file, which is read by
    the scan: the record does not parse as a message index, so its messages are reported lost, never skipped."""
    path, written = log
    data = path.read_bytes()
    end, lost, start = _chunk_ends(data)[which]
    blob = bytearray(data[:-50])
    blob[start] ^= 0x01
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(blob))
    with pytest.raises(FuelidError, match=f"damaged chunk at bytes {start}-"):
        list(read_messages(bad))


def test_a_damaged_last_chunk_of_a_cut_file_is_damage_not_the_cut(log, tmp_path):
    path, written = log
    data = path.read_bytes()
    ends = _chunk_ends(data)
    end, lost, start = ends[-1]
    flipped, _ = _flipped(data[:end], ends[-1], 0.5, 0x02)  # cut right after the last chunk, which is damaged
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(flipped)
    with pytest.raises(FuelidError, match=f"damaged chunk at bytes {start}-{end}"):
        list(read_messages(bad))
