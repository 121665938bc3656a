"""Peak memory and CPU of one fleet refit job's phases on many files of one truck: the dataset (fleet.jobs.job_dataset:
built from whole files evenly spaced in time, at most IDENTIFY_HOURS of them, fleet.jobs.files_sample), the model `fuelid identify` builds on
it (ident.fuellag.identify_lag_chosen, paper orders: the fuel lag and the model kind judged on held-out blocks, one
dataset held at a time), the diagnosis on the job's smaller sample (fleet.jobs.cycles_sample, DIAGNOSIS_HOURS), and
the model again with the effects the diagnosis recommends, in one process, for 1.5 h files of the shipped trip
(bench_dataset.long_recording), so memory per hour of data and per file can be read off. Limit: a truck-week
(70 h) within 1 GB.

    python benchmarks/bench_job_memory.py --hours 3 12 24 72

Each size runs in a fresh process (peak RSS only grows; Linux: /proc) with the allocator settings of a Dask worker
(WORKER_ENV); prints peak RSS [MB] after each phase and CPU [s].
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

from threadpoolctl import threadpool_limits

from fuelid.fleet.jobs import DIAGNOSIS_HOURS, IDENTIFY_HOURS, cycles_sample, files_sample, job_dataset
from fuelid.ident.diagnosis import confirmed_effects, diagnose
from fuelid.ident.fuellag import identify_lag_chosen
from fuelid.ident.identify import MIN_SEGMENT_S
from fuelid.ident.modelchoice import ModelKind, identify_chosen
from fuelid.ident.polymodel import Structure, parse_orders

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
from bench_dataset import converted_trip, long_recording, peak_rss_mb  # noqa: E402


# glibc returns freed heap memory to the system as a Dask worker's does (its nanny sets this before the worker
# starts: distributed's `nanny.pre-spawn-environ`), so that the peaks are a fleet job's
WORKER_ENV = {"MALLOC_TRIM_THRESHOLD_": "65536"}


def one_job(paths: list[str]) -> dict:
    """The phases of fleet.jobs.identify_truck up to the identification with effects, with peak RSS [MB] and CPU
    [s] after each."""
    phases, t0 = {}, time.process_time()
    structure = Structure(**parse_orders("paper"))
    with threadpool_limits(1), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        n_files = len(paths)
        paths = [paths[i] for i in files_sample(paths, IDENTIFY_HOURS)]  # as fleet.jobs.identify_truck
        built = {0.0: job_dataset(paths, 0.0)}  # as fleet.jobs.identify_truck: handed over once
        phases["dataset"] = (peak_rss_mb(), time.process_time() - t0)
        model, ds = identify_lag_chosen(
            lambda lag: built.pop(lag) if lag in built else job_dataset(paths, lag), structure,
            min_segment_s=MIN_SEGMENT_S)
        phases["identify"] = (peak_rss_mb(), time.process_time() - t0)
        sample = cycles_sample(ds, DIAGNOSIS_HOURS)
        effects = confirmed_effects(diagnose(model, sample).to_json()["candidates"])
        phases["diagnose"] = (peak_rss_mb(), time.process_time() - t0)
        if effects:
            identify_chosen(ds, structure, effects, kind=ModelKind(model.info["model_choice"]["chosen"]),
                            min_segment_s=MIN_SEGMENT_S, base=model)
        phases["identify with effects"] = (peak_rss_mb(), time.process_time() - t0)
    return {"files": n_files, "read": len(paths), "samples": int(ds.t.size), "diagnosed_samples": int(sample.t.size),
            "effects": effects, "phases": phases}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hours", type=float, nargs="+", default=[3.0, 12.0, 24.0])
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(one_job(args.child)))
        return
    files = [str(p) for p in long_recording(converted_trip(), max(args.hours))]
    print(f"{'hours':>6} {'files':>5} {'read':>4}  peak RSS [MB] after dataset / identify / diagnose / with effects   "
          "CPU [s] at each   (samples, diagnosed, effects)")
    for hours in args.hours:
        n = max(1, round(hours / 1.5))
        out = subprocess.run([sys.executable, __file__, "--child", *files[:n]], capture_output=True, text=True,
                             check=True, env=dict(os.environ, FUELID_DATASET_CACHE="0", **WORKER_ENV), cwd=REPO)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        rss = " / ".join(f"{v[0]:6.0f}" for v in r["phases"].values())
        cpu = " / ".join(f"{v[1]:5.1f}" for v in r["phases"].values())
        print(f"{n * 1.5:6.1f} {n:5d} {r['read']:4d}  {rss}      {cpu}   ({r['samples']}, {r['diagnosed_samples']}, "
              f"{','.join(r['effects']) or '-'})")


if __name__ == "__main__":
    main()
