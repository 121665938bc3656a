"""SAE J1939 addressing: the 29-bit CAN identifier and the parameter group numbers fuelid needs.

Identifier layout (J1939-21): priority bits 28-26, extended data page 25, data page 24, PDU format (PF)
23-16, PDU specific (PS) 15-8, source address (SA) 7-0. When PF < 240 (PDU1) the PS byte is the
destination address and is not part of the PGN; when PF >= 240 (PDU2) the message goes to everyone
(destination 255) and PS is part of the PGN.
"""
from typing import NamedTuple

import numpy as np

GLOBAL_ADDRESS = 255
"""Destination address meaning "all nodes" (also the destination of every PDU2 message)."""

PGN_TP_CM = 60416
"""TP.CM, transport protocol connection management (0xEC00): BAM, RTS, CTS, EndOfMsgAck, Abort."""
PGN_TP_DT = 60160
"""TP.DT, transport protocol data transfer (0xEB00): sequence number + 7 data bytes."""

DEFAULT_SOURCE_PREFERENCE: dict[str, int] = {"default": 0x00, "ETC2": 0x03}
"""Source address preferred per DBC message name when several nodes send one PGN: the engine (0x00)
for every message under "default", the transmission (0x03) for ETC2."""


class J1939Id(NamedTuple):
    """The fields of a 29-bit J1939 identifier."""

    priority: int
    """0 (highest) to 7."""
    pgn: int
    """Parameter group number, 18 bits; for PDU1 with the PS (destination) byte zeroed."""
    sa: int
    """Source address, 0-255."""
    da: int
    """Destination address, 0-255; 255 (global) for PDU2."""


def parse_id(can_id: int) -> J1939Id:
    """Split a 29-bit identifier into priority, PGN, source and destination address.

    >>> parse_id(0x0CF00400)
    J1939Id(priority=3, pgn=61444, sa=0, da=255)
    >>> parse_id(0x18EA00F9)  # request (PDU1) from 0xF9 to the engine
    J1939Id(priority=6, pgn=59904, sa=249, da=0)
    """
    pgn = (can_id >> 8) & 0x3FFFF
    if (pgn >> 8) & 0xFF < 240:  # PDU1: PS is the destination address
        return J1939Id((can_id >> 26) & 7, pgn & 0x3FF00, can_id & 0xFF, pgn & 0xFF)
    return J1939Id((can_id >> 26) & 7, pgn, can_id & 0xFF, GLOBAL_ADDRESS)


def parse_ids(can_id: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`parse_id` of many 29-bit identifiers at once: (PGN, source address, destination address) arrays."""
    pgn = can_id >> 8 & 0x3FFFF
    pdu1 = (pgn >> 8 & 0xFF) < 240  # PDU1: PS is the destination address
    return np.where(pdu1, pgn & 0x3FF00, pgn), can_id & 0xFF, np.where(pdu1, pgn & 0xFF, GLOBAL_ADDRESS)


def make_id(pgn: int, sa: int, da: int = GLOBAL_ADDRESS, priority: int = 6) -> int:
    """The 29-bit identifier for `pgn` sent by `sa` to `da` (ignored for PDU2 PGNs)."""
    if (pgn >> 8) & 0xFF < 240:
        pgn = (pgn & 0x3FF00) | da
    return (priority & 7) << 26 | (pgn & 0x3FFFF) << 8 | (sa & 0xFF)


def preferred_source(message: str, preference: dict[str, int] = DEFAULT_SOURCE_PREFERENCE) -> int:
    """The source address to prefer for DBC message `message` (its own entry, else "default")."""
    return preference.get(message, preference["default"])
