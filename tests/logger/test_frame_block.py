"""candump -L read in blocks of columns and recorded column by column: the same frames, counts and MCAP bytes as
line by line and frame by frame, whatever the lines hold."""
import gzip
import random

import can
import cantools
import pytest
from hypothesis import given, settings, strategies as st
from mcap.reader import make_reader

from fuelid.dbc import FMS_DBC
from fuelid.logger.columns import NAME, read_block
from fuelid.logger.frame_block import FrameBlock
from fuelid.logger.mcap_log import read_attachments
from fuelid.logger.readers import one_timeline, open_frames
from fuelid.logger.recorder import Recorder, open_writer
from fuelid.logger.tp import bam_frames, rts_cts_frames

ODD_LINES = [
    "\n", "   \n", "garbage\n", "(1700000000.5) can0 0CF00400\n",  # blank and malformed
    "(1700000000.500000) can0 123#0011\n",  # 11-bit
    "(1700000000.500000) can0 20000080#0000000000000000\n",  # error frame
    "(1700000000.500000) can0 18FEF100#R\n", "(1700000000.500000) can0 18FEF100##1" + "00" * 12 + "\n",  # remote, FD
    "(1700000000.500000) can0 18FEF100#00112233 T\n", "(1700000000.500000)  can0 18FEF100#0011\n",  # flag, 2 spaces
    "(1700000000.500000)\tcan0\t18FEF100#0011\n", "(0001.5) can0 0CF00400#00112233\n",  # tabs, leading zeros
    "(1700000000.500000) can0 0CF00400#0011223\n", "(1700000000.500000) can0 0CF00400#001122334455667788\n",
    "(1700000000.500000) ca\"n0 0CF00400#0011\n", "(1700000000.500000) cän0 0CF00400#0011\n",  # JSON-escaped names
    "(100000000000000000000.000000) can0 0CF00400#0000000000000000\n",  # out of range
    "(1.5.5) can0 0CF00400#00\n", "(.5) can0 0CF00400#00\n", "(5.) can0 0CF00400#00\n",
    "(1700000000.500000) can0 0cf00400#ffffffffffffffff\n", "(1700000000.500000) can1 0CF00400#\n",
    "(1700000000.500000) can0 0CF00400#0011\r\n", "(1700000000.500000) can0 0CF00400#0011\r",
]


def frames(n: int, seed: int = 1) -> list[can.Message]:
    """Every DBC message with random bytes (so every null status comes up), some short, from two sources,
    and EC1 and VI by BAM and RTS/CTS."""
    rng = random.Random(seed)
    db = cantools.database.load_file(FMS_DBC)
    out, t = [], 1_700_000_000.0
    while len(out) < n:
        m = rng.choice(db.messages)
        size = 8 if rng.random() < 0.9 else rng.randint(0, 7)
        sa = rng.choice([0x00, 0x03, 0x31])
        out.append(can.Message(timestamp=t, arbitration_id=(m.frame_id & ~0xFF) | sa, channel="can0",
                               data=bytes(rng.choice([0, 0xFF, 0xFE, 0xFB, 0xFC, rng.randrange(256)]) for _ in range(size))))
        t = round(t + 0.001, 6)
        if rng.random() < 0.01:
            payload = bytes(rng.randrange(256) for _ in range(rng.randint(9, 40)))
            vin = rng.choice([b"YS2R4X20005399401*", b"\xff" * 20])
            out += bam_frames(65251, 0x00, payload, t0=t, gap_s=0.0005) if rng.random() < 0.5 else \
                rts_cts_frames(65260, 0x00, 0xF9, vin, t0=t, gap_s=0.0005)
            t = round(out[-1].timestamp + 0.001, 6)
    return out


def candump_l(msgs) -> str:
    return "".join(f"({m.timestamp:.6f}) {m.channel} {m.arbitration_id:08X}#{bytes(m.data).hex().upper()}\n" for m in msgs)


def messages(path):
    with open(path, "rb") as f:
        return [(c.topic, m.log_time, m.data) for _, c, m in make_reader(f).iter_messages(log_time_order=False)]


def columns(path):
    """The message columns of `path`, every array of every block as a list."""
    found = read_attachments(path, NAME)
    return [] if found is None else [{k: v.tolist() for k, v in vars(read_block(data)).items()} for data in found[1]]


def record(path, items, tmp_path, name):
    out = tmp_path / name
    writer = open_writer(out, live=False)
    recorder = Recorder(writer)
    for item in items:
        recorder.on_block(item) if isinstance(item, FrameBlock) else recorder.on_message_received(item)
    recorder.reassembler.expire(float("inf"))
    writer.close()
    return out, recorder


def both_ways(path, tmp_path):
    """(messages, counts) of `path` recorded frame by frame, and in blocks."""
    results = []
    for blocks in (False, True):
        source = open_frames(path)
        out, recorder = record(path, one_timeline([source], [], blocks=blocks), tmp_path, f"{blocks}.mcap")
        counts = (source.frames, source.skipped, source.status, source.position, source.error,
                  recorder.stats, recorder.decoder.counters(), recorder.reassembler.counters(), recorder.vin)
        results.append((messages(out), columns(out), counts))
    return results


def test_blocks_write_the_bytes_frame_by_frame_writes(tmp_path):
    """Every signal of every DBC message, null statuses, short frames and transport-protocol messages included."""
    log = tmp_path / "a.log"
    log.write_text(candump_l(frames(20_000)))
    by_frame, by_block = both_ways(log, tmp_path)
    assert by_block == by_frame
    assert sum(len(b["seq"]) for b in by_frame[1]) > 10_000  # the message columns too
    counts = by_frame[2][6]
    assert all(counts[s] > 100 for s in ("not_available", "error", "reserved", "missing"))
    assert by_frame[2][7]["completed"] > 100 and by_frame[2][8] == "YS2R4X20005399401"


def test_odd_lines_among_ordinary_ones_read_and_record_as_line_by_line(tmp_path):
    rng = random.Random(2)
    lines = candump_l(frames(3_000)).splitlines(keepends=True)
    for odd in ODD_LINES * 3:
        lines.insert(rng.randrange(len(lines)), odd)
    log = tmp_path / "odd.log.gz"
    with gzip.open(log, "wb") as f:
        f.write("".join(lines).encode("latin-1"))
    by_frame, by_block = both_ways(log, tmp_path)
    assert by_block == by_frame and by_frame[2][1] > 10


@pytest.mark.parametrize("cut", [0, 1, 9, 1000, 5000])
def test_a_cut_gzip_or_a_cut_last_line_ends_where_line_by_line_ends(tmp_path, cut):
    blob = gzip.compress(candump_l(frames(2_000)).encode())
    log = tmp_path / "cut.log.gz"
    log.write_bytes(blob[: len(blob) - cut] if cut >= 1000 else gzip.compress(candump_l(frames(2_000)).encode()[: -cut or None]))
    by_frame, by_block = both_ways(log, tmp_path)
    assert by_block == by_frame


@settings(max_examples=40, deadline=None)
@given(st.lists(st.sampled_from(ODD_LINES) | st.text(alphabet="()#.0123456789ABCDEFcanR \t\r\n", max_size=40),
                max_size=12), st.integers(0, 300))
def test_any_lines_read_as_line_by_line(odd, where):
    import tempfile
    from pathlib import Path
    lines = candump_l(frames(300, seed=3)).splitlines(keepends=True)
    lines[where:where] = odd
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "x.log"
        log.write_bytes(("".join(lines)).encode("latin-1", "replace"))
        try:
            by_line = list(open_frames(log))
        except Exception:  # noqa: BLE001 -- not a candump any more: nothing to compare
            return
        source = open_frames(log)
        by_block = [m for item in source.blocks()
                    for m in ([item.message(i) for i in range(len(item))] if isinstance(item, FrameBlock) else [item])]
        key = lambda m: (m.timestamp, m.arbitration_id, m.is_extended_id, m.is_error_frame, m.is_remote_frame,
                         m.is_fd, m.dlc, bytes(m.data), m.channel)
        assert [key(m) for m in by_block] == [key(m) for m in by_line]
