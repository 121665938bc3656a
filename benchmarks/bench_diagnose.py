"""Diagnosis time (fuelid diagnose, in one process and with workers) against trip length, on the paper engine and a
VECTO map engine.

    python benchmarks/bench_diagnose.py                      # paper engine: 15/30/60/90-min trips with a DPF regeneration
    python benchmarks/bench_diagnose.py --truth map          # the default VECTO engine (325 kW)
    python benchmarks/bench_diagnose.py --truth map --engine ../shared/engines/vecto_220kW_7.7l/Engine_220kW.veng

Each trip is diagnosed with each of --jobs (default 1 and 2: one process, and this one with a spawned worker,
fuelid.parallel, as `fuelid diagnose --jobs N` runs it; the workers started before the clock, as the command starts
them while it reads the data) and the ratio of the wall times against the first printed; the diagnoses must be the
same (the benchmark stops if not).

Trips are simulated diesel trips (fuelid/sim/) decoded by fuelid's recorder (tests/ident/hidden.py), seed 7; the
model diagnosed is the one `fuelid identify` builds by default (the paper's orders, `--model auto --fuel-lag auto`:
the engine model and the fuel binned one report period earlier on a map engine), its kind and fuel lag [s] printed
in the first columns. Wall time (best of --repeat, the machine is shared) and CPU time of this process (the workers'
not counted); the peak of memory the diagnosis allocates in one process (tracemalloc, with the first of --jobs) and a
worker's peak resident memory (its imports and the data of its calls: a copy of the dataset each), which grow
linearly with the samples (the folds' simulations
and the screening's columns are N × a few tens). The acceptance rates: benchmarks/bench_diagnosis_acceptance.py.
"""
import argparse
import json
import sys
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fuelid.ident import diagnosis as dg  # noqa: E402
from fuelid.ident.identify import MIN_SEGMENT_S  # noqa: E402
from fuelid.ident.fuellag import identify_lag_chosen  # noqa: E402
from fuelid.output import json_safe  # noqa: E402
from fuelid.parallel import jobs, side_by_side  # noqa: E402
from tests.ident import hidden  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_dataset import peak_rss_mb  # noqa: E402  (VmHWM, called in a worker: its own peak)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--truth", default="diesel_p320", help="diesel_p320 (paper engine, default) or map")
    p.add_argument("--engine", default="", help="VECTO .veng for --truth map (default the 325 kW engine)")
    p.add_argument("--minutes", type=int, nargs="*", default=[15, 30, 60, 90])
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--jobs", type=int, nargs="*", default=[1, 2], help="process counts to time (the first the base)")
    args = p.parse_args()
    print("model   lag s  trip     samples  jobs  wall [s]  CPU [s]  ratio  peak memory [MB]  worker RSS [MB]  "
          "recommended")
    for minutes in args.minutes:
        model, ds = identify_lag_chosen(
            lambda lag: hidden.simulated("dpf_regeneration", 7, minutes * 60.0, truth=args.truth, engine=args.engine,
                                         fuel_lag_s=lag)[0], hidden.PAPER, min_segment_s=MIN_SEGMENT_S)
        kind = model.info["model_choice"]["chosen"]
        first, same = None, None
        for n in args.jobs:
            walls, cpus = [], []
            with jobs(n, ["fuelid.ident.diagnosis"]):
                side_by_side([int] * n)  # the workers up
                for _ in range(args.repeat):
                    w, c = time.perf_counter(), time.process_time()
                    out = dg.diagnose(model, ds)
                    walls.append(time.perf_counter() - w)
                    cpus.append(time.process_time() - c)
                # the worker's peak resident memory (its imports and its calls' data): asked of it by a call
                worker = side_by_side([peak_rss_mb] * n)[-1] if n > 1 else float("nan")
            result = json.dumps(json_safe(out.to_json()), sort_keys=True)
            if same is not None and result != same:
                raise SystemExit(f"the diagnosis with {n} jobs differs from the one with {args.jobs[0]}")
            same = same or result
            if first is None:
                first = min(walls)
                tracemalloc.start()
                dg.diagnose(model, ds)
                peak = tracemalloc.get_traced_memory()[1] / 1e6
                tracemalloc.stop()
            rec = [c.spec or c.effect for c in out.recommended]
            if out.engine_map.status is dg.MapStatus.ADVISED:
                rec.insert(0, "engine map")
            print(f"{kind:6s}  {ds.fuel_lag_s:5.2f}  {minutes:3d} min  {len(ds.t):7d}  {n:4d}  {min(walls):8.2f}  "
                  f"{min(cpus):7.2f}  {min(walls) / first:5.2f}  {peak:16.1f}  {worker:15.0f}  {', '.join(rec) or '-'}",
                  flush=True)


if __name__ == "__main__":
    main()
