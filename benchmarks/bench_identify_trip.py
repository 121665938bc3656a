"""The whole identification of the shipped 1.5 h trip as `fuelid identify --orders paper --no-cache` does it: the
dataset built from the converted file, then `identify_model` with the paper's orders (PEM and validation), CPU
seconds in a fresh process, two versions of fuelid alternating round by round (e.g. main's checkout against this
one). Issue 17's goal: under 2 s on one core, dataset included.

    .venv/bin/python benchmarks/bench_identify_trip.py --before /work/main/.venv/bin/python [--rounds 3] [--json]

The trip (replay_logs/diesel_ident_90min.log.gz) is converted once by this checkout's `fuelid convert`, into
benchmarks/.cache/dataset/ as `bench_dataset.py` does. Each run is its own process on CPU 0 with one BLAS thread, imports excluded from the
time (time.process_time around build_dataset and identify_model); the load average is printed with each round,
since CPU time on a shared machine still varies with what runs beside it.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

from versions import oe_iterations, worker_results


def worker(path: str):
    """Build the dataset and identify the model with the fuelid this interpreter imports; one JSON line."""
    import time
    import warnings

    from fuelid.ident.dataset import build_dataset
    from fuelid.ident.identify import identify_model
    from fuelid.ident.polymodel import PAPER_ORDERS, Structure

    t0 = time.process_time()
    with warnings.catch_warnings():  # as `fuelid identify`: the notes go to the summary, not to stderr
        warnings.simplefilter("ignore", UserWarning)
        ds = build_dataset([path], Ts=0.3, fuel="auto", max_gap_s=1.0, cycle_s=1800.0, skip_damaged=False)
    t1 = time.process_time()
    model = identify_model(ds, Structure(**PAPER_ORDERS), files=[path])
    t2 = time.process_time()
    info = model.info
    print(json.dumps({"dataset_s": t1 - t0, "identify_s": t2 - t1, "total_s": t2 - t0, "V": info["loss_V"],
                      "oe_iterations": oe_iterations(info),
                      "iterations": info["iterations"]}))


def run(python: str, path: Path) -> dict:
    """`worker` run by `python` (cwd outside the checkout: it imports its own fuelid)."""
    return worker_results(python, __file__, ["--worker", str(path)])[-1]


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--before", help="the python of the version to compare with (its own fuelid)")
    p.add_argument("--rounds", type=int, default=3, help="runs of each version, alternating")
    p.add_argument("--json", action="store_true")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    args = p.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {0})
    if args.worker:
        return worker(args.worker)
    # bench_dataset puts this checkout first on sys.path: imported here only, never by a worker of another version
    from bench_dataset import converted_trip

    path = converted_trip()
    versions = {"before": args.before, "after": sys.executable} if args.before else {"after": sys.executable}
    rounds = []
    for _ in range(args.rounds):
        rounds.append({"load": os.getloadavg()[0], **{name: run(python, path) for name, python in versions.items()}})
    if args.json:
        print(json.dumps(rounds, indent=1))
        return
    print(f"{'round':>5} {'load':>5}  " + "  ".join(f"{name + ': dataset + identify = total [CPU s]':44}" for name in versions))
    for k, r in enumerate(rounds, 1):
        print(f"{k:5d} {r['load']:5.2f}  " + "  ".join(
            f"{r[v]['dataset_s']:7.3f} + {r[v]['identify_s']:6.3f} = {r[v]['total_s']:6.3f}  V {r[v]['V']:.6f}".ljust(44)
            for v in versions))
    for v in versions:
        total = [r[v]["total_s"] for r in rounds]
        same = len({(r[v]["V"], r[v]["oe_iterations"], r[v]["iterations"]) for r in rounds}) == 1
        print(f"{v}: total {min(total):.3f}–{max(total):.3f} s (median {statistics.median(total):.3f}), "
              f"OE {rounds[0][v]['oe_iterations']} + BJ {rounds[0][v]['iterations']} iterations"
              f"{'' if same else ' (runs differ!)'}")
    if args.before:
        same = all(r["before"]["V"] == r["after"]["V"] for r in rounds)
        ratio = statistics.median(r["after"]["total_s"] for r in rounds) / statistics.median(
            r["before"]["total_s"] for r in rounds)
        print(f"V the same to the bit: {same}; after / before (medians) {ratio:.2f}×")


if __name__ == "__main__":
    main()
