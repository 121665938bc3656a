"""Decode + MCAP write throughput against python-can's own writers, and `fuelid convert` end to end against
`python -m can.logconvert` to BLF on a recorded candump, in one run.

    .venv/bin/python benchmarks/bench_convert.py [--frames 200000] [--repeat 3] [--candump replay_logs/diesel_ident_90min.log.gz]

In memory: the frame stream mixes the FMS messages at their bus rates (EEC1 every 20 ms, EEC2 50 ms,
LFE1/CCVS1/ETC2 100 ms, EEC3 250 ms, AMB/ET1/DPFC1/FD/LFC1/HRLFC 1 s, a second ECU repeating CCVS1 and LFE1,
EC1 and VI by BAM every 5 s), with random in-range values. fuelid runs twice: as `fuelid convert` writes (big
chunks, no disk sync) and as the daemon does (one-second chunks, fsync every second of wall time, so a power cut
loses at most a second). Each contender gets the frames already in memory and writes a file in a temporary
directory; the best of --repeat runs counts. One core: the process is pinned to CPU 0 where possible.

End to end (--candump, skipped when empty): each command runs as a user runs it, in a child process pinned to
the same core, reading the gzipped candump and writing its file, the two commands alternating; wall-clock time
(start-up, reading and writing included) and CPU time (user + sys) of the best of --repeat runs count, each as
fuelid's ÷ logconvert's (limit: wall clock ≤ 1.0×), and the file sizes are compared with the gzipped candump and with the same frames written the way
the daemon writes (one-second chunks with message indexes).
"""
import argparse
import os
import random
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import can
import cantools

from fuelid.dbc import FMS_DBC
from fuelid.logger.readers import read_frames
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


def time_fuelid(frames, path: Path, live: bool) -> float:
    start = time.perf_counter()
    writer = open_writer(path, source="benchmark", live=live)
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


def child_times(command: list[str]) -> tuple[float, float]:
    """(wall-clock, CPU time (user + sys)) [s] of running `command` to completion in a child process."""
    before, start = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    wall, after = time.perf_counter() - start, resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime


def end_to_end(candump: Path, repeat: int, tmp: Path) -> None:
    mcap, blf, live = tmp / "converted.mcap", tmp / "converted.blf", tmp / "live.mcap"
    fuelid = [str(Path(sys.executable).with_name("fuelid")), "convert", str(candump), "-o", str(mcap)]  # as installed
    logconvert = [sys.executable, "-m", "can.logconvert", str(candump), str(blf)]
    names = {"fuelid convert → MCAP (decoded channels)": fuelid, "python -m can.logconvert → BLF": logconvert}
    runs = {name: [] for name in names}
    for _ in range(repeat):  # alternating, so a burst of other work on the machine hits both alike
        for name, command in names.items():
            runs[name].append(child_times(command))
    wall = {name: min(w for w, _ in r) for name, r in runs.items()}
    cpu = {name: min(c for _, c in r) for name, r in runs.items()}
    frames = 0
    writer = open_writer(live, source="benchmark")  # the daemon's file of the same frames
    recorder = Recorder(writer)
    for msg in read_frames(candump):
        recorder.on_message_received(msg)
        frames += 1
    writer.close()
    ours = "fuelid convert → MCAP (decoded channels)"
    print(f"\nend to end on {candump} ({frames} frames), best of {repeat}, one core, load average "
          f"{os.getloadavg()[0]:.1f}")
    print(f"{'command':<45} {'wall s':>8} {'CPU s':>8} {'fuelid ÷ it: wall':>18} {'CPU':>6}")
    for name in names:
        print(f"{name:<45} {wall[name]:>8.2f} {cpu[name]:>8.2f} {wall[ours] / wall[name]:>18.2f} "
              f"{cpu[ours] / cpu[name]:>6.2f}")
    sizes = {"fuelid convert (MCAP, big chunks, no message indexes)": mcap.stat().st_size,
             "the daemon's MCAP (1 s chunks, message indexes)": live.stat().st_size,
             "BLF (can.logconvert)": blf.stat().st_size, "gzipped candump (input)": candump.stat().st_size}
    print(f"{'file':<55} {'MB':>8} {'converted ÷ it':>15}")
    for name, size in sizes.items():
        print(f"{name:<55} {size / 1e6:>8.2f} {sizes[next(iter(sizes))] / size:>15.2f}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200_000, help="in-memory frames (0: skip that part)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--candump", default="replay_logs/diesel_ident_90min.log.gz",
                        help="recorded candump for the end-to-end part ('' to skip it)")
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {0})  # inherited by the child processes
    with tempfile.TemporaryDirectory() as tmp:
        if args.frames:
            in_memory(args.frames, args.repeat, Path(tmp))
        if args.candump:
            end_to_end(Path(args.candump), args.repeat, Path(tmp))


def in_memory(n_frames: int, repeat: int, tmp: Path) -> None:
    frames = fms_frames(n_frames)
    contenders = {
        "fuelid convert (decode + MCAP)": lambda p: time_fuelid(frames, p.with_suffix(".mcap"), live=False),
        "fuelid log (+ fsync every second)": lambda p: time_fuelid(frames, p.with_suffix(".mcap"), live=True),
        "python-can BLFWriter (no decoding)": lambda p: time_python_can(can.BLFWriter, frames, p.with_suffix(".blf")),
        "python-can ASCWriter (no decoding)": lambda p: time_python_can(can.ASCWriter, frames, p.with_suffix(".asc")),
    }
    results = {name: min(run(tmp / f"run{i}") for i in range(repeat)) for name, run in contenders.items()}
    ours = len(frames) / results["fuelid convert (decode + MCAP)"]
    print(f"{len(frames)} frames in memory, best of {repeat}, one core")
    print(f"{'writer':<40} {'frames/s':>12} {'fuelid ÷ it':>12}")
    for name, seconds in results.items():
        rate = len(frames) / seconds
        print(f"{name:<40} {rate:>12,.0f} {ours / rate:>12.2f}")
    print(f"fuelid vs a saturated 250 kbit/s bus (1,800 frames/s): {ours / 1800:.0f}x")


if __name__ == "__main__":
    main()
