"""Peak memory and CPU of one fleet refit job's phases on many files of one truck: the dataset, PEM (paper
orders) and the diagnosis, in one process, for 1.5 h files of the shipped trip (bench_dataset.long_recording),
so memory per hour of data and per file can be read off.

    python benchmarks/bench_job_memory.py --hours 3 12 24

Each size runs in a fresh process (peak RSS only grows; Linux: /proc); prints peak RSS [MB] after each phase and CPU [s].
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

from fuelid.ident.dataset import build_dataset
from fuelid.ident.diagnosis import diagnose
from fuelid.ident.identify import identify_model
from fuelid.ident.polymodel import Structure, parse_orders

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
from bench_dataset import converted_trip, long_recording  # noqa: E402


def peak_rss_mb() -> float:
    """This process's peak RSS [MB]: VmHWM, which starts afresh at exec (ru_maxrss would carry the parent's)."""
    status = Path("/proc/self/status").read_text()
    return int(next(line.split()[1] for line in status.splitlines() if line.startswith("VmHWM:"))) / 1024


def one_job(paths: list[str]) -> dict:
    """The phases of fleet.jobs.identify_truck up to the diagnosis, with peak RSS [MB] and CPU [s] after each."""
    phases, t0 = {}, time.process_time()
    with threadpool_limits(1), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = build_dataset(paths)
        phases["dataset"] = (peak_rss_mb(), time.process_time() - t0)
        model = identify_model(ds, Structure(**parse_orders("paper")))
        phases["identify"] = (peak_rss_mb(), time.process_time() - t0)
        diagnose(model, ds)
        phases["diagnose"] = (peak_rss_mb(), time.process_time() - t0)
    return {"files": len(paths), "samples": int(ds.t.size), "phases": phases}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hours", type=float, nargs="+", default=[3.0, 12.0, 24.0])
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(one_job(args.child)))
        return
    files = [str(p) for p in long_recording(converted_trip(), max(args.hours))]
    print(f"{'hours':>6} {'files':>5}  peak RSS [MB] after dataset / identify / diagnose   CPU [s] at each")
    for hours in args.hours:
        n = max(1, round(hours / 1.5))
        out = subprocess.run([sys.executable, __file__, "--child", *files[:n]], capture_output=True, text=True,
                             check=True, env=dict(os.environ, FUELID_DATASET_CACHE="0"), cwd=REPO)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        rss = " / ".join(f"{v[0]:6.0f}" for v in r["phases"].values())
        cpu = " / ".join(f"{v[1]:5.1f}" for v in r["phases"].values())
        print(f"{n * 1.5:6.1f} {n:5d}  {rss}      {cpu}")


if __name__ == "__main__":
    main()
