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

The engine model (--engine-samples, 0 skips): identified (`--model engine`, the paper's orders) on a synthetic
Hammerstein trip (tests/ident/engine_data.py), then run online from it as the daemon runs a prior:
  engine gain    ident.kalman.GainTracker (RPEM, λ = 0.9995) over its inputs, the map's columns computed at once
  engine rpem    ident.rpem.RPEM adapting every parameter, likewise
  daemon path    ident.live.LiveEstimator.feed over decoded records (three EEC1 and one LFE1 per 0.3 s bin): the
                 bins' resampling, the map's columns computed bin by bin, the gain tracker, the /ident/* records;
                 per bin, beside the same path for the paper's linear model
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
    ap.add_argument("--engine-samples", type=int, default=20_000)
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
    if args.engine_samples:
        engine_rates(args.engine_samples, rate_rpem)


def records(ds, ref_nm: float = 2000.0):
    """Decoded records (topic, receive time [s], record) of dataset ds: EC1, then per bin three EEC1 and one LFE1."""
    yield "/j1939/EC1", 0.0, {"sa": 0, "EngReferenceTorque": ref_nm}
    for k in range(len(ds)):
        t = 0.01 + k * ds.Ts
        for j in range(3):
            yield "/j1939/EEC1", t + j * 0.1, {"sa": 0, "EngSpeed": float(ds.u[k, 0]),
                                               "ActualEngPercentTorque": float(ds.u[k, 1] / ref_nm * 100.0)}
        yield "/j1939/LFE1", t + 0.05, {"sa": 0, "EngFuelRate": float(ds.y[k])}


def engine_rates(n: int, rate_rpem: float) -> None:
    """The engine model's online rates (module docstring) [samples/s], and the ratio to the linear RPEM's."""
    from fuelid.ident.identify import MIN_SEGMENT_S
    from fuelid.ident.kalman import GainTracker
    from fuelid.ident.live import LiveEstimator
    from fuelid.ident.modelchoice import ModelKind, identify_chosen
    from fuelid.ident.modeldata import model_data
    from fuelid.ident.polymodel import Structure, parse_orders
    from tests.ident.engine_data import trip

    structure = Structure(**parse_orders("paper"))
    engine = identify_chosen(trip(n=12000, seed=0), structure, kind=ModelKind.ENGINE, min_segment_s=MIN_SEGMENT_S)
    linear = identify_chosen(trip(n=12000, seed=0), structure, kind=ModelKind.LINEAR, min_segment_s=MIN_SEGMENT_S)
    ds = trip(n=n, seed=1)
    u, y = model_data(engine, ds)
    rates = {}
    for name, make in (("engine gain (compiled, one pass)", lambda: GainTracker(engine, lam=0.9995)),
                       ("engine rpem (compiled, one pass)", lambda: RPEM(prior=engine, lam=0.9995))):
        make().update(u[:100], y[:100])  # JIT compile
        est = make()
        t = time.perf_counter()
        est.update(u, y)
        rates[name] = n / (time.perf_counter() - t)
    recs = list(records(ds))
    for name, model in (("daemon path, engine model (per bin)", engine), ("daemon path, linear model (per bin)", linear)):
        live = LiveEstimator.from_model(model, forgetting=0.9995)
        live.prepare()
        t = time.perf_counter()
        for topic, t_rec, rec in recs:
            live.feed(topic, t_rec, rec)
        rates[name] = n / (time.perf_counter() - t)
    print(f"engine model: {engine.structure.n_params} parameters ({len(engine.B)} inputs), {n} samples")
    for name, rate in rates.items():
        print(f"{name:<44} {rate:>12,.0f} {rate / rate_rpem:>8.2f}")


if __name__ == "__main__":
    main()
