"""Diagnosis time (fuelid diagnose, in one process) against trip length, on the paper engine and a VECTO map engine.

    python benchmarks/bench_diagnose.py                      # paper engine: 15/30/60/90-min trips with a DPF regeneration
    python benchmarks/bench_diagnose.py --truth map          # the default VECTO engine (325 kW)
    python benchmarks/bench_diagnose.py --truth map --engine ../shared/engines/vecto_220kW_7.7l/Engine_220kW.veng

Trips are simulated diesel trips (fuelid/sim/) decoded by fuelid's recorder (tests/ident/hidden.py), seed 7; the
model diagnosed is the one `fuelid identify` builds by default (the paper's orders, `--model auto --fuel-lag auto`:
the engine model and the fuel binned one report period earlier on a map engine), its kind and fuel lag [s] printed
in the first columns. Wall time (best of --repeat, the machine is shared) and CPU time of the process; the
peak of memory the diagnosis allocates (tracemalloc), which grows linearly with the samples (the folds' simulations
and the screening's columns are N × a few tens). The acceptance rates: benchmarks/bench_diagnosis_acceptance.py.
"""
import argparse
import sys
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fuelid.ident import diagnosis as dg  # noqa: E402
from fuelid.ident.identify import MIN_SEGMENT_S  # noqa: E402
from fuelid.ident.fuellag import identify_lag_chosen  # noqa: E402
from tests.ident import hidden  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--truth", default="diesel_p320", help="diesel_p320 (paper engine, default) or map")
    p.add_argument("--engine", default="", help="VECTO .veng for --truth map (default the 325 kW engine)")
    p.add_argument("--minutes", type=int, nargs="*", default=[15, 30, 60, 90])
    p.add_argument("--repeat", type=int, default=2)
    args = p.parse_args()
    print("model   lag s  trip     samples  wall [s]  CPU [s]  peak memory [MB]  recommended")
    for minutes in args.minutes:
        model, ds = identify_lag_chosen(
            lambda lag: hidden.simulated("dpf_regeneration", 7, minutes * 60.0, truth=args.truth, engine=args.engine,
                                         fuel_lag_s=lag)[0], hidden.PAPER, min_segment_s=MIN_SEGMENT_S)
        walls, cpus = [], []
        for _ in range(args.repeat):
            w, c = time.perf_counter(), time.process_time()
            out = dg.diagnose(model, ds)
            walls.append(time.perf_counter() - w)
            cpus.append(time.process_time() - c)
        tracemalloc.start()
        dg.diagnose(model, ds)
        peak = tracemalloc.get_traced_memory()[1] / 1e6
        tracemalloc.stop()
        rec = [c.spec or c.effect for c in out.recommended]
        if out.engine_map.status is dg.MapStatus.ADVISED:
            rec.insert(0, "engine map")
        kind = model.info["model_choice"]["chosen"]
        print(f"{kind:6s}  {ds.fuel_lag_s:5.2f}  {minutes:3d} min  {len(ds.t):7d}  {min(walls):8.2f}  {min(cpus):7.2f}  {peak:16.1f}  "
              f"{', '.join(rec) or '-'}", flush=True)


if __name__ == "__main__":
    main()
