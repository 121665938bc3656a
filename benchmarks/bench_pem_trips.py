"""The PEM on every shipped trip and on the diagnosis tests' simulated cases: loss V, iterations and CPU time of
two versions of fuelid side by side in one run (e.g. main's checkout against this one).

    .venv/bin/python benchmarks/bench_pem_trips.py --before /work/main/.venv/bin/python [--only SUBSTRING]
        [--repeat N] [--perturb EPS] [--json]

Problems (cached in benchmarks/.cache/pem/trips/, built with this checkout's dataset code): every
replay_logs/{diesel,map,effect,map_effect}_*.log.gz converted and built into the dataset `fuelid identify` fits
(its segments, operating point; the paper's orders), and the simulated cases of
tests/ident/diagnosis/test_hidden_effects.py whose start is hard for the OE initialisation: the ambient effect's three trips identified together (seeds 2004
and 3004) and one trip with nothing hidden (seed 11), identified as tests.ident.hidden.identify does. Each version
fits every problem in its own subprocess on CPU 0 (one BLAS thread); CPU seconds of `pem` are reported
(time.process_time, the least of --repeat fits), and V after / V before − 1. Without --before the one version is
compared with itself.
--perturb EPS fits each problem twice more, its fuel (and operating point) multiplied by 1 + EPS and 1 − EPS, and
reports the spread of V over the three (largest / smallest − 1) per problem and the largest: how far the fit's
minimum moves when only the last bits of the data do (EPS = 1e-12), which no physics can tell apart. The goal is a
spread below SPREAD_GOAL on every problem (docs/explanation/numerics.md):

    .venv/bin/python benchmarks/bench_pem_trips.py --perturb 1e-12
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from versions import oe_iterations, worker_results

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
CACHE = HERE / ".cache" / "pem" / "trips"
FAMILIES = ("diesel_", "map_", "effect_", "map_effect_")
SIMULATED = (("ambient", 2004), ("ambient", 3004), (None, 11))
SPREAD_GOAL = 1e-3  # the largest spread of V under the perturbation that is accepted (0.1 %)


def save(name, u, y, segments, u0, y0):
    import numpy as np

    np.savez(CACHE / f"{name}.npz", u=u, y=y, u0=u0, y0=y0, segments=[(s.start, s.stop) for s in segments])


def problems(only: str) -> list[Path]:
    """The cached problems (built on first use) whose name contains `only`."""
    import warnings

    sys.path[:0] = [str(REPO)]
    CACHE.mkdir(parents=True, exist_ok=True)
    trips = sorted(p for p in (REPO / "replay_logs").glob("*.log.gz") if p.name.startswith(FAMILIES))
    for log in trips:
        name = log.name.removesuffix(".log.gz")
        if only in name and not (CACHE / f"{name}.npz").exists():
            from fuelid.ident.dataset import build_dataset
            from fuelid.ident.identify import training_segments

            mcap = CACHE / f"{name}.mcap"
            subprocess.run([sys.executable, "-m", "fuelid.cli", "convert", str(log), "-o", str(mcap), "--json"],
                           check=True, stdout=subprocess.DEVNULL, cwd=REPO)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ds = build_dataset([mcap])
            save(name, ds.u, ds.y, training_segments(ds, ds.u, ds.y, 30.0), ds.u0, ds.y0)
            mcap.unlink()
    from fuelid.sim.catalog import ALL_EFFECT_TRIPS

    for effect, seed in SIMULATED:
        n_trips = len(ALL_EFFECT_TRIPS.get(effect, ((),)))  # in the name: a cache of another set is never served
        name = f"simulated_{effect or 'nothing'}_{seed}" + (f"_{n_trips}_trips" if n_trips > 1 else "")
        if only in name and not (CACHE / f"{name}.npz").exists():
            from tests.ident import hidden

            ds, _, _ = hidden.simulated(effect, seed)
            save(name, ds.u, ds.y, [s for s in ds.segments() if s.stop - s.start > 100], ds.u0, ds.y0)
    return sorted(p for p in CACHE.glob("*.npz") if only in p.stem)


def worker(paths, repeat: int, perturb: float):
    """Fit each problem `repeat` times with the fuelid this interpreter imports; one JSON line each (the least
    CPU time); with perturb > 0, once more with the fuel scaled by 1 + perturb and by 1 − perturb (V_spread)."""
    import warnings

    import numpy as np

    from fuelid.ident.pem import pem
    from fuelid.ident.polymodel import PAPER_ORDERS, Structure

    structure = Structure(**PAPER_ORDERS)
    warnings.simplefilter("ignore")
    for path in paths:
        d = np.load(path)
        cpu = float("inf")
        for _ in range(repeat):
            t0 = time.process_time()
            m = fitted_model(pem, structure, d)
            cpu = min(cpu, time.process_time() - t0)
        info = m.info
        vs = [info["loss_V"]] + [fitted_model(pem, structure, d, 1.0 + k * perturb).info["loss_V"]
                                 for k in ((1, -1) if perturb else ())]
        print(json.dumps({"problem": Path(path).stem, "V": info["loss_V"], "cpu_s": cpu,
                          "V_spread": max(vs) / min(vs) - 1,
                          "oe_iterations": oe_iterations(info),
                          "iterations": info["iterations"], "stop_reason": info["stop_reason"]}), flush=True)


def fitted_model(pem, structure, d, factor: float = 1.0):
    """`pem` of `structure` (Ts = 0.3 s) on problem d, its fuel [L/h] and fuel operating point multiplied by factor."""
    return pem(d["u"], d["y"] * factor, structure, 0.3,
               segments=[tuple(map(int, s)) for s in d["segments"]], u0=d["u0"], y0=float(d["y0"]) * factor)


def fitted(python: str, paths, repeat: int, perturb: float) -> dict:
    """{problem: result} of `worker` run by `python` (cwd outside the checkout: it imports its own fuelid)."""
    args = ["--repeat", str(repeat), "--perturb", repr(perturb), "--worker", *map(str, paths)]
    return {r["problem"]: r for r in worker_results(python, __file__, args)}


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--before", required=False, help="the python of the version to compare with (its own fuelid)")
    p.add_argument("--only", default="", help="problems whose name contains this")
    p.add_argument("--repeat", type=int, default=1, help="fits per problem and version; the least CPU time counts")
    p.add_argument("--perturb", type=float, default=0.0,
                   help="also fit with the fuel scaled by 1 ± this (e.g. 1e-12) and report the spread of V")
    p.add_argument("--json", action="store_true")
    p.add_argument("--worker", nargs="*", help=argparse.SUPPRESS)
    args = p.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {0})
    if args.worker is not None:
        return worker(args.worker, args.repeat, args.perturb)
    paths = problems(args.only)
    before = fitted(args.before, paths, args.repeat, args.perturb) if args.before else {}
    after = fitted(sys.executable, paths, args.repeat, args.perturb)
    rows = [{"problem": k, "before": before.get(k), "after": a} for k, a in after.items()]
    if args.json:
        print(json.dumps(rows, indent=1))
        return
    spread = " V spread % (1 ± perturb)" if args.perturb else ""
    print(f"{'problem':38} {'V before':>11} {'V after':>11} {'ΔV %':>7} {'OE it':>9} {'BJ it':>7} {'CPU s':>11}"
          + spread)
    worst, cpu, same, widest, over = -float("inf"), [0.0, 0.0], 0, [0.0, 0.0], [0, 0]
    for r in rows:
        a, b = r["after"], r["before"] or r["after"]
        dv = 100 * (a["V"] / b["V"] - 1)
        worst, same = max(worst, dv), same + (a["V"] == b["V"])
        cpu[0] += b["cpu_s"]
        cpu[1] += a["cpu_s"]
        widest = [max(widest[0], b["V_spread"]), max(widest[1], a["V_spread"])]
        over = [over[0] + (b["V_spread"] > SPREAD_GOAL), over[1] + (a["V_spread"] > SPREAD_GOAL)]
        print(f"{r['problem']:38} {b['V']:11.3f} {a['V']:11.3f} {dv:+7.3f} {b['oe_iterations']:4d}>{a['oe_iterations']:<4d}"
              f" {b['iterations']:3d}>{a['iterations']:<3d} {b['cpu_s']:5.2f}>{a['cpu_s']:<5.2f}"
              + (f" {100 * b['V_spread']:8.4f}>{100 * a['V_spread']:<8.4f}" if args.perturb else ""))
    print(f"worst ΔV {worst:+.3f} %, V the same to the bit on {same} of {len(rows)}, CPU total {cpu[0]:.1f} s before, "
          f"{cpu[1]:.1f} s after ({cpu[1] / cpu[0]:.2f}×)"
          + (f"; widest V spread with the fuel scaled by 1 ± {args.perturb:g}: {100 * widest[0]:.4f} % before, "
             f"{100 * widest[1]:.4f} % after; above {100 * SPREAD_GOAL:g} %: {over[0]} before, {over[1]} after"
             if args.perturb else ""))


if __name__ == "__main__":
    main()
