"""J1939-21 transport protocol: BAM and RTS/CTS reassembly, and never a wrong payload."""
import math

import can
import pytest
from hypothesis import given, settings, strategies as st

from fuelid.logger.decode import Decoder
from fuelid.logger.j1939 import PGN_TP_CM, make_id
from fuelid.logger.tp import TransportReassembler, bam_frames, rts_cts_frames

EC1, VI = 65251, 65260
PAYLOAD = bytes(range(100, 139))  # 39 bytes, 6 packets


def feed(reassembler, frames):
    out = []
    for f in frames:
        out += reassembler.feed(f)
    return out


def cm(t, sa, da, *data):
    return can.Message(timestamp=t, arbitration_id=make_id(PGN_TP_CM, sa, da, 7), data=bytes(data))


def shifted(frames, dt):
    return [can.Message(timestamp=f.timestamp + dt, arbitration_id=f.arbitration_id, data=f.data)
            for f in frames]


def test_bam_frames_layout():
    frames = bam_frames(EC1, 0x00, PAYLOAD, t0=10.0, gap_s=0.05)
    assert len(frames) == 7
    assert frames[0].arbitration_id == 0x1CECFF00
    assert bytes(frames[0].data) == bytes([32, 39, 0, 6, 0xFF, 0xE3, 0xFE, 0x00])
    assert all(f.arbitration_id == 0x1CEBFF00 and len(f.data) == 8 for f in frames[1:])
    assert [f.data[0] for f in frames[1:]] == [1, 2, 3, 4, 5, 6]
    assert bytes(frames[-1].data) == bytes([6]) + PAYLOAD[35:] + b"\xff\xff\xff"
    assert frames[-1].timestamp == pytest.approx(10.3)


def test_bam_reassembles_and_decodes_ec1():
    r = TransportReassembler()
    payload = bytearray(b"\xff" * 39)
    payload[19:21] = (2386).to_bytes(2, "little")
    [msg] = feed(r, bam_frames(EC1, 0x00, bytes(payload), t0=2.0))
    assert (msg.pgn, msg.sa, msg.da, msg.kind, msg.payload) == (EC1, 0, 255, "bam", bytes(payload))
    assert msg.t == pytest.approx(2.3)
    d = Decoder().decode_payload(msg.t, msg.pgn, msg.sa, msg.da, msg.payload, tp=msg.kind)
    assert d.values["EngReferenceTorque"] == 2386 and d.tp == "bam"
    assert r.counters() == {"started": 1, "completed": 1, "aborted": 0, "timed_out": 0, "replaced": 0,
                            "sequence_errors": 0, "duplicates": 0, "invalid_cm": 0, "orphan_frames": 0,
                            "discarded": 0}


def test_interleaved_bam_from_two_sources():
    a = bam_frames(EC1, 0x00, PAYLOAD, t0=0.0, gap_s=0.05)
    b = bam_frames(VI, 0x17, b"YS2R4X20005399401*", t0=0.02, gap_s=0.05)
    out = feed(TransportReassembler(), sorted(a + b, key=lambda f: f.timestamp))
    assert {(m.sa, m.pgn, m.payload) for m in out} == {(0x00, EC1, PAYLOAD),
                                                       (0x17, VI, b"YS2R4X20005399401*")}


@pytest.mark.parametrize("gap_s, delivered", [(0.7, True), (0.8, False)])
def test_t1_timeout_on_message_timestamps(gap_s, delivered):
    frames = bam_frames(EC1, 0x00, PAYLOAD)
    frames = frames[:3] + shifted(frames[3:], gap_s)
    r = TransportReassembler()
    assert (feed(r, frames) != []) == delivered
    assert r.stats.timed_out == (0 if delivered else 1)


def test_expire_at_end_of_recording_counts_unfinished_sessions():
    r = TransportReassembler()
    feed(r, bam_frames(EC1, 0x00, PAYLOAD)[:4])
    r.expire(math.inf)
    assert r.stats.timed_out == 1 and r.stats.discarded == 1


def test_new_bam_from_the_same_source_replaces_the_unfinished_one():
    first = bam_frames(EC1, 0x00, bytes(39), t0=0.0)[:4]
    second = bam_frames(EC1, 0x00, PAYLOAD, t0=0.2)
    r = TransportReassembler()
    assert [m.payload for m in feed(r, first + second)] == [PAYLOAD]
    assert r.stats.replaced == 1


def test_dropped_packet_discards_the_message():
    frames = bam_frames(EC1, 0x00, PAYLOAD)
    r = TransportReassembler()
    assert feed(r, frames[:3] + frames[4:]) == []
    assert r.stats.sequence_errors == 1


def test_identical_duplicate_is_ignored_a_different_one_discards():
    frames = bam_frames(EC1, 0x00, PAYLOAD)
    r = TransportReassembler()
    assert [m.payload for m in feed(r, frames[:3] + frames[2:])] == [PAYLOAD]
    assert r.stats.duplicates == 1
    bad = can.Message(timestamp=frames[2].timestamp, arbitration_id=frames[2].arbitration_id,
                      data=bytes([2]) + bytes(7))
    assert feed(r, frames[:3] + [bad] + frames[3:]) == []
    assert r.stats.sequence_errors == 1


def test_invalid_connection_management_is_ignored():
    r = TransportReassembler()
    feed(r, [cm(0, 0, 255, 32, 8, 0, 2, 0xFF, 0xE3, 0xFE, 0),       # size 8 < 9
             cm(0, 0, 255, 32, 0xFA, 0x06, 255, 0xFF, 0xE3, 0xFE, 0),  # 1786 bytes
             cm(0, 0, 255, 32, 39, 0, 7, 0xFF, 0xE3, 0xFE, 0),       # 7 packets for 39 bytes
             cm(0, 0, 0x17, 32, 39, 0, 6, 0xFF, 0xE3, 0xFE, 0),      # BAM to one node
             cm(0, 0, 255, 16, 39, 0, 6, 0xFF, 0xE3, 0xFE, 0),       # RTS to everyone
             cm(0, 0, 255, 99, 39, 0, 6, 0xFF, 0xE3, 0xFE, 0),       # unknown control byte
             cm(0, 0, 255, 32, 39, 0)])                              # short frame
    assert r.stats.invalid_cm == 7 and r.stats.started == 0


def test_rts_cts_with_windows_of_two_packets():
    frames = rts_cts_frames(EC1, 0x00, 0x17, PAYLOAD, t0=1.0, packets_per_cts=2)
    kinds = [(f.arbitration_id >> 16 & 0xFF, f.data[0]) for f in frames]
    assert kinds[0] == (0xEC, 16) and kinds[1] == (0xEC, 17) and kinds[-1] == (0xEC, 19)
    assert sum(1 for k in kinds if k == (0xEC, 17)) == 3
    r = TransportReassembler()
    [msg] = feed(r, frames)
    assert (msg.pgn, msg.sa, msg.da, msg.kind, msg.payload) == (EC1, 0x00, 0x17, "rts", PAYLOAD)
    assert msg.t == frames[-1].timestamp


def test_rts_cts_retransmission_requested_by_the_receiver():
    frames = rts_cts_frames(EC1, 0x00, 0x17, PAYLOAD, packets_per_cts=3)
    # after packets 1-3 the receiver asks again for 2 and 3; the sender repeats them (here with the
    # right data where the first copy was wrong: the CTS says the first copy is void)
    first_window = frames[:5]
    wrong = can.Message(timestamp=first_window[3].timestamp, arbitration_id=first_window[3].arbitration_id,
                        data=bytes([2]) + bytes(7))
    first_window[3] = wrong
    t = first_window[-1].timestamp
    again = [cm(t + 0.01, 0x17, 0x00, 17, 2, 2, 0xFF, 0xFF, 0xE3, 0xFE, 0x00)] + shifted(frames[3:5], 0.02)
    r = TransportReassembler()
    [msg] = feed(r, first_window + again + shifted(frames[5:], 0.05))
    assert msg.payload == PAYLOAD


def test_cts_asking_for_packets_we_never_saw_discards():
    frames = rts_cts_frames(EC1, 0x00, 0x17, PAYLOAD, packets_per_cts=2)
    # drop the second window's CTS and its data, keep the third CTS (next packet 5)
    r = TransportReassembler()
    assert feed(r, frames[:4] + frames[7:]) == []
    assert r.stats.sequence_errors == 1


def test_data_before_any_cts_discards():
    frames = rts_cts_frames(EC1, 0x00, 0x17, PAYLOAD)
    r = TransportReassembler()
    assert feed(r, [frames[0]] + frames[2:]) == []
    assert r.stats.sequence_errors == 1


def test_abort_from_the_receiver_ends_the_session():
    frames = rts_cts_frames(EC1, 0x00, 0x17, PAYLOAD)
    abort = cm(frames[3].timestamp, 0x17, 0x00, 255, 3, 0xFF, 0xFF, 0xFF, 0xE3, 0xFE, 0x00)
    r = TransportReassembler()
    assert feed(r, frames[:4] + [abort] + frames[4:]) == []
    assert r.stats.aborted == 1 and r.stats.orphan_frames > 0


def test_abort_for_another_pgn_is_ignored():
    frames = rts_cts_frames(EC1, 0x00, 0x17, PAYLOAD)
    abort = cm(frames[3].timestamp, 0x17, 0x00, 255, 3, 0xFF, 0xFF, 0xFF, 0xEC, 0xFE, 0x00)
    assert [m.payload for m in feed(TransportReassembler(), frames[:4] + [abort] + frames[4:])] == [PAYLOAD]


def test_end_of_message_ack_without_all_packets_delivers_nothing():
    frames = rts_cts_frames(EC1, 0x00, 0x17, PAYLOAD)
    r = TransportReassembler()
    assert feed(r, frames[:5] + frames[-1:]) == []
    assert r.stats.sequence_errors == 1 and r.stats.completed == 0


def test_bam_and_connection_from_one_source_run_side_by_side():
    bam = bam_frames(VI, 0x00, b"YS2R4X20005399401*", gap_s=0.05)
    rts = rts_cts_frames(EC1, 0x00, 0x17, PAYLOAD, t0=0.01, gap_s=0.02)
    out = feed(TransportReassembler(), sorted(bam + rts, key=lambda f: f.timestamp))
    assert sorted((m.kind, m.payload) for m in out) == [("bam", b"YS2R4X20005399401*"), ("rts", PAYLOAD)]


# -- property-based: whatever happens to the frames, a delivered payload is the one that was sent --

payloads = st.binary(min_size=9, max_size=300)


def mutate(frames, data):
    """Drop, duplicate, swap and renumber frames, as a faulty bus, stack or logger might.

    Renumbering picks a sequence number no packet of this message has (0 or above the packet count):
    TP has no checksum, so a frame carrying one packet's data under another packet's valid number is
    indistinguishable from the genuine packet; CAN's CRC guards the bits, TP only the order. Misplaced
    genuine packets are what drop, duplicate and swap produce."""
    n_packets = sum(1 for f in frames if f.arbitration_id >> 16 & 0xFF == 0xEB)
    frames = list(frames)
    for _ in range(data.draw(st.integers(0, 4))):
        op = data.draw(st.sampled_from(["drop", "dup", "swap", "renumber"]))
        i = data.draw(st.integers(1, len(frames) - 1)) if len(frames) > 1 else 0
        if op == "drop":
            del frames[i]
        elif op == "dup":
            frames.insert(i, frames[i])
        elif op == "swap" and i + 1 < len(frames):
            frames[i], frames[i + 1] = frames[i + 1], frames[i]
        elif op == "renumber":
            f = frames[i]
            seq = data.draw(st.sampled_from([0, *range(n_packets + 1, 256)]))
            frames[i] = can.Message(timestamp=f.timestamp, arbitration_id=f.arbitration_id,
                                    data=bytes([seq]) + bytes(f.data[1:]))
        if not frames:
            break
    # keep timestamps increasing so timeouts are not what is tested here
    return [can.Message(timestamp=k * 0.01, arbitration_id=f.arbitration_id, data=f.data)
            for k, f in enumerate(frames)]


@settings(max_examples=200, deadline=None)
@given(payloads, payloads, st.data())
def test_fuzz_bam_never_delivers_a_wrong_payload(p1, p2, data):
    a = mutate(bam_frames(EC1, 0x00, p1), data)
    b = mutate(bam_frames(VI, 0x31, p2), data)
    order = data.draw(st.permutations([0] * len(a) + [1] * len(b)))
    streams = [iter(a), iter(b)]
    merged = [next(streams[k]) for k in order]
    merged = [can.Message(timestamp=k * 0.01, arbitration_id=f.arbitration_id, data=f.data)
              for k, f in enumerate(merged)]
    sent = {0x00: p1, 0x31: p2}
    for msg in feed(TransportReassembler(), merged):
        assert msg.payload == sent[msg.sa]


@settings(max_examples=200, deadline=None)
@given(payloads, st.integers(1, 8), st.data())
def test_fuzz_rts_cts_never_delivers_a_wrong_payload(payload, per_cts, data):
    frames = mutate(rts_cts_frames(EC1, 0x00, 0x17, payload, packets_per_cts=per_cts), data)
    for msg in feed(TransportReassembler(), frames):
        assert msg.payload == payload


def test_unmutated_sequences_always_deliver():
    for size in (9, 14, 15, 39, 1785):
        payload = bytes(i % 251 for i in range(size))
        assert [m.payload for m in feed(TransportReassembler(), bam_frames(EC1, 0, payload))] == [payload]
        assert [m.payload for m in feed(TransportReassembler(),
                                        rts_cts_frames(EC1, 0, 0x17, payload, packets_per_cts=16))] == [payload]


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(st.sampled_from([0xEC, 0xEB]), st.integers(0, 255), st.integers(0, 255),
                          st.binary(max_size=8)), max_size=40))
def test_fuzz_random_tp_frames_never_raise(frames):
    r = TransportReassembler()
    for k, (pf, da, sa, d) in enumerate(frames):
        r.feed(can.Message(timestamp=k * 0.1, arbitration_id=0x1C000000 | pf << 16 | da << 8 | sa, data=d))
    r.expire(math.inf)
    assert r.stats.completed <= r.stats.started
