"""Online update rate for the paper's orders (41 parameters) against re-running the offline PEM on a growing
window, on the same data, in one run.

    .venv/bin/python benchmarks/bench_online.py [--samples 200000] [--window-samples 20000] [--refit-every 1000]

Data: the appendix diesel model (tests/ident/synthetic.py, noise std 0.5 L/h) on truck-like inputs. Contenders:
  rpem     ident.rpem.RPEM from scratch over all --samples (compiled loop; the JIT compile is done before timing)
  kalman   ident.kalman.ParameterKalman from the PEM model (random-walk fuel gain)
  pem      ident.pem.pem refitted every --refit-every new samples on all samples so far (warm-started from the
           previous fit), over the first --window-samples: what keeping a model current offline costs
Rates are samples processed per second of wall time on one core (the process is pinned to CPU 0 where possible);
the goal is ≥ 50,000 samples/s (a week at Ts = 0.3 s, 2.0 M samples, in under a minute). The simulated fit of
each final model on the window is printed for comparison.
"""
import argparse
import os
import sys
import time
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fuelid.ident.kalman import ParameterKalman  # noqa: E402
from fuelid.ident.pem import pem  # noqa: E402
from fuelid.ident.polymodel import simulate  # noqa: E402
from fuelid.ident.rpem import RPEM  # noqa: E402
from fuelid.ident.validation import fit_percent  # noqa: E402
from tests.ident.online_data import diesel_truth  # noqa: E402
from tests.ident.synthetic import paper_data  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=200_000)
    ap.add_argument("--window-samples", type=int, default=20_000)
    ap.add_argument("--refit-every", type=int, default=1000)
    args = ap.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {0})
    warnings.simplefilter("ignore")

    truth = diesel_truth()
    s = truth.structure
    u, y, _ = paper_data(truth, n=args.samples, seed=0, sigma_e=0.5)
    n_w = min(args.window_samples, args.samples)
    uw, yw = u[:n_w], y[:n_w]

    RPEM(s, 0.3).update(u[:100], y[:100])  # JIT compile (cached on disk after the first run)
    est = RPEM(s, 0.3)
    t = time.perf_counter()
    est.update(u, y)
    t_rpem = time.perf_counter() - t
    rate_rpem = args.samples / t_rpem

    t = time.perf_counter()
    model, fits = None, 0
    for end in range(max(args.refit_every, 2 * s.n_params + s.n_start + 1), n_w + 1, args.refit_every):
        model = pem(uw[:end], yw[:end], s, 0.3, init=model)
        fits += 1
    t_pem = time.perf_counter() - t
    rate_pem = n_w / t_pem

    kal = ParameterKalman(prior=model)
    t = time.perf_counter()
    kal.update(u, y)
    rate_kal = args.samples / (time.perf_counter() - t)

    est_w = RPEM(s, 0.3)
    est_w.update(uw, yw)
    print(f"paper orders: {s.n_params} parameters, {args.samples} samples (Ts 0.3 s: {args.samples * 0.3 / 3600:.1f} h)")
    print(f"{'contender':<44} {'samples/s':>12} {'ratio':>8}")
    print(f"{'rpem (compiled, one pass)':<44} {rate_rpem:>12,.0f} {1.0:>8.2f}")
    print(f"{'kalman (compiled, one pass)':<44} {rate_kal:>12,.0f} {rate_kal / rate_rpem:>8.2f}")
    print(f"{f'pem refit every {args.refit_every} on growing window ({fits} fits)':<44} {rate_pem:>12,.0f} "
          f"{rate_pem / rate_rpem:>8.4f}")
    print(f"rpem is {rate_rpem / rate_pem:,.0f}x the refitting PEM; a week (2.0 M samples) takes "
          f"{2.016e6 / rate_rpem:.0f} s; goal >= 50,000 samples/s: {'met' if rate_rpem >= 50_000 else 'NOT met'}")
    print(f"simulated fit on the {n_w}-sample window: rpem {fit_percent(yw, simulate(est_w.model(), uw)):.2f} %, "
          f"pem {fit_percent(yw, simulate(model, uw)):.2f} %")


if __name__ == "__main__":
    main()
