"""Diagnosis time of two checkouts of fuelid side by side: `fuelid diagnose` on the 60- and 90-minute trips with a
DPF regeneration (seed 7, as `bench_diagnose.py` times them) on both engines, CPU seconds of every thread of the
process and wall seconds (each the least of 3 in a process), fresh processes alternating between the checkouts, on
one core with one BLAS thread unless asked otherwise; and whether both name, and recommend, the same effects. With
--with-worker, instead, the map engine's trips that decide issue 16's time criterion (60 and 90 min with a DPF
regeneration, 90 min with a hidden 0.4 s fuel delay, three days of 20 min with the hot intake air, as
`bench_diagnose.py --truth map` makes them), diagnosed as `fuelid diagnose` does on two cores: the models identify
would build made ahead in a worker process (workers=1), any core.

    .venv/bin/python benchmarks/bench_diagnose_versions.py --before /path/to/other/checkout [--rounds 2] [--cpu 0]
    .venv/bin/python benchmarks/bench_diagnose_versions.py --before CHECKOUT --cpu -1 --blas-threads 2  # all cores
    .venv/bin/python benchmarks/bench_diagnose_versions.py --before CHECKOUT --with-worker             # issue 16's time

Both checkouts run with this interpreter (so with the same dependencies), each importing its own fuelid and
tests/ident/hidden.py (sys.path[0] = the checkout), e.g. `git worktree add --detach /tmp/base main` for main.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import NamedTuple

from versions import worker_results



class Case(NamedTuple):
    """A simulated trip (tests.ident.hidden.simulated: hidden effect, seed, minutes per day, days, engine truth)."""

    truth: str
    minutes: int
    effect: str = "dpf_regeneration"
    seed: int = 7
    days: int = 1

    def label(self) -> str:
        days = f" × {self.days}" if self.days > 1 else ""
        effect = "" if self.effect == "dpf_regeneration" else f", {self.effect}"
        return f"{self.minutes} min{days}{effect}"


CASES = [Case("diesel_p320", 60), Case("diesel_p320", 90), Case("map", 60), Case("map", 90)]
WORKER_CASES = [Case("map", 60), Case("map", 90), Case("map", 90, "fuel_delay"),
                Case("map", 20, "hot_intake_air", 3000, days=3)]


def worker(root: str, case: Case, workers: int):
    """Diagnose the trip with the fuelid of checkout `root` (`workers` processes building ahead); one JSON line:
    least CPU (this process's threads) and wall time [s] of 3, effects named and recommended."""
    sys.path.insert(0, root)  # the checkout's fuelid, imported only now
    import time
    import warnings

    from fuelid.ident import diagnosis as dg
    from tests.ident import hidden

    warnings.simplefilter("ignore")
    ds, _, _ = hidden.simulated(case.effect, case.seed, case.minutes * 60.0, truth=case.truth, days=case.days)
    model = hidden.identify(ds)
    cpu, wall = [], []
    for _ in range(3):
        t, c = time.perf_counter(), time.process_time()
        out = dg.diagnose(model, ds, workers=workers)
        cpu.append(time.process_time() - c)
        wall.append(time.perf_counter() - t)
    print(json.dumps({"cpu_s": min(cpu), "wall_s": min(wall), "named": [c.effect for c in out.candidates if c.role],
                      "recommended": [c.effect for c in out.candidates if c.recommended]}))


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--before", help="the other checkout (a directory holding fuelid/ and tests/)")
    p.add_argument("--rounds", type=int, default=2, help="processes of each checkout per case, alternating")
    p.add_argument("--cpu", type=int, default=0, help="the core every process runs on (-1: any core)")
    p.add_argument("--blas-threads", type=int, default=1, help="BLAS threads each process may run")
    p.add_argument("--with-worker", action="store_true",
                   help="issue 16's time: the map engine's trips diagnosed with a worker process, any core")
    p.add_argument("--worker", nargs=3, help=argparse.SUPPRESS)  # ROOT CASE_JSON WORKERS
    args = p.parse_args()
    cpu = -1 if args.with_worker else args.cpu  # a worker process pinned beside this one would only take turns
    if cpu >= 0 and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {cpu})  # inherited by the workers
    if args.worker:
        return worker(args.worker[0], Case(*json.loads(args.worker[1])), int(args.worker[2]))
    if not args.before:
        p.error("--before is required")
    roots = {"before": str(Path(args.before).resolve()), "after": str(Path(__file__).resolve().parents[1])}
    print(f"{'engine':12} {'trip':>22}  {'before [CPU s]':>14}  {'after [CPU s]':>13}  after/before  "
          f"{'before [wall s]':>15}  {'after [wall s]':>14}  after/before  same effects named  same recommended  load")
    for case in WORKER_CASES if args.with_worker else CASES:
        runs = {name: [] for name in roots}
        for _ in range(args.rounds):
            for name, root in roots.items():
                runs[name].append(worker_results(sys.executable, __file__,
                                                 ["--worker", root, json.dumps(case), str(int(args.with_worker)),
                                                  "--cpu", str(cpu)], args.blas_threads)[-1])
        (cpu_before, cpu_after), (wall_before, wall_after) = ([min(r[key] for r in runs[n]) for n in roots]
                                                              for key in ("cpu_s", "wall_s"))
        same = [runs["before"][-1][key] == runs["after"][-1][key] for key in ("named", "recommended")]
        print(f"{case.truth:12} {case.label():>22}  {cpu_before:14.2f}  {cpu_after:13.2f}"
              f"  {cpu_after / cpu_before:11.2f}×  "
              f"{wall_before:15.2f}  {wall_after:14.2f}  {wall_after / wall_before:11.2f}×  {str(same[0]):>18}"
              f"  {str(same[1]):>16}"
              f"  {os.getloadavg()[0]:.2f}", flush=True)


if __name__ == "__main__":
    main()
