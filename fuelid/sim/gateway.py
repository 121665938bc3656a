"""The FMS gateway: which J1939 messages the truck sends, from which source address, how often, and their bytes.

Frames are scheduled at each message's period with a random phase and small timing jitter (`schedule`), sampled from the
simulator's fine-grid signals, quantised exactly as the DBC scales them (cantools' rounding) and clipped to the
valid range; a few values are sent as "not available" (all ones), as ECUs do during start-up or for a missing
sensor. A cab controller (SA 0x31) repeats CCVS1 and LFE1 as real trucks do (its LFE1 carries no fuel rate, as
in the recorded truck in ../shared/real_logs). EC1 and VI go by TP BAM (logger.tp.bam_frames).

Hand-written packing (`pack`) instead of cantools' Message.encode: encoding a 1.5 h trip frame by frame takes
cantools about 20 s, packing whole columns with numpy well under a second. It reads start bit, length, scale
and offset from the DBC, so the DBC stays the single source of truth, and tests compare it with cantools.
"""
from dataclasses import dataclass, field

import cantools
import numpy as np

from fuelid.dbc import FMS_DBC
from fuelid.logger.tp import bam_frames

CAN_CHANNEL = "can0"
ENGINE_SA, TRANSMISSION_SA, RETARDER_SA, CAB_SA = 0x00, 0x03, 0x0F, 0x31
NA_PROBABILITY = 2e-4
"""Chance that a measured value in a frame is sent as not available [per value]."""
NA_SIGNALS = {"EEC1": ("EngSpeed", "ActualEngPercentTorque"), "LFE1": ("EngFuelRate",),
              "CCVS1": ("WheelBasedVehicleSpeed",)}
"""Signals that occasionally arrive as not available."""
ARBITRATION_LOSS_PROBABILITY = 0.05
FRAME_TIME_S = 0.000544
"""Time on the bus of one extended 8-byte frame at 250 kbit/s (~136 bits with stuffing) [s]."""


def load_dbc() -> cantools.database.can.Database:
    return cantools.database.load_file(FMS_DBC)


def max_valid_raw(length: int) -> int:
    """Largest raw value that is a valid measurement: 0xFA, 0xFAFF, 0xFAFFFFFF for 1/2/4-byte fields (above
    are error, reserved and not-available codes); small bit fields use their whole range but all-ones."""
    if length >= 8 and length % 8 == 0:
        return (0xFB << (length - 8)) - 1
    return (1 << length) - 2


def pack(message, values: dict, n: int) -> tuple[np.ndarray, dict]:
    """The data bytes (n x 8 uint8) of n frames of an 8-byte `message` and the values they carry.

    values: signal name -> physical values (array of n, NaN = not available). Missing signals and NaN stay
    all ones (not available), like every unused bit (J1939 padding). Returns the bytes and, per signal, the
    physical value after clipping to the valid raw range (NaN where not available), i.e. what a decoder
    must read back within one quantisation step.
    """
    word = np.full(n, np.iinfo(np.uint64).max, np.uint64)
    sent = {}
    for sig in message.signals:
        if sig.name not in values:
            continue
        assert sig.byte_order == "little_endian" and not sig.is_signed
        v = np.broadcast_to(np.asarray(values[sig.name], float), (n,))
        na = np.isnan(v)
        lo, hi = sig.offset, sig.offset + sig.scale * max_valid_raw(sig.length)
        v = np.clip(np.where(na, lo, v), lo, hi)
        raw = np.round((v - sig.offset) / sig.scale).astype(np.uint64)
        ones = np.uint64((1 << sig.length) - 1)
        raw = np.where(na, ones, raw)
        mask = ones << np.uint64(sig.start)
        word = (word & ~mask) | (raw << np.uint64(sig.start))
        sent[sig.name] = np.where(na, np.nan, v)
    return word.astype("<u8").view(np.uint8).reshape(n, 8), sent


@dataclass
class FrameBlock:
    """n frames of one message from one source address."""

    name: str
    can_id: int
    t: np.ndarray            # send time [s, Unix]
    data: np.ndarray         # n x 8 uint8
    values: dict = field(default_factory=dict)  # signal -> physical values sent (NaN = not available)


def schedule(period_s: float, t_start: float, t_end: float, rng: np.random.Generator) -> np.ndarray:
    """Send times [s] as CAN produces them: the sender's task runs every period on its 1 ms tick (random
    phase), the frame leaves after a fixed queueing offset (0-0.5 ms), and about one frame in twenty loses
    arbitration to one or two higher-priority frames and leaves a frame time (0.544 ms at 250 kbit/s)
    later. Discrete jitter like this is what a real bus shows, and it keeps the logs compressible."""
    phase = rng.integers(0, max(1, int(round(period_s * 1000)))) * 1e-3 + rng.uniform(0.0, 5e-4)
    t = t_start + phase + np.arange(int((t_end - t_start - phase) / period_s) + 1) * period_s
    t = t[t < t_end]
    late = rng.random(len(t)) < ARBITRATION_LOSS_PROBABILITY
    return t + np.where(late, FRAME_TIME_S * rng.integers(1, 3, len(t)), 0.0)


def can_id(message, sa: int) -> int:
    """29-bit identifier of `message` sent from source address `sa` (the DBC's id with its SA replaced)."""
    return (message.frame_id & 0x1FFFFF00) | sa


def block(db, name: str, sa: int, period_s: float, signals, t0: float, duration_s: float, dt: float,
          rng: np.random.Generator, na_probability: float = NA_PROBABILITY) -> FrameBlock:
    """Frames of message `name` from `sa` every `period_s`; signals: fine-grid arrays (or callables of the
    fine-grid sample index) per signal name."""
    message = db.get_message_by_name(name)
    t = schedule(period_s, t0, t0 + duration_s, rng)
    # the value in effect when the frame leaves: an ECU sends its latest value, never the next one
    idx = np.clip(np.floor((t - t0) / dt + 1e-9).astype(int), 0, int(round(duration_s / dt)) - 1)
    values = {k: (v(idx) if callable(v) else np.broadcast_to(np.asarray(v, float), (int(round(duration_s / dt)),))[idx])
              for k, v in signals.items()}
    for sig in NA_SIGNALS.get(name, ()):
        if sig in values:
            values[sig] = np.where(rng.random(len(t)) < na_probability, np.nan, values[sig])
    data, sent = pack(message, values, len(t))
    return FrameBlock(name, can_id(message, sa), np.round(t, 6), data, sent)


def bam_block(db, name: str, sa: int, payload: bytes, starts_s) -> FrameBlock:
    """TP BAM broadcasts of `payload` (message `name`) from `sa`, one starting at each of `starts_s` [s],
    50 ms between packets."""
    pgn = db.get_message_by_name(name).frame_id >> 8 & 0x3FFFF
    frames = [m for start in starts_s for m in bam_frames(pgn, sa, payload, float(start), gap_s=0.05)]
    return FrameBlock(f"{name}/BAM", -1, np.round(np.array([m.timestamp for m in frames]), 6),
                      np.frombuffer(b"".join(bytes(m.data) for m in frames), np.uint8).reshape(-1, 8),
                      {"can_id": np.array([m.arbitration_id for m in frames])})


def merge(blocks: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All frames in send order: times [s], 29-bit ids, n x 8 data bytes."""
    t = np.concatenate([b.t for b in blocks])
    ids = np.concatenate([b.values["can_id"] if b.can_id < 0 else np.full(len(b.t), b.can_id) for b in blocks])
    data = np.concatenate([b.data for b in blocks])
    order = np.argsort(t, kind="stable")
    return t[order], ids[order].astype(np.uint32), data[order]


def candump_lines(t: np.ndarray, ids: np.ndarray, data: np.ndarray, channel: str = CAN_CHANNEL) -> str:
    """The frames as `candump -L` text: "(1700000000.123456) can0 0CF00400#F07D7DA00D00FF7D" per line."""
    hexes = data.tobytes().hex().upper()
    return "".join(f"({ts:.6f}) {channel} {i:08X}#{hexes[16 * k:16 * k + 16]}\n"
                   for k, (ts, i) in enumerate(zip(t.tolist(), ids.tolist())))


def fms_schedule(diesel: bool) -> list:
    """(message, source address, period [s], {DBC signal: fine-grid signal key}) of the truck's periodic
    messages. The gas truck sends LFE1 without fuel rate and economy (its FMS data had no fuel rate), has an
    intake throttle, no DPF and no liquid fuel counters."""
    lfe1 = ({"EngFuelRate": "fuel_rate_l_h", "EngInstantaneousFuelEconomy": "economy_km_l"} if diesel
            else {"EngThrottleValve1Pos": "throttle_pct"})
    table = [
        ("EEC1", ENGINE_SA, 0.02, {"EngTorqueMode": "torque_mode", "DriversDemandEngPercentTorque": "driver_demand_pct",
                                   "ActualEngPercentTorque": "torque_reported_pct", "EngSpeed": "engine_speed_rpm",
                                   "EngDemandPercentTorque": "engine_demand_pct"}),
        ("EEC2", ENGINE_SA, 0.05, {"AccelPedal1LowIdleSwitch": "low_idle_switch", "AccelPedalPos1": "pedal_pct",
                                   "EngPercentLoadAtCurrentSpeed": "load_pct"}),
        ("EEC3", ENGINE_SA, 0.25, {"NominalFrictionPercentTorque": "friction_pct",
                                   "EngDesiredOperatingSpeed": "desired_speed_rpm",
                                   "EstEngParasiticLossesPercentTorque": "aux_pct"}),
        ("LFE1", ENGINE_SA, 0.1, lfe1),
        ("LFE1", CAB_SA, 0.1, {}),
        ("CCVS1", ENGINE_SA, 0.1, {"ParkingBrakeSwitch": "park_brake", "WheelBasedVehicleSpeed": "speed_kmh",
                                   "CruiseCtrlActive": "cruise_active", "BrakeSwitch": "brake_switch",
                                   "ClutchSwitch": "clutch_switch", "CruiseCtrlSetSpeed": "cruise_set_kmh"}),
        ("CCVS1", CAB_SA, 0.1, {"ParkingBrakeSwitch": "park_brake", "WheelBasedVehicleSpeed": "speed_kmh"}),
        ("ETC2", TRANSMISSION_SA, 0.1, {"TransSelectedGear": "selected_gear", "TransActualGearRatio": "gear_ratio",
                                        "TransCurrentGear": "current_gear"}),
        ("ERC1", RETARDER_SA, 0.1, {"RetarderTorqueMode": "retarder_mode",
                                    "ActualRetarderPercentTorque": "retarder_pct"}),
        ("AMB", ENGINE_SA, 1.0, {"BarometricPress": "pressure_kpa", "CabInteriorTemp": "cab_c",
                                 "AmbientAirTemp": "ambient_c", "EngAirInletTemp": "inlet_c"}),
        ("ET1", ENGINE_SA, 1.0, {"EngCoolantTemp": "coolant_c", "EngFuelTemp1": "fuel_temp_c",
                                 "EngOilTemp1": "oil_c"}),
        ("FD", ENGINE_SA, 1.0, {"EstPercentFanSpeed": "fan_pct", "FanDriveState": "fan_state"}),
    ]
    if diesel:
        table += [
            ("DPFC1", ENGINE_SA, 1.0, {"DPFLampCommand": "zero", "DPFPassiveRegenStatus": "zero",
                                       "DPFActiveRegenStatus": "dpf_active", "DPFStatus": "zero"}),
            ("LFC1", ENGINE_SA, 1.0, {"EngTripFuel": "trip_fuel_l", "EngTotalFuelUsed": "total_fuel_l"}),
            ("HRLFC", ENGINE_SA, 1.0, {"HighResEngTripFuel": "trip_fuel_l", "HighResEngTotalFuelUsed": "total_fuel_l"}),
        ]
    return table


def vi_payload(vin: str) -> bytes:
    """VI (PGN 65260) data: the VIN in ASCII, '*' terminated (SPN 237)."""
    return vin.encode("ascii") + b"*"


def fms_frames(db, signals: dict, diesel: bool, t0: float, duration_s: float, dt: float,
               rng: np.random.Generator, ec1: dict, vin: str) -> list:
    """Every frame block of the trip: the periodic messages of `fms_schedule`, EC1 by BAM every 5 s and VI by
    BAM every 10 s (0.5 s after an EC1, so the two broadcasts from SA 0x00 never overlap)."""
    blocks = [block(db, name, sa, period, {dbc: signals[key] for dbc, key in fields.items()},
                    t0, duration_s, dt, rng)
              for name, sa, period, fields in fms_schedule(diesel)]
    ec1_starts = schedule(5.0, t0, t0 + duration_s - 1.0, rng)
    ec1_payload = db.get_message_by_name("EC1").encode(ec1, padding=True)
    blocks.append(bam_block(db, "EC1", ENGINE_SA, ec1_payload, ec1_starts))
    blocks.append(bam_block(db, "VI", ENGINE_SA, vi_payload(vin), ec1_starts[::2] + 0.5))
    return blocks
