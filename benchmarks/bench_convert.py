"""Decode + MCAP write throughput against python-can's own writers, on the same FMS-like frames, in one run.

    .venv/bin/python benchmarks/bench_convert.py [--frames 200000] [--repeat 3]

The frame stream mixes the FMS messages at their bus rates (EEC1 every 20 ms, EEC2 50 ms, LFE1/CCVS1/ETC2
100 ms, EEC3 250 ms, AMB/ET1/DPFC1/FD/LFC1/HRLFC 1 s, a second ECU repeating CCVS1 and LFE1, EC1 and VI by
BAM every 5 s), with random in-range values. fuelid runs twice: as `fuelid convert` writes (no disk sync) and as the daemon does (fsync every second of
wall time, so a power cut loses at most a second). Each contender gets the frames already in memory and writes a file
in a temporary directory; the best of --repeat runs counts. One core: the process is pinned to CPU 0 where possible.
"""
import argparse
import os
import random
import tempfile
import time
from pathlib import Path

import can
import cantools

from fuelid.dbc import FMS_DBC
from fuelid.logger.recorder import Recorder, open_writer
from fuelid.logger.tp import bam_frames

PERIODS_S = {"EEC1": 0.02, "EEC2": 0.05, "LFE1": 0.1, "CCVS1": 0.1, "ETC2": 0.1, "EEC3": 0.25,
             "AMB": 1.0, "ET1": 1.0, "DPFC1": 1.0, "FD": 1.0, "LFC1": 1.0, "HRLFC": 1.0}
SECOND_ECU = {"CCVS1": 0x31, "LFE1": 0x31}


def random_values(message, rng):
    return {s.name: rng.uniform(s.minimum, s.maximum) if s.scale != 1 or s.length > 8 else rng.randint(int(s.minimum), int(s.maximum))
            for s in message.signals}


def fms_frames(n_frames: int, seed: int = 1) -> list[can.Message]:
    """An FMS-like stream of at least n_frames frames, time-ordered."""
    rng = random.Random(seed)
    db = cantools.database.load_file(FMS_DBC)
    ec1, vi = db.get_message_by_name("EC1"), db.get_message_by_name("VI")
    frames, t = [], 0.0
    next_due = {name: 0.0 for name in PERIODS_S}
    while len(frames) < n_frames:
        for name, period in PERIODS_S.items():
            if next_due[name] <= t:
                message = db.get_message_by_name(name)
                data = message.encode(random_values(message, rng), padding=True, strict=False)
                for sa in (message.frame_id & 0xFF, SECOND_ECU.get(name)):
                    if sa is not None:
                        frames.append(can.Message(timestamp=t, arbitration_id=(message.frame_id & ~0xFF) | sa, data=data))
                next_due[name] += period
        if int(t * 1000) % 5000 == 0:
            frames += bam_frames(ec1.frame_id >> 8 & 0x3FFFF, 0x00, ec1.encode(random_values(ec1, rng), padding=True, strict=False), t0=t)
            frames += bam_frames(vi.frame_id >> 8 & 0x3FFFF, 0x00, b"YS2R4X20005399401*", t0=t)
        t = round(t + 0.01, 6)
    frames.sort(key=lambda m: m.timestamp)
    return frames


def time_fuelid(frames, path: Path, fsync: bool) -> float:
    start = time.perf_counter()
    writer = open_writer(path, source="benchmark", fsync=fsync)
    recorder = Recorder(writer)
    for msg in frames:
        recorder.on_message_received(msg)
    writer.close()
    return time.perf_counter() - start


def time_python_can(writer_class, frames, path: Path) -> float:
    start = time.perf_counter()
    writer = writer_class(path)
    for msg in frames:
        writer.on_message_received(msg)
    writer.stop()
    return time.perf_counter() - start


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200_000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {0})
    frames = fms_frames(args.frames)
    contenders = {
        "fuelid convert (decode + MCAP)": lambda p: time_fuelid(frames, p.with_suffix(".mcap"), fsync=False),
        "fuelid log (+ fsync every second)": lambda p: time_fuelid(frames, p.with_suffix(".mcap"), fsync=True),
        "python-can BLFWriter (no decoding)": lambda p: time_python_can(can.BLFWriter, frames, p.with_suffix(".blf")),
        "python-can ASCWriter (no decoding)": lambda p: time_python_can(can.ASCWriter, frames, p.with_suffix(".asc")),
    }
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, run in contenders.items():
            results[name] = min(run(Path(tmp) / f"run{i}") for i in range(args.repeat))
    ours = len(frames) / results["fuelid convert (decode + MCAP)"]
    print(f"{len(frames)} frames, best of {args.repeat}, one core")
    print(f"{'writer':<40} {'frames/s':>12} {'fuelid ÷ it':>12}")
    for name, seconds in results.items():
        rate = len(frames) / seconds
        print(f"{name:<40} {rate:>12,.0f} {ours / rate:>12.2f}")
    print(f"fuelid vs a saturated 250 kbit/s bus (1,800 frames/s): {ours / 1800:.0f}x")


if __name__ == "__main__":
    main()
