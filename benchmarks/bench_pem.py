"""Box-Jenkins PEM on the paper's orders: fuelid vs SIPPY vs statsmodels SARIMAX, side by side in one run.

    .venv/bin/python benchmarks/bench_pem.py [--quick] [--timeout 900] [--no-trip] [--json]

Data: 18,000 samples at Ts = 0.3 s simulated from the appendix diesel model (paper_models.json; printed D
stabilised) on truck-like inputs (tests/ident/synthetic.py), a second record with another seed for validation.
Orders: Gw nb=4 nf=5 nk=3, GT nb=5 nf=5 nk=0, C and D 11 (41 parameters). Reported per tool: wall time of the
estimation, simulation fit [%] on the validation record (against the measured and the noise-free output), and
whether the returned predictor is stable (largest root radius of F, C, D; ε = D/C (y − Σ B/F u) needs F and C
inside the unit circle, a stationary noise model needs D inside too).

Hard initialisation (skipped with --no-trip): the dataset of the shipped 1.5 h trip (replay_logs/diesel_ident_90min,
converted as benchmarks/bench_dataset.py does, same cache; the dataset cached in benchmarks/.cache/pem/), fitted as
`fuelid identify --orders paper` does (ident.identify.identify_model's segments and operating point). On these data
the initialisation's OE fit needs hundreds of LM iterations where the simulated data need a few dozen: both are
reported, with the share of the time spent before the final fit and the loss V (fuelid only: the peers are run
on the simulated data).

Peers run in their own environment benchmarks/.venv-peers (git-ignored), created on first use with
`python -m venv benchmarks/.venv-peers && benchmarks/.venv-peers/bin/pip install sippy_unipi statsmodels`,
each in a subprocess with --timeout seconds; --quick skips them. Everything runs on one core (CPU 0, one BLAS
thread). How each peer approximates the structure:
  SIPPY (sippy_unipi, 'BJ'): one F shared by both inputs (its BJ has one F per output), nf = 5, nb = [4, 5],
      delays [3, 0], nc = nd = 11.
  SARIMAX (statsmodels): regression with ARMA(11, 11) errors; G as FIR taps (speed lags 3..17, torque 0..14),
      no F at all: y = Σ b u(t − l) + η, D η = C e.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from versions import blas_threads_env, oe_iterations

HERE = Path(__file__).resolve().parent
PEERS = HERE / ".venv-peers"
PEER_PYTHON = PEERS / "bin" / "python"
NB, NF, NK, NC = (4, 5), 5, (3, 0), 11
FIR_TAPS = 15


# ---- peers: run inside benchmarks/.venv-peers, given u (N × 2) and y (N) in an .npz ----

def run_sippy(u, y):
    from sippy_unipi import system_identification

    m = system_identification(y[None, :], u.T, "BJ", BJ_orders=[[list(NB)], [NC], [NC], [NF], [list(NK)]],
                              tsample=0.3, max_iterations=200)
    num, den = m.NUMERATOR[0], m.DENOMINATOR[0]
    return {"B": [list(map(float, b)) for b in num], "F": [list(map(float, f)) for f in den],
            "C": list(map(float, m.NUMERATOR_H[0][0])), "D": list(map(float, m.DENOMINATOR_H[0][0]))}


def run_sarimax(u, y):
    import numpy as np
    from statsmodels.tsa.statespace.sarimax import SARIMAX

    lags = [range(NK[i], NK[i] + FIR_TAPS) for i in range(2)]
    X = np.column_stack([np.r_[np.zeros(l), u[: len(u) - l, i]] for i in range(2) for l in lags[i]])
    res = SARIMAX(y, exog=X, order=(NC, 0, NC), trend="n").fit(disp=False, maxiter=200)
    b = res.params[: X.shape[1]]
    B = [np.r_[np.zeros(NK[i]), b[i * FIR_TAPS:(i + 1) * FIR_TAPS]].tolist() for i in range(2)]
    return {"B": B, "F": [[1.0], [1.0]], "C": np.r_[1.0, res.maparams].tolist(), "D": np.r_[1.0, -res.arparams].tolist()}


def peer_main(args):
    import numpy as np

    d = np.load(args.data)
    t0 = time.perf_counter()
    polys = {"sippy": run_sippy, "sarimax": run_sarimax}[args.peer](d["u"], d["y"])
    Path(args.out).write_text(json.dumps({"wall_time_s": time.perf_counter() - t0, **polys}))


# ---- main: data, fuelid, peers in subprocesses, the table ----

def ensure_peers():
    if PEER_PYTHON.exists():
        return
    print(f"creating {PEERS} (sippy_unipi, statsmodels) ...", file=sys.stderr)
    subprocess.run([sys.executable, "-m", "venv", str(PEERS)], check=True)
    subprocess.run([str(PEERS / "bin" / "pip"), "install", "-q", "sippy_unipi", "statsmodels"], check=True)


def run_peer(name, u, y, timeout):
    import numpy as np

    with tempfile.TemporaryDirectory() as tmp:
        data, out = Path(tmp) / "data.npz", Path(tmp) / "out.json"
        np.savez(data, u=u, y=y)
        cmd = [str(PEER_PYTHON), __file__, "--peer", name, "--data", str(data), "--out", str(out)]
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout,
                                  env={**os.environ, **blas_threads_env(1)})
        except subprocess.TimeoutExpired:
            return {"status": f"timeout after {timeout:.0f} s", "wall_time_s": time.perf_counter() - t0}
        if proc.returncode != 0 or not out.exists():
            last = (proc.stderr.strip().splitlines() or ["no output"])[-1]
            return {"status": f"failed: {last[:160]}", "wall_time_s": time.perf_counter() - t0}
        return {"status": "ok", **json.loads(out.read_text())}


def assess(polys, u_val, y_val, y0_val):
    """Validation fit [%] (vs measured, vs noise-free) and the largest root radius of F, C, D."""
    import numpy as np

    from fuelid.ident.polymodel import PolyModel, simulate
    from fuelid.ident.validation import fit_percent

    m = PolyModel(A=[1.0], B=polys["B"], F=polys["F"], C=polys["C"], D=polys["D"], Ts=0.3,
                  nk=[int(np.argmax(np.asarray(b) != 0)) for b in polys["B"]])
    ys = simulate(m, u_val)
    radius = lambda p: float(np.abs(np.roots(p)).max()) if len(p) > 1 else 0.0  # noqa: E731
    r = {"F": max(radius(f) for f in m.F), "C": radius(m.C), "D": radius(m.D)}
    return {"fit_validation_pct": fit_percent(y_val, ys), "fit_noise_free_pct": fit_percent(y0_val, ys),
            "max_root_radius": r, "stable": bool(max(r.values()) < 1.0)}


def trip_data():
    """(u, y, segments, u0, y0) of the shipped 1.5 h trip's dataset as `fuelid identify` fits it (cached)."""
    import numpy as np

    cache = HERE / ".cache" / "pem" / "diesel_ident_90min.npz"
    if not cache.exists():
        import warnings

        from bench_dataset import converted_trip
        from fuelid.ident.dataset import build_dataset
        from fuelid.ident.identify import training_segments

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = build_dataset([converted_trip()])
        segs = training_segments(ds, ds.u, ds.y, 30.0)  # identify's --min-segment default
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez(cache, u=ds.u, y=ds.y, u0=ds.u0, y0=ds.y0, segments=[(s.start, s.stop) for s in segs])
    d = np.load(cache)
    return d["u"], d["y"], [tuple(map(int, s)) for s in d["segments"]], d["u0"], float(d["y0"])


def timed_pem(repeat, *args, **kw):
    """The model of the last of `repeat` pem runs and the median wall time [s]."""
    import warnings

    import numpy as np

    from fuelid.ident.pem import pem

    times = []
    for _ in range(max(1, repeat)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t0 = time.perf_counter()
            model = pem(*args, **kw)
            times.append(time.perf_counter() - t0)
    return model, float(np.median(times))


def effort(model) -> dict:
    """Iterations of the initialisation's OE and ARMA fits and of the final fit, the initialisation's share of
    the time, the loss V."""
    info = model.info
    return {"oe_iterations": oe_iterations(info),
            "arma_iterations": info["initialisation_iterations"]["arma"], "iterations": info["iterations"],
            "initialisation_share": info["initialisation_time_s"] / info["wall_time_s"], "loss_V": info["loss_V"],
            "converged": info["converged"], "stop_reason": info["stop_reason"]}


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="skip the peers (SIPPY, SARIMAX)")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds allowed to each peer (default 900)")
    p.add_argument("--repeat", type=int, default=3, help="fuelid runs; the median time counts")
    p.add_argument("--no-trip", action="store_true", help="skip the shipped 1.5 h trip (hard initialisation)")
    p.add_argument("--json", action="store_true")
    p.add_argument("--peer", choices=["sippy", "sarimax"], help=argparse.SUPPRESS)
    p.add_argument("--data", help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    args = p.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {0})
    if args.peer:
        return peer_main(args)

    sys.path[:0] = [str(HERE.parent), str(HERE)]
    from fuelid.ident.modelfile import load_paper_model
    from tests.ident.synthetic import paper_data, true_model

    paper = load_paper_model("diesel_scania_p320")
    truth = true_model(paper)
    u, y, _ = paper_data(truth, seed=0)
    u_val, y_val, y0_val = paper_data(truth, seed=1)
    results = {}

    model, wall = timed_pem(args.repeat, u, y, paper.structure, 0.3)
    results["fuelid"] = {"status": "ok", "wall_time_s": wall, **effort(model),
                         **assess({"B": model.B, "F": model.F, "C": model.C, "D": model.D}, u_val, y_val, y0_val)}
    results["truth"] = {"status": "reference", **assess({"B": truth.B, "F": truth.F, "C": truth.C, "D": truth.D},
                                                        u_val, y_val, y0_val)}
    if not args.quick:
        ensure_peers()
        for name in ("sippy", "sarimax"):
            r = run_peer(name, u, y, args.timeout)
            if r["status"] == "ok":
                r.update(assess(r, u_val, y_val, y0_val))
            results[name] = {k: v for k, v in r.items() if k not in ("B", "F", "C", "D")}
    for name in ("sippy", "sarimax"):
        if name in results:
            results[name]["time_ratio_vs_fuelid"] = results[name]["wall_time_s"] / results["fuelid"]["wall_time_s"]

    if not args.no_trip:
        tu, ty, segments, u0, y0 = trip_data()
        model, wall = timed_pem(args.repeat, tu, ty, paper.structure, 0.3, segments=segments, u0=u0, y0=y0)
        results["fuelid_trip"] = {"status": "ok", "wall_time_s": wall, "samples": len(ty), **effort(model)}
    if args.json:
        print(json.dumps(results, indent=1))
        return
    print(f"BJ PEM, 18,000 samples, Ts 0.3 s, paper orders (41 parameters), one core")
    print(f"{'tool':8} {'status':22} {'time [s]':>9} {'× fuelid':>9} {'fit val %':>9} {'fit true %':>10} {'|root| F/C/D':>20} stable")
    for name, r in ((n, r) for n, r in results.items() if n != "fuelid_trip"):
        t = f"{r['wall_time_s']:9.2f}" if "wall_time_s" in r else " " * 9
        ratio = f"{r['time_ratio_vs_fuelid']:9.0f}" if "time_ratio_vs_fuelid" in r else " " * 9
        if "fit_validation_pct" in r:
            rr = r["max_root_radius"]
            tail = (f"{r['fit_validation_pct']:9.2f} {r['fit_noise_free_pct']:10.2f} "
                    f"{rr['F']:6.4f}/{rr['C']:6.4f}/{rr['D']:6.4f} {r['stable']}")
        else:
            tail = ""
        print(f"{name:8} {r['status'][:22]:22} {t} {ratio} {tail}")
    print(f"{'fuelid on':14} {'time [s]':>9} {'init share':>10} {'OE it':>6} {'ARMA it':>7} {'final it':>8} "
          f"{'loss V':>12} stop")
    for name, label in (("fuelid", "simulated"), ("fuelid_trip", "shipped trip")):
        if name in results:
            f = results[name]
            print(f"{label:14} {f['wall_time_s']:9.2f} {100 * f['initialisation_share']:9.0f}% {f['oe_iterations']:6d} "
                  f"{f['arma_iterations']:7d} {f['iterations']:8d} {f['loss_V']:12.4f} "
                  f"{'converged' if f['converged'] else 'NOT converged'} ({f['stop_reason']})")


if __name__ == "__main__":
    main()
