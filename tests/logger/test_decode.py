"""J1939 decoding: reserved raw values per field size, short frames, source addresses, records, schemas."""
import json
import math

import can
import pytest
from hypothesis import given, settings, strategies as st

from fuelid.logger.decode import INVALID_STATUSES, Decoder, message_schema
from fuelid.logger.j1939 import make_id, parse_id


@pytest.fixture(scope="module")
def decoder():
    return Decoder()


def frame(name_pgn: int, data: bytes, sa: int = 0x00, t: float = 1.5, priority: int = 6) -> can.Message:
    return can.Message(timestamp=t, arbitration_id=make_id(name_pgn, sa, priority=priority), data=data)


EEC1, CCVS1, ETC2, LFC1, DPFC1, EC1, VI = 61444, 65265, 61445, 65257, 64892, 65251, 65260


def test_eec1_from_a_real_frame(decoder):
    # SystemsCyber drive: 0CF00400 [8] 21 9B 9B DD 2F 00 0F 9B
    d = decoder.decode(can.Message(timestamp=0.017118, arbitration_id=0x0CF00400,
                                   data=bytes.fromhex("219B9BDD2F000F9B")))
    assert (d.name, d.pgn, d.sa, d.da, d.t) == ("EEC1", 61444, 0, 255, 0.017118)
    assert d.values == {"EngTorqueMode": 1, "DriversDemandEngPercentTorque": 30,
                        "ActualEngPercentTorque": 30, "EngSpeed": 0x2FDD * 0.125,
                        "EngDemandPercentTorque": 30}
    assert d.invalid == {}


def test_all_ff_eec1_is_not_available_not_8191_rpm(decoder):
    d = decoder.decode(frame(EEC1, b"\xff" * 8))
    assert all(v is None for v in d.values.values())
    assert d.invalid == dict.fromkeys(d.values, "not_available")


@pytest.mark.parametrize("speed_raw, status", [
    (0xFAFF, None), (0xFB00, None), (0xFBFF, None),          # valid, parameter specific
    (0xFC00, "reserved"), (0xFDFF, "reserved"),
    (0xFE00, "error"), (0xFEFF, "error"),
    (0xFF00, "not_available"), (0xFFFF, "not_available"),
])
def test_two_byte_field(decoder, speed_raw, status):
    d = decoder.decode(frame(EEC1, bytes([0xF0, 125, 125]) + speed_raw.to_bytes(2, "little") + b"\xff\xff\x7d"))
    if status is None:
        assert d.values["EngSpeed"] == speed_raw * 0.125 and "EngSpeed" not in d.invalid
    else:
        assert d.values["EngSpeed"] is None and d.invalid["EngSpeed"] == status
    assert d.values["ActualEngPercentTorque"] == 0


@pytest.mark.parametrize("raw, status", [
    (0xFA, None), (0xFB, None), (0xFC, "reserved"), (0xFD, "reserved"), (0xFE, "error"),
    (0xFF, "not_available")])
def test_one_byte_field(decoder, raw, status):
    d = decoder.decode(frame(EEC1, bytes([0xF0, 0, raw, 0, 0, 0xFF, 0xFF, 0])))
    value = d.values["ActualEngPercentTorque"]
    assert (value is None, d.invalid.get("ActualEngPercentTorque")) == \
        ((False, None) if status is None else (True, status))
    if status is None:
        assert value == raw - 125


def test_parameter_specific_gear_is_kept(decoder):
    # ETC2 current gear 0xFB: parameter specific (park) -- a number, not null
    d = decoder.decode(frame(ETC2, bytes([125, 0xE8, 0x03, 0xFB, 0xFF, 0xFF, 0xFF, 0xFF]), sa=0x03))
    assert d.values == {"TransSelectedGear": 0, "TransActualGearRatio": 1.0, "TransCurrentGear": 126}


@pytest.mark.parametrize("top, status", [
    (0xFA, None), (0xFB, None), (0xFC, "reserved"), (0xFE, "error"), (0xFF, "not_available")])
def test_four_byte_field_judged_on_its_top_byte(decoder, top, status):
    d = decoder.decode(frame(LFC1, bytes([0, 0, 0, 0, 0x12, 0x34, 0x56, top])))
    assert d.values["EngTripFuel"] == 0
    total = d.values["EngTotalFuelUsed"]
    if status is None:
        assert total == int.from_bytes(bytes([0x12, 0x34, 0x56, top]), "little") * 0.5
    else:
        assert total is None and d.invalid["EngTotalFuelUsed"] == status


@pytest.mark.parametrize("bits, status", [(0, None), (1, None), (2, "error"), (3, "not_available")])
def test_two_bit_state(decoder, bits, status):
    # CCVS1 parking brake switch: byte 1 bits 3-4
    d = decoder.decode(frame(CCVS1, bytes([bits << 2, 0, 0, 0, 0, 0, 0, 0])))
    assert d.values["ParkingBrakeSwitch"] == (None if status else bits)
    assert d.invalid.get("ParkingBrakeSwitch") == status


def test_three_four_five_bit_fields(decoder):
    # 4 bits: EEC1 torque mode, 3 bits: DPF status, 5 bits: PTO governor state
    assert decoder.decode(frame(EEC1, bytes([0x0E]) + bytes(7))).values["EngTorqueMode"] == 14  # "other": a mode
    assert decoder.decode(frame(EEC1, bytes([0x0F]) + bytes(7))).invalid == {"EngTorqueMode": "not_available"}
    assert decoder.decode(frame(EEC1, bytes([0x0D]) + bytes(7))).values["EngTorqueMode"] == 13
    d = decoder.decode(frame(DPFC1, bytes([0x06, 0x7 << 4 | 0x2 << 2 | 0x1]) + bytes(6)))
    assert d.values == {"DPFLampCommand": None, "DPFPassiveRegenStatus": 1,
                        "DPFActiveRegenStatus": 2, "DPFStatus": None}  # 2: regeneration needed
    assert d.invalid == {"DPFLampCommand": "reserved", "DPFStatus": "not_available"}
    assert decoder.decode(frame(CCVS1, bytes(6) + bytes([30, 0]))).invalid == {"PTOGovernorState": "reserved"}
    assert decoder.decode(frame(CCVS1, bytes(6) + bytes([31, 0]))).invalid == {"PTOGovernorState": "not_available"}
    assert decoder.decode(frame(CCVS1, bytes(6) + bytes([20, 0]))).values["PTOGovernorState"] == 20


# Every bit field of the DBC, by SPN: its raw values that are states (J1939-71, checked against public
# decoders: J1939_FACTS.md); the all-ones value is not available; anything else is reserved, except the
# 2-bit switch states, where 10b is the error indicator.
BIT_FIELD_STATES = {
    899: set(range(15)),   # engine torque mode: 0-14 modes (14 "other")
    900: set(range(15)),   # retarder torque mode: the same table
    558: {0, 1},           # accelerator low-idle switch: 10b error
    70: {0, 1}, 595: {0, 1}, 597: {0, 1}, 598: {0, 1},  # switches: 10b error
    976: set(range(21)),   # PTO governor state: 0-20 states, 21-30 reserved
    977: set(range(15)),   # fan drive state: 0-14 states
    3697: {0, 1, 4},       # DPF lamp: off, on solid, on fast blink
    3699: {0, 1, 2},       # DPF passive regeneration: 2 = regeneration needed
    3700: {0, 1, 2},       # DPF active regeneration: 2 = regeneration needed
    3701: {0, 1, 2, 3},    # DPF status: regeneration not needed, needed lowest/moderate/highest
}
SWITCHES = {558, 70, 595, 597, 598}


def test_every_bit_field_follows_its_spns_definition(decoder):
    bit_fields = [(m, s) for m in decoder.db.messages for s in m.signals if s.length < 8]
    spn = lambda s: s.dbc.attributes["SPN"].value
    assert {spn(s) for _, s in bit_fields} == set(BIT_FIELD_STATES)  # a new bit field needs its row here
    for message, signal in bit_fields:
        states, all_ones = BIT_FIELD_STATES[spn(signal)], (1 << signal.length) - 1
        for raw in range(all_ones + 1):
            data = (raw << signal.start).to_bytes(message.length, "little")
            d = decoder.decode_payload(0.0, parse_id(message.frame_id).pgn, 0, 255, data)
            expected = (None if raw in states else "not_available" if raw == all_ones
                        else "error" if spn(signal) in SWITCHES and raw == 2 else "reserved")
            assert d.invalid.get(signal.name) == expected, (signal.name, raw)
            assert d.values[signal.name] == (raw if expected is None else None)


def test_short_frame_decodes_its_complete_signals_and_is_counted():
    decoder = Decoder()
    d = decoder.decode(frame(EEC1, bytes([0x01, 125, 135, 0x00])))  # speed needs bytes 4-5
    assert d.values["ActualEngPercentTorque"] == 10 and d.values["EngTorqueMode"] == 1
    assert d.values["EngSpeed"] is None and d.values["EngDemandPercentTorque"] is None
    assert d.invalid == {"EngSpeed": "missing", "EngDemandPercentTorque": "missing"}
    assert decoder.decode(frame(EEC1, b"")).invalid == dict.fromkeys(d.values, "missing")
    assert decoder.stats.short_frames == 2
    assert decoder.counters()["missing"] == 7


def test_full_length_frame_is_not_short():
    decoder = Decoder()
    decoder.decode(frame(EEC1, bytes(8)))
    assert decoder.stats.short_frames == 0


def test_two_sources_of_ccvs1_are_kept_apart(decoder):
    engine = decoder.decode(frame(CCVS1, bytes.fromhex("F3341703CC00FFFF"), sa=0x00))
    cab = decoder.decode(frame(CCVS1, b"\xff" * 8, sa=0x31))
    assert (engine.sa, cab.sa) == (0x00, 0x31)
    assert engine.values["WheelBasedVehicleSpeed"] == 0x1734 / 256
    assert cab.values["WheelBasedVehicleSpeed"] is None
    assert engine.to_record()["sa"] == 0 and cab.to_record()["sa"] == 0x31


def test_matches_by_pgn_for_any_priority_and_source(decoder):
    d = decoder.decode(frame(EEC1, bytes(8), sa=0x17, priority=7))
    assert (d.name, d.sa) == ("EEC1", 0x17)


def test_frames_that_are_no_j1939_message_are_counted():
    decoder = Decoder()
    assert decoder.decode(can.Message(arbitration_id=0x18FEDA00, data=bytes(8))) is None
    assert decoder.decode(can.Message(arbitration_id=0x123, is_extended_id=False, data=bytes(8))) is None
    assert decoder.decode(can.Message(arbitration_id=0x0CF00400, is_remote_frame=True)) is None
    assert decoder.decode(can.Message(arbitration_id=0x0CF00400, is_error_frame=True)) is None
    c = decoder.counters()
    assert (c["frames"], c["unknown_pgn"], c["not_j1939"], c["decoded"]) == (4, 1, 3, 0)


def test_record_layout(decoder):
    d = decoder.decode(frame(EEC1, bytes([0xF1, 125, 132, 0x50, 0x14, 0xFF, 0xFF, 0xFF]), t=12.25))
    record = d.to_record()
    assert list(record) == ["t", "pgn", "sa", "da", "EngTorqueMode", "DriversDemandEngPercentTorque",
                            "ActualEngPercentTorque", "EngSpeed", "EngDemandPercentTorque", "invalid"]
    assert record["EngSpeed"] == 650.0 and record["EngDemandPercentTorque"] is None
    assert record["invalid"] == {"EngDemandPercentTorque": "not_available"}
    json.dumps(record, allow_nan=False)
    tp = decoder.decode_payload(3.0, EC1, 0, 255, bytes(39), tp="bam").to_record()
    assert tp["tp"] == "bam"


def test_ec1_reference_torque_from_a_reassembled_payload(decoder):
    payload = bytearray(b"\xff" * 39)
    payload[0:2] = (650 * 8).to_bytes(2, "little")
    payload[19:21] = (2386).to_bytes(2, "little")
    payload[30:32] = (956).to_bytes(2, "little")
    d = decoder.decode_payload(7.0, EC1, 0x00, 255, bytes(payload), tp="bam")
    assert d.values == {"EngSpeedAtIdlePoint1": 650.0, "EngReferenceTorque": 2386,
                        "EngMomentOfInertia": pytest.approx(3.824)}
    assert d.tp == "bam"


@pytest.mark.parametrize("payload, vin", [
    (b"1HGCM82633A004352*", "1HGCM82633A004352"),
    (b"1HGCM82633A004352*\xff\xff\xff", "1HGCM82633A004352"),
    (b"1HGCM82633A004352", "1HGCM82633A004352"),
    (b"  1HGCM82633A004352\x00\x00*garbage*", "1HGCM82633A004352"),
])
def test_vin(decoder, payload, vin):
    d = decoder.decode_payload(1.0, VI, 0x00, 255, payload, tp="bam")
    assert d.to_record() == {"t": 1.0, "pgn": VI, "sa": 0, "da": 255, "VIN": vin, "invalid": {}, "tp": "bam"}


def test_empty_vin_is_not_available(decoder):
    d = decoder.decode_payload(1.0, VI, 0x00, 255, b"\xff" * 9 + b"*")
    assert d.values == {"VIN": None} and d.invalid == {"VIN": "not_available"}


@pytest.mark.parametrize("payload", [
    b"1HGCM82633A004352XYZ",         # printable garbage after the 17 characters
    b"1HGCM82633A004352/../..*",
    b"1HGCM82633A00435*",            # 16 characters
    b"1HGCM82633A0O4352*",           # O is not in the VIN alphabet (nor I, Q)
    b"\x011HG\xfeCM826\x0733A004352*",  # bytes dropped from the middle would make one up
    b"1hgcm82633a004352*",           # lower case
])
def test_anything_but_17_vin_characters_is_not_a_vin(decoder, payload):
    d = decoder.decode_payload(1.0, VI, 0x00, 255, payload)
    assert d.values == {"VIN": None} and d.invalid == {"VIN": "reserved"}


def test_schema_describes_every_signal_with_spn_and_unit(decoder):
    for name in decoder.message_names():
        schema = message_schema(name)
        assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
        props = schema["properties"]
        for signal in decoder.signal_names(name):
            assert "SPN " in props[signal]["description"]
        assert set(schema["required"]) <= set(props)
    assert message_schema("EEC1")["properties"]["EngSpeed"]["description"].endswith("[rpm]")
    assert "SPN 190" in message_schema("EEC1")["properties"]["EngSpeed"]["description"]
    assert "[L/h]" in message_schema("LFE1")["properties"]["EngFuelRate"]["description"]
    assert set(message_schema("EEC1")["properties"]["invalid"]["additionalProperties"]["enum"]) == \
        set(INVALID_STATUSES)


def test_records_have_exactly_the_schema_fields(decoder):
    for name in decoder.message_names():
        record = decoder.decode_payload(0.0, decoder.db.get_message_by_name(name).frame_id >> 8 & 0x3FFFF,
                                        0, 255, bytes(39), tp="rts").to_record()
        assert set(record) == set(message_schema(name)["properties"])


ids = st.integers(0, 0x1FFFFFFF)
known_ids = st.sampled_from([EEC1, CCVS1, ETC2, LFC1, DPFC1, EC1, VI, 65269, 65262]).flatmap(
    lambda pgn: st.integers(0, 255).map(lambda sa: make_id(pgn, sa)))


@settings(max_examples=400, deadline=None)
@given(st.one_of(ids, known_ids), st.binary(max_size=64), st.booleans(), st.booleans(), st.booleans())
def test_fuzz_decoder_never_raises_and_nulls_always_say_why(can_id, data, extended, remote, error):
    decoder = Decoder()
    msg = can.Message(arbitration_id=can_id if extended else can_id & 0x7FF, is_extended_id=extended,
                      is_remote_frame=remote, is_error_frame=error, data=data, is_fd=len(data) > 8)
    d = decoder.decode(msg)
    if d is None:
        return
    assert set(d.values) == set(decoder.signal_names(d.name))
    for signal, value in d.values.items():
        if value is None:
            assert d.invalid[signal] in INVALID_STATUSES
        else:
            assert signal not in d.invalid
            assert isinstance(value, str) or math.isfinite(value)
    json.dumps(d.to_record(), allow_nan=False)
