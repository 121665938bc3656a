"""Fault-injection sweeps: what a damaged or cut file gives, counted over thousands of cases, in one run.

    .venv/bin/python benchmarks/bench_faults.py [--flips 3000] [--seed 1]

1. MCAP, one byte flipped (xor with a random non-zero mask) at random offsets of a complete log written
   the daemon's way (~20 chunks), and of the same log cut before its footer: each read with `read_messages`
   ends in one of: the messages written (the byte was not in anything that is read), a FuelidError (refused),
   or different messages without an error (silently wrong: the count the issue asks to be zero).
   `recover` on each flipped file: messages kept vs the chunks left intact.
2. The same flips read by plain mcap (`make_reader(...).iter_messages()`), side by side: what the library
   alone returns without a word.
3. Recorded CAN files, mutated lines (a random byte of a random line replaced) and cuts at random bytes, in
   every text format: `open_frames` must never raise, every frame it gives must be in range, and a cut file
   must say `truncated`.
Measured figures go in the README ("What a fault costs you").
"""
import argparse
import json
import random
import tempfile
import time
from collections import Counter
from pathlib import Path

import can
from mcap.reader import make_reader

from fuelid.errors import FuelidError
from fuelid.logger.mcap_log import RAW_SCHEMA, McapLogWriter, raw_record, read_messages, recover
from fuelid.logger.readers import in_range, open_frames

T0 = 1_700_000_000_000_000_000  # log time origin [ns]


def write_log(path: Path, n: int = 2000) -> None:
    """A log of `n` frames 10 ms apart (1 s of log time per chunk: ~20 chunks)."""
    with McapLogWriter(path, metadata={"truck": "T1"}, fsync=False) as w:
        w.add_channel("/can/raw", RAW_SCHEMA)
        for i in range(n):
            t_ns = T0 + i * 10_000_000
            record = raw_record(can.Message(timestamp=t_ns / 1e9, arbitration_id=0x0CF00400,
                                            data=bytes([i % 256, 125, 135, 0x40, 0x1F, 0, 0, 125])))
            w.write("/can/raw", t_ns, record)


def outcome(read, expected) -> str:
    try:
        got = list(read())
    except FuelidError:
        return "refused"
    except Exception:  # noqa: BLE001 -- the plain library's own errors
        return "exception"
    return "identical" if got == expected else "silently wrong"


def plain(path: Path):
    with open(path, "rb") as f:
        for _, channel, m in make_reader(f).iter_messages(log_time_order=False):
            yield channel.topic, m.log_time, json.loads(m.data)


def sweep_mcap(flips: int, rng: random.Random, tmp: Path) -> None:
    source = tmp / "trip.mcap"
    write_log(source)
    data = source.read_bytes()
    for label, base in (("complete", data), ("cut before footer", data[: len(data) - 200])):
        ours, theirs, kept = Counter(), Counter(), []
        start = time.perf_counter()
        (tmp / "intact.mcap").write_bytes(base)
        expected = list(read_messages(tmp / "intact.mcap"))  # a cut file: the messages of its complete chunks
        for _ in range(flips):
            blob = bytearray(base)
            blob[rng.randrange(len(blob))] ^= rng.randrange(1, 256)
            bad = tmp / "bad.mcap"
            bad.write_bytes(bytes(blob))
            ours[outcome(lambda: read_messages(bad), expected)] += 1
            if label == "complete":
                theirs[outcome(lambda: plain(bad), expected)] += 1
            try:
                stats = recover(bad, tmp / "fixed.mcap")
                kept.append(sum(stats.messages.values()) / max(1, len(expected)))
            except FuelidError:
                kept.append(0.0)
        s = time.perf_counter() - start
        print(f"MCAP {label}, {flips} single-byte flips ({s:.1f} s):")
        print(f"  fuelid read_messages: {dict(ours)}")
        if theirs:
            print(f"  plain mcap reader:    {dict(theirs)}")
        kept.sort()
        print(f"  recover kept (fraction of messages): median {kept[len(kept) // 2]:.3f}, "
              f"5th percentile {kept[len(kept) // 20]:.3f}, min {kept[0]:.3f}")


def sweep_text(cases: int, rng: random.Random, tmp: Path) -> None:
    frames = [can.Message(timestamp=1_700_000_000 + i * 0.01, arbitration_id=0x18FEF100 + i % 3,
                          data=bytes([i % 256] * 8), channel=0) for i in range(500)]
    files = {}
    for name, writer in (("x.asc", can.ASCWriter), ("x.trc", can.TRCWriter), ("x.log", can.CanutilsLogWriter)):
        with writer(tmp / name) as w:
            for m in frames:
                w.on_message_received(m)
        files[name] = (tmp / name).read_bytes()
    for name, blob in files.items():
        counts = Counter()
        for k in range(cases):
            mutated = bytearray(blob)
            if k % 2:
                mutated[rng.randrange(len(mutated) // 10, len(mutated))] = rng.choice(b"0123456789ABCDEFxn.-e# \t;")
            else:
                mutated = mutated[: rng.randrange(len(mutated) // 10, len(mutated))]
            path = tmp / ("m_" + name)
            path.write_bytes(bytes(mutated))
            try:
                source = open_frames(path)
                read = list(source)
            except FuelidError:
                counts["refused"] += 1
                continue
            except Exception as exc:  # noqa: BLE001 -- the count that must stay zero
                counts[f"raised {type(exc).__name__}"] += 1
                continue
            counts["out of range frame" if not all(map(in_range, read)) else source.status] += 1
        print(f"{name}: {cases} mutations and cuts: {dict(counts)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--flips", type=int, default=3000)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    rng = random.Random(args.seed)
    with tempfile.TemporaryDirectory() as d:
        sweep_mcap(args.flips, rng, Path(d))
        sweep_text(args.flips // 3, rng, Path(d))


if __name__ == "__main__":
    main()
