"""The gas truck's thermal mass-flow meter and its ADC data logger (docs/reference/formats.md, flow-meter protocol).

    volts = clip((f (1 + g) + b + ε) / 12.5 kg/h/V, 0, 10.2 V), quantised to the 12-bit ADC step

f true gas flow [kg/h]; g gain error and b offset [kg/h] fixed per trip, ε white noise: together within the
meter's ±2 % of full scale (125 kg/h). The logger sends "<device_time_s>,<volts>" lines at 10 Hz on its own
clock (30 ppm fast); the host stamps each line on arrival (a few ms of serial latency). About one line in
10,000 arrives garbled, as on a real serial link.
"""
import os
from pathlib import Path

import numpy as np

from fuelid.logger.flowmeter import CaptureWriter
from fuelid.sim.files import gzip_file

FULL_SCALE_KG_H = 125.0
GAIN_KG_H_PER_V = 12.5
ADC_STEP_V = 10.0 / 4096
RATE_HZ = 10.0
CLOCK_DRIFT = 30e-6
GARBLED_PROBABILITY = 1e-4


def readings(t_s: np.ndarray, flow_kg_h: np.ndarray, t0: float, rng: np.random.Generator) -> dict:
    """Meter readings over the trip: host_t [s, Unix], device_t [s], volts [V], the flow they stand for
    [kg/h] and the meter's error terms. t_s, flow_kg_h: the fine-grid flow."""
    device_t = np.arange(0.0, t_s[-1], 1.0 / RATE_HZ)
    flow = np.interp(device_t, t_s, flow_kg_h)
    gain = rng.uniform(-0.008, 0.008)
    bias = rng.uniform(-0.004, 0.004) * FULL_SCALE_KG_H
    noise = np.clip(rng.normal(0.0, 0.002 * FULL_SCALE_KG_H, len(device_t)), -0.006 * FULL_SCALE_KG_H,
                    0.006 * FULL_SCALE_KG_H)
    volts = np.clip((flow * (1.0 + gain) + bias + noise) / GAIN_KG_H_PER_V, 0.0, 10.2)
    volts = np.round(volts / ADC_STEP_V) * ADC_STEP_V
    host_t = t0 + device_t * (1.0 + CLOCK_DRIFT) + 0.002 + rng.exponential(0.001, len(device_t))
    garbled = rng.random(len(device_t)) < GARBLED_PROBABILITY
    return {"host_t": host_t, "device_t": device_t, "volts": volts, "flow_kg_h": flow, "garbled": garbled,
            "gain_error": gain, "offset_error_kg_h": bias}


def lines(r: dict) -> list:
    """The serial lines (bytes, no terminator) of `readings`; a garbled line is cut and has a byte flipped."""
    out = []
    for dt, v, bad in zip(r["device_t"].tolist(), r["volts"].tolist(), r["garbled"].tolist()):
        line = b"%.2f,%.3f" % (dt, v)
        out.append(line[: len(line) // 2] + b"\xff\x00" if bad else line)
    return out


def write_capture(path: Path, r: dict) -> None:
    """Write the readings as a flow-meter capture with logger.flowmeter.CaptureWriter; a `.gz` path is
    compressed afterwards with a fixed header (mtime 0), so the same trip gives the same bytes."""
    path = Path(path)
    plain = path.with_suffix("") if path.suffix == ".gz" else path
    with CaptureWriter(plain) as writer:
        for host_t, line in zip(r["host_t"].tolist(), lines(r)):
            writer.write(host_t, line)
    if plain != path:
        gzip_file(plain, path)
        os.remove(plain)
