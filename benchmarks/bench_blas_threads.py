"""The PEM fit of the shipped 1.5 h trip with BLAS on one thread (as fuelid runs it, fuelid.blas) and on two,
wall and CPU seconds, fresh processes alternating round by round; the load average is printed with each round.

    .venv/bin/python benchmarks/bench_blas_threads.py [--rounds 5] [--json]

The problem is bench_pem_trips.py's diesel_ident_90min (built there on first use, same cache): the dataset
`fuelid identify` fits, the paper's orders. The two-thread runs replace pem's one-thread context by a limit of two
threads; both may use every core of the machine.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
PROBLEM = "diesel_ident_90min"


def worker(path: str, threads: int):
    """Fit the problem with BLAS on `threads` threads; one JSON line: wall and CPU seconds, V."""
    import time
    import warnings

    import numpy as np
    from threadpoolctl import threadpool_limits

    from fuelid.ident import pem as pem_module
    from fuelid.ident.polymodel import PAPER_ORDERS, Structure

    if threads != 1:
        pem_module.one_blas_thread = lambda: threadpool_limits(limits=threads, user_api="blas")
    d = np.load(path)
    warnings.simplefilter("ignore")
    wall, cpu = time.perf_counter(), time.process_time()
    m = pem_module.pem(d["u"], d["y"], Structure(**PAPER_ORDERS), 0.3,
                       segments=[tuple(map(int, s)) for s in d["segments"]], u0=d["u0"], y0=float(d["y0"]))
    print(json.dumps({"threads": threads, "wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu,
                      "V": m.info["loss_V"]}))


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--json", action="store_true")
    p.add_argument("--worker", nargs=2, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker:
        return worker(args.worker[0], int(args.worker[1]))
    sys.path[:0] = [str(HERE)]
    from bench_pem_trips import problems

    path = str(problems(PROBLEM)[0])
    runs = []
    for k in range(args.rounds):
        for threads in (1, 2):
            out = subprocess.run([sys.executable, __file__, "--worker", path, str(threads)], capture_output=True,
                                 text=True, check=True, cwd="/").stdout
            runs.append({**json.loads(out), "round": k + 1, "load": os.getloadavg()[0]})
            if not args.json:
                r = runs[-1]
                print(f"round {r['round']}  load {r['load']:.2f}  {threads} thread(s): wall {r['wall_s']:.2f} s, "
                      f"CPU {r['cpu_s']:.2f} s, V {r['V']:.6f}")
    summary = {t: {key: statistics.median(r[key] for r in runs if r["threads"] == t) for key in ("wall_s", "cpu_s")}
               for t in (1, 2)}
    if args.json:
        print(json.dumps({"runs": runs, "median": summary}, indent=1))
    else:
        print(f"median: one thread wall {summary[1]['wall_s']:.2f} s CPU {summary[1]['cpu_s']:.2f} s; two threads "
              f"wall {summary[2]['wall_s']:.2f} s CPU {summary[2]['cpu_s']:.2f} s "
              f"(two / one: wall {summary[2]['wall_s'] / summary[1]['wall_s']:.2f}×, "
              f"CPU {summary[2]['cpu_s'] / summary[1]['cpu_s']:.2f}×)")


if __name__ == "__main__":
    main()
