"""fuelid online: the recursive (RPEM or Kalman) estimator run over recorded files, as it runs live in the daemon."""
import dataclasses
import time

import numpy as np

from fuelid.commands.dataset import add_dataset_arguments, build
from fuelid.commands.identify import ORDERS_HELP
from fuelid.errors import FuelidError
from fuelid.ident.effects import reference_torque
from fuelid.ident.identify import check_variation
from fuelid.ident.live import check_online, fuel_scale, input_scales, prior_estimator
from fuelid.ident.modeldata import model_data
from fuelid.ident.modelfile import load_model, save_model
from fuelid.ident.polymodel import Structure, parse_orders
from fuelid.ident.rpem import RPEM, scaled_P0
from fuelid.ident.validation import evaluate
from fuelid.output import print_json
from fuelid.progress import progress

CHUNK = 20000  # samples per estimator call (progress bar step)


def add_arguments(p):
    p.add_argument("inputs", nargs="+", metavar="DATA.mcap", help="MCAP recordings, in time order")
    p.add_argument("-o", "--output", required=True, metavar="MODEL.json", help="model file to write (final estimate)")
    p.add_argument("--orders", default=None, metavar="paper|SPEC",
                   help=ORDERS_HELP.replace("'auto' (order search), ", "") + "; default: the prior's, else paper")
    p.add_argument("--prior", metavar="MODEL.json", help="model to start from (e.g. a fleet model), with its "
                   "covariance as the initial P; default: from scratch")
    p.add_argument("--method", choices=["rpem", "kalman"], default="rpem",
                   help="rpem: recursive prediction error with forgetting; kalman: random-walk parameters "
                        "(tracks a drifting fuel gain; needs --prior)")
    p.add_argument("--forgetting", type=float, metavar="LAMBDA",
                   help="rpem: constant forgetting factor λ in (0, 1], e.g. 0.9995 (memory ≈ Ts/(1−λ) = 10 min); "
                        "default λ growing from 0.99 towards 1 (1 with a prior)")
    p.add_argument("--drift", type=float, default=3e-4, metavar="RATE",
                   help="kalman: relative fuel-gain drift per sample (default 3e-4)")
    p.add_argument("--adapt", choices=["gain", "all"], default="gain",
                   help="with --prior: 'gain' tracks only the common fuel gain, the prior's dynamics and noise "
                        "model held (drift of injectors, fuel, meter; default), 'all' every parameter")
    add_dataset_arguments(p)
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def run(args) -> int:
    prior = load_model(args.prior) if args.prior else None
    structure = Structure(**parse_orders(args.orders or "paper")) if args.orders or not prior else prior.structure
    if prior is not None and prior.structure != structure:
        raise FuelidError(f"--orders {args.orders} differ from the prior's structure {prior.structure}")
    check_online(structure, prior.effects if prior is not None else (), args.prior)
    if args.forgetting is not None and not 0.0 < args.forgetting <= 1.0:
        raise FuelidError(f"--forgetting must be in (0, 1], got {args.forgetting}")

    if prior is not None and args.fuel_lag is None:
        args.fuel_lag = prior.fuel_lag_s
    ds = build(args, args.inputs)
    if prior is not None and abs(prior.fuel_lag_s - ds.fuel_lag_s) > 1e-9:
        raise FuelidError(f"the prior was identified with --fuel-lag {prior.fuel_lag_s:g}, the data are built "
                          f"with --fuel-lag {ds.fuel_lag_s:g}")
    if prior is not None and (tuple(prior.input_units[:2]) != tuple(ds.input_units) or prior.output_unit != ds.output_unit):
        raise FuelidError(f"prior units {list(prior.input_units[:2])} -> {prior.output_unit} do not match the data's "
                          f"{list(ds.input_units)} -> {ds.output_unit}")
    if prior is not None and abs(prior.Ts - ds.Ts) > 1e-9:
        raise FuelidError(f"prior Ts = {prior.Ts} s but the data are resampled to {ds.Ts} s (use --ts {prior.Ts})")
    check_variation(ds, ds.u, ds.y, np.flatnonzero(ds.valid))  # valid: speed, torque and fuel finite
    est = make_estimator(args, structure, ds, prior)
    # an engine model's map is fixed (the prior's): its inputs are computed from speed and torque like the others
    u, y = model_data(prior, ds) if prior is not None and prior.effects else (ds.u, ds.y)

    # one restart per jump of the time axis (engine off, rotated files): the filter states are not continuous
    breaks = np.flatnonzero(np.diff(ds.t) > 1.5 * ds.Ts) + 1
    pieces = [p for part in np.split(np.arange(len(ds)), breaks) for p in np.array_split(part, -(-len(part) // CHUNK))]
    counts = np.zeros(5, int)
    est.update(np.empty((0, u.shape[1])), np.empty(0))  # load the compiled loop before timing (seconds on a first run)
    t_est = 0.0
    with progress(total=len(ds), desc="online", unit="sample") as bar:
        for idx in pieces:
            if idx[0] in breaks:
                est.reset()
            t0 = time.perf_counter()
            trace = est.update(u[idx], y[idx], ds.valid[idx] & np.isfinite(u[idx]).all(axis=1))
            t_est += time.perf_counter() - t0
            counts += np.bincount(trace.status + 1, minlength=5)
            bar.update(len(idx))

    model = est.model(files=list(map(str, args.inputs)))
    model = dataclasses.replace(model, input_names=ds.input_names, input_units=ds.input_units,
                                output_name=ds.output_name, output_unit=ds.output_unit, training=ds.summary())
    if prior is not None and prior.effects:
        model = dataclasses.replace(model, input_names=prior.input_names, input_units=prior.input_units,
                                    effects=prior.effects, info={**model.info, **{
                                        k: prior.info[k] for k in ("effect_parameters", "effect_definitions")
                                        if k in prior.info}})
    metrics = evaluate(model, ds)
    model = dataclasses.replace(model, validation=metrics)
    save_model(model, args.output)

    report = model.info
    result = {
        "model": args.output,
        "method": args.method,
        "adapt": args.adapt if prior is not None else None,
        "structure": dataclasses.asdict(structure),
        "samples": len(ds),
        "updates": report["updates"],
        "samples_without_update": int(counts[0] + counts[1]),
        "shrunk_steps": report["shrunk_steps"],
        "rejected_steps": report["rejected_steps"],
        "restarts": len(breaks),
        "update_rate_samples_per_s": len(ds) / t_est if t_est > 0 else None,
        "final_lambda": report["lam"],
        "trace_P": report["trace_P"],
        "running_fit_percent": {"prediction": report["running_fit_prediction_pct"],
                                "simulation": report["running_fit_simulation_pct"]},
        "fuel_change_percent": ({"change": report["fuel_change_pct"], "ci95": report["fuel_change_ci95_pct"]}
                                if "fuel_change_pct" in report else None),
        **metrics,
    }
    if args.json:
        print_json(result)
    else:
        fit = metrics["fit_percent"]
        print(f"{args.output}: {args.method} over {len(ds)} samples ({len(ds) * ds.Ts / 3600:.2f} h), "
              f"{result['updates']} updates, {len(breaks)} restarts")
        print(f"final model fit: simulation {_pct(fit['simulation'])}, prediction {_pct(fit.get('prediction'))}"
              f" (running over the last window: {_pct(result['running_fit_percent']['simulation'])} / "
              f"{_pct(result['running_fit_percent']['prediction'])})")
        change = result["fuel_change_percent"]
        if change:
            print(f"steady-state fuel change since the prior: {change['change']:+.1f} % ± {change['ci95']:.1f} % (95 %)")
        print(f"update rate: {result['update_rate_samples_per_s']:,.0f} samples/s")
    return 0


def _pct(v) -> str:
    """A fit [%] as printed: "-" when there is none (None or NaN)."""
    return "-" if v is None or v != v else f"{v:.1f} %"


def make_estimator(args, structure, ds, prior):
    """The estimator the options ask for: from the prior (ident.live.prior_estimator), else an RPEM from scratch
    at the data's operating point, its P0 scaled as the daemon's (ident.live: idle speed, reference torque, idle
    fuel; the largest torque in the data when EC1 never arrived)."""
    if prior is not None:
        return prior_estimator(prior, method=args.method, forgetting=args.forgetting, drift=args.drift,
                               adapt=args.adapt)
    if args.method == "kalman":
        raise FuelidError("--method kalman needs --prior (its drift covariance is scaled from the prior's B)")
    torque_ref = 100.0 if ds.input_units[1] == "%" else reference_torque(ds) or float(np.nanmax(np.abs(ds.u[:, 1])))
    P0 = scaled_P0(structure, input_scales(ds.u0[0], torque_ref), fuel_scale(ds.y0))
    return RPEM(structure, ds.Ts, lam=args.forgetting, u0=ds.u0, y0=ds.y0, P0=P0)
