"""Small FMS traffic for the daemon and replay tests: a candump -L log encoded with the project's DBC,
and a flow-meter capture, written the way the truck's loggers write them."""
import math
from pathlib import Path

import can
import cantools

from fuelid.dbc import FMS_DBC

VIN = "YV2RT40A5KB123456"
# message name -> (period [s], source address)
SCHEDULE = {"EEC1": (0.02, 0x00), "EEC2": (0.05, 0x00), "CCVS1": (0.1, 0x00), "LFE1": (0.1, 0x00),
            "ETC2": (0.1, 0x03), "ET1": (1.0, 0x00)}


def _signals(message, t: float) -> dict:
    # Smooth values inside each signal's range; 2-bit states 0.
    values = {}
    for s in message.signals:
        lo, hi = s.minimum, s.maximum
        if s.length <= 2:
            values[s.name] = 0
        else:
            values[s.name] = lo + (hi - lo) * (0.3 + 0.2 * math.sin(t + s.start))
    return values


def _vin_bam(t: float, sa: int = 0x00) -> list[can.Message]:
    """The VI message (PGN 65260) sent by the transport protocol's broadcast (BAM)."""
    payload = (VIN + "*").encode()
    packets = math.ceil(len(payload) / 7)
    cm = bytes([0x20, len(payload), 0, packets, 0xFF, 0xEC, 0xFE, 0x00])
    frames = [can.Message(timestamp=t, arbitration_id=0x1CECFF00 | sa, data=cm)]
    for i in range(packets):
        chunk = payload[7 * i: 7 * i + 7].ljust(7, b"\xff")
        frames.append(can.Message(timestamp=t + 0.05 * (i + 1), arbitration_id=0x1CEBFF00 | sa, data=bytes([i + 1]) + chunk))
    return frames


def frames(duration_s: float, t0: float = 1_700_000_000.0) -> list[can.Message]:
    """Frames of `duration_s` seconds of FMS traffic (about 130 frames/s), the VIN once, and one malformed
    (too short) EEC1 frame."""
    db = cantools.database.load_file(str(FMS_DBC))
    out = []
    for name, (period, sa) in SCHEDULE.items():
        message = db.get_message_by_name(name)
        for k in range(int(duration_s / period)):
            t = t0 + k * period + 0.001 * len(out) % 0.01
            data = message.encode(_signals(message, t - t0), strict=False)
            out.append(can.Message(timestamp=t, arbitration_id=(message.frame_id & ~0xFF) | sa, data=data))
    out += _vin_bam(t0 + 0.5)
    out.append(can.Message(timestamp=t0 + duration_s / 2, arbitration_id=0x0CF00400, data=b"\x01\x02"))
    out.sort(key=lambda m: m.timestamp)
    for m in out:
        m.channel = "can0"
    return out


def write_candump(path: Path, duration_s: float, t0: float = 1_700_000_000.0) -> list[can.Message]:
    msgs = frames(duration_s, t0)
    with can.CanutilsLogWriter(str(path), channel="can0") as w:
        for m in msgs:
            w.on_message_received(m)
    return msgs


def write_capture(path: Path, duration_s: float, t0: float = 1_700_000_000.0, period_s: float = 0.1) -> int:
    """A flow-meter capture (docs/reference/formats.md) at 10 readings/s, one garbage line among them; returns lines."""
    lines = ["# fuelid flowmeter capture v1"]
    n = int(duration_s / period_s)
    for k in range(n):
        t = t0 + k * period_s
        body = "\\xff\\x00garbage" if k == n // 2 else f"{k * period_s:.3f},{3 + math.sin(k / 10):.3f}"
        lines.append(f"({t:.6f}) {body}")
    path.write_text("\n".join(lines) + "\n")
    return n
