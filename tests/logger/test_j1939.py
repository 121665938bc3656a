"""29-bit identifier parsing (J1939-21 PDU1/PDU2) and the source preference table."""
from hypothesis import given, strategies as st

from fuelid.logger.j1939 import (DEFAULT_SOURCE_PREFERENCE, GLOBAL_ADDRESS, PGN_TP_CM, PGN_TP_DT, J1939Id,
                          make_id, parse_id, preferred_source)


def test_pdu2_eec1_from_the_engine():
    assert parse_id(0x0CF00400) == J1939Id(priority=3, pgn=61444, sa=0x00, da=GLOBAL_ADDRESS)


def test_pdu2_ccvs1_from_the_cab_controller():
    assert parse_id(0x18FEF131) == J1939Id(priority=6, pgn=65265, sa=0x31, da=255)


def test_pdu1_destination_is_not_part_of_the_pgn():
    # request (PGN 59904 = 0xEA00) from 0xF9 to the engine, and a TP.CM from the engine to everyone
    assert parse_id(0x18EA00F9) == J1939Id(priority=6, pgn=59904, sa=0xF9, da=0x00)
    assert parse_id(0x1CECFF00) == J1939Id(priority=7, pgn=PGN_TP_CM, sa=0x00, da=255)
    assert parse_id(0x1CEB1700) == J1939Id(priority=7, pgn=PGN_TP_DT, sa=0x00, da=0x17)


def test_data_page_bits_belong_to_the_pgn():
    assert parse_id(0x19FEF100).pgn == 0x1FEF1
    assert parse_id(0x1BEA00F9) == J1939Id(priority=6, pgn=0x3EA00, sa=0xF9, da=0x00)


@given(st.integers(0, 7), st.integers(0, 0x3FFFF), st.integers(0, 255), st.integers(0, 255))
def test_make_id_and_parse_id_round_trip(priority, pgn, sa, da):
    ident = parse_id(make_id(pgn, sa, da, priority))
    pdu1 = (pgn >> 8) & 0xFF < 240
    assert ident == J1939Id(priority, pgn & 0x3FF00 if pdu1 else pgn, sa, da if pdu1 else 255)


def test_source_preference_engine_by_default_transmission_for_etc2():
    assert preferred_source("EEC1") == 0x00
    assert preferred_source("CCVS1") == 0x00
    assert preferred_source("ETC2") == 0x03
    assert preferred_source("CCVS1", {**DEFAULT_SOURCE_PREFERENCE, "CCVS1": 0x31}) == 0x31
