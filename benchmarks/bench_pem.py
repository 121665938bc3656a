"""Box-Jenkins PEM on the paper's orders: fuelid vs SIPPY vs statsmodels SARIMAX, side by side in one run.

    .venv/bin/python benchmarks/bench_pem.py [--quick] [--timeout 900] [--json]

Data: 18,000 samples at Ts = 0.3 s simulated from the appendix diesel model (paper_models.json; printed D
stabilised) on truck-like inputs (tests/ident/synthetic.py), a second record with another seed for validation.
Orders: Gw nb=4 nf=5 nk=3, GT nb=5 nf=5 nk=0, C and D 11 (41 parameters). Reported per tool: wall time of the
estimation, simulation fit [%] on the validation record (against the measured and the noise-free output), and
whether the returned predictor is stable (largest root radius of F, C, D; ε = D/C (y − Σ B/F u) needs F and C
inside the unit circle, a stationary noise model needs D inside too).

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

HERE = Path(__file__).resolve().parent
PEERS = HERE / ".venv-peers"
PEER_PYTHON = PEERS / "bin" / "python"
NB, NF, NK, NC = (4, 5), 5, (3, 0), 11
FIR_TAPS = 15
ONE_CORE_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


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
                                  env={**os.environ, **ONE_CORE_ENV})
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


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="skip the peers (SIPPY, SARIMAX)")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds allowed to each peer (default 900)")
    p.add_argument("--repeat", type=int, default=3, help="fuelid runs; the median time counts")
    p.add_argument("--json", action="store_true")
    p.add_argument("--peer", choices=["sippy", "sarimax"], help=argparse.SUPPRESS)
    p.add_argument("--data", help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    args = p.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {0})
    if args.peer:
        return peer_main(args)

    import warnings

    import numpy as np

    sys.path.insert(0, str(HERE.parent))
    from fuelid.ident.modelfile import load_paper_model
    from fuelid.ident.pem import pem
    from tests.ident.synthetic import paper_data, true_model

    paper = load_paper_model("diesel_scania_p320")
    truth = true_model(paper)
    u, y, _ = paper_data(truth, seed=0)
    u_val, y_val, y0_val = paper_data(truth, seed=1)
    results = {}

    times = []
    for _ in range(max(1, args.repeat)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t0 = time.perf_counter()
            model = pem(u, y, paper.structure, 0.3)
            times.append(time.perf_counter() - t0)
    results["fuelid"] = {"status": "ok", "wall_time_s": float(np.median(times)), "iterations": model.info["iterations"],
                         "converged": model.info["converged"], "stop_reason": model.info["stop_reason"],
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

    if args.json:
        print(json.dumps(results, indent=1))
        return
    print(f"BJ PEM, 18,000 samples, Ts 0.3 s, paper orders (41 parameters), one core")
    print(f"{'tool':8} {'status':22} {'time [s]':>9} {'× fuelid':>9} {'fit val %':>9} {'fit true %':>10} {'|root| F/C/D':>20} stable")
    for name, r in results.items():
        t = f"{r['wall_time_s']:9.2f}" if "wall_time_s" in r else " " * 9
        ratio = f"{r['time_ratio_vs_fuelid']:9.0f}" if "time_ratio_vs_fuelid" in r else " " * 9
        if "fit_validation_pct" in r:
            rr = r["max_root_radius"]
            tail = (f"{r['fit_validation_pct']:9.2f} {r['fit_noise_free_pct']:10.2f} "
                    f"{rr['F']:6.4f}/{rr['C']:6.4f}/{rr['D']:6.4f} {r['stable']}")
        else:
            tail = ""
        print(f"{name:8} {r['status'][:22]:22} {t} {ratio} {tail}")
    f = results["fuelid"]
    print(f"fuelid {'converged' if f['converged'] else 'did NOT converge'} ({f['stop_reason']}) after "
          f"{f['iterations']} iterations")


if __name__ == "__main__":
    main()
