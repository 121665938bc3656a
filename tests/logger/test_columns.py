"""The message columns a conversion writes beside its JSON channels (logger.columns): a block reads back as
written, and decoding a column of payloads gives exactly what the Decoder gives frame by frame."""
import numpy as np
import pytest

from fuelid.logger.columns import BLOCK_ROWS, ColumnWriter, read_block
from fuelid.logger.decode import Decoder
from fuelid.logger.j1939 import parse_id


def test_a_block_reads_back_grouped_by_message_with_its_write_order():
    blocks = []
    w = ColumnWriter(lambda data, t0: blocks.append((data, t0)))
    w.add_message(30, 61444, 0, 255, None, bytes(range(8)))
    w.add_flow(35, 12.5, None)
    w.add_message(20, 65251, 0, 255, "bam", bytes(39))  # a transport-protocol payload: longer than a frame
    w.add_message(40, 61444, 0, 255, None, b"\x01\x02")  # a short frame
    w.flush()
    w.flush()  # nothing more to write
    assert len(blocks) == 1 and blocks[0][1] == 20  # stamped with its earliest log time [ns]
    b = read_block(blocks[0][0])
    assert b.rows == 4
    assert b.pgn.tolist() == [61444, 61444, 65251] and b.seq.tolist() == [0, 3, 2]
    assert b.t_ns.tolist() == [30, 40, 20] and b.length.tolist() == [8, 2, 39]
    assert b.payload.shape == (3, 39) and bytes(b.payload[0, :8]) == bytes(range(8))
    assert bytes(b.payload[1, :3]) == b"\x01\x02\xff"  # padded with 0xFF, the length says what is real
    assert b.flow_seq.tolist() == [1] and b.flow_kg_h.tolist() == [12.5] and np.isnan(b.volts).all()


def test_a_full_block_is_written_at_once():
    blocks = []
    w = ColumnWriter(lambda data, t0: blocks.append(data))
    for i in range(BLOCK_ROWS + 1):
        w.add_flow(i, 1.0, 2.0)
    assert len(blocks) == 1 and read_block(blocks[0]).rows == BLOCK_ROWS


@pytest.mark.parametrize("data", [b"", b"garbage", bytes(100)])
def test_what_is_not_a_block_is_a_value_error(data):
    with pytest.raises(ValueError):
        read_block(data)


def test_decoded_columns_equal_the_decoder_frame_by_frame():
    """Every DBC message, random payloads rich in reserved values (0xFA-0xFF bytes) and short ones: the values
    are the very floats `decode_payload` gives (None as NaN)."""
    rng = np.random.default_rng(7)
    decoder = Decoder()
    for m in decoder.db.messages:
        pgn = parse_id(m.frame_id).pgn
        width = max(8, m.length)
        payload = rng.integers(0, 256, (400, width)).astype(np.uint8)
        payload[rng.random(payload.shape) < 0.3] = rng.choice([0xFA, 0xFB, 0xFC, 0xFE, 0xFF])
        length = np.where(rng.random(400) < 0.1, rng.integers(0, width, 400), width)
        name, values = decoder.decode_columns(pgn, payload, length)
        assert name == m.name
        for i in range(len(payload)):
            want = decoder.decode_payload(0.0, pgn, 0, 255, bytes(payload[i, :length[i]])).values
            got = {k: (None if np.isnan(v[i]) else v[i]) for k, v in values.items()}
            assert got == {k: v for k, v in want.items() if k != "VIN"}, (m.name, i)
            for k, v in got.items():
                assert v is None or float(want[k]).hex() == float(v).hex()  # bit for bit
    assert decoder.decode_columns(12345, np.zeros((1, 8), np.uint8), np.array([8])) is None


def test_many_messages_at_once_make_the_blocks_one_at_a_time_makes():
    """Across a block boundary, among single messages and readings; payload bytes past a length do not count."""
    rng = np.random.default_rng(3)
    n = BLOCK_ROWS + 500
    t = np.arange(n) * 1000
    pgn, sa = rng.choice([61444, 65265, 61443], n), rng.choice([0, 0x31], n)
    length = rng.integers(0, 9, n)
    payload = rng.integers(0, 256, (n, 8)).astype(np.uint8)
    one, many = [], []
    a, b = ColumnWriter(lambda data, t0: one.append(data)), ColumnWriter(lambda data, t0: many.append(data))
    for w in (a, b):
        w.add_message(5, 65251, 0, 255, "bam", bytes(39))
        w.add_flow(6, 2.5, 1.0)
    for i in range(n):
        if i == 100:
            a.add_flow(100_500, None, 3.0)
        a.add_message(int(t[i]), int(pgn[i]), int(sa[i]), 255, None, bytes(payload[i, : length[i]]))
    payload[np.arange(8) >= length[:, None]] = 0  # as a FrameBlock holds them
    b.add_messages(t[:100], pgn[:100], sa[:100], np.full(100, 255), length[:100], payload[:100])
    b.add_flow(100_500, None, 3.0)
    b.add_messages(t[100:], pgn[100:], sa[100:], np.full(n - 100, 255), length[100:], payload[100:])
    for w in (a, b):
        w.flush()
    assert len(one) == len(many) == 2
    for x, y in zip(one, many):
        x, y = read_block(x), read_block(y)
        for k in vars(x):
            np.testing.assert_array_equal(getattr(x, k), getattr(y, k), err_msg=k)
