"""fuelid identify: a Box-Jenkins fuel-flow model from MCAP recordings by prediction-error identification."""
import dataclasses
import json
import sys
import time
from pathlib import Path

from fuelid.commands.dataset import add_dataset_arguments, build
from fuelid.errors import FuelidError
from fuelid.ident.diagnosis import effects_to_add
from fuelid.ident.effectfile import defined_effects
from fuelid.ident.fuellag import LagChoice, identify_lag_chosen
from fuelid.ident.identify import MIN_SEGMENT_S
from fuelid.ident.modelchoice import ModelChoice, ModelKind, identify_chosen
from fuelid.ident.modelfile import save_model
from fuelid.ident.orders import search_dataset_orders
from fuelid.ident.polymodel import Structure, parse_orders
from fuelid.output import print_json

ORDERS_HELP = ("model orders: 'paper' (Madhusudhanan et al.'s: Gw nb=4 nf=5 nk=3, GT nb=5 nf=5 nk=0, C and D "
               "order 11), 'auto' (order search), or a SPEC 'nb=4,5;nf=5,5;nk=3,0;nc=11;nd=11' (per-input lists for nb, nf, nk; "
               "nc, nd, na single numbers, 0 when left out)")
def add_arguments(p):
    p.add_argument("inputs", nargs="+", metavar="DATA.mcap", help="MCAP recordings to identify on")
    p.add_argument("-o", "--output", required=True, metavar="MODEL.json", help="model file to write")
    p.add_argument("--orders", default="paper", metavar="paper|auto|SPEC", help=ORDERS_HELP)
    p.add_argument("--model", dest="model_kind", default="auto", choices=[k.value for k in ModelKind],
                   help="auto (default): the engine model (the engine's fuel map, a smooth surface over speed x "
                        "torque, under the paper's dynamics) when it simulates held-out blocks of the data better "
                        "than the paper's linear model by more than the fits' spread, else the linear model; "
                        "linear: the paper's linear model; engine: the engine model "
                        "(docs/explanation/engine-model.md)")
    p.add_argument("--effect", action="append", default=[], metavar="ID",
                   help="add a physical effect as extra input (ids as in `fuelid diagnose`; fuel_delay=SECONDS); "
                        "repeatable")
    p.add_argument("--effects-file", action="append", default=[], metavar="EFFECTS.toml",
                   help="effects you define (docs/reference/formats.md): --effect ID may name them; the model carries their "
                        "definitions; repeatable")
    p.add_argument("--effects-from", metavar="DIAGNOSIS.json",
                   help="also add every effect a saved `fuelid diagnose --json` result recommends (`recommended: true`; "
                        "named but not recommended ones are left out), and the engine map when it advises the "
                        "engine model; --fuel-lag then defaults to the lag of the data it diagnosed")
    p.add_argument("--min-segment", type=float, default=MIN_SEGMENT_S, metavar="S",
                   help=f"leave out valid stretches shorter than this [s] (default {MIN_SEGMENT_S:g})")
    add_dataset_arguments(p, lag_auto=True)
    p.add_argument("--verbose", action="store_true",
                   help="print the estimator's details (pole-zero cancellations, stability bound, stopping)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def estimator_summary(info: dict) -> str | None:
    """One plain line on what the estimator's warnings (info['warnings'], for experts) mean for the user, or
    None when there are none."""
    if not info.get("warnings"):
        return None
    if not info["converged"]:
        return ("the estimation stopped before it converged: the model may not be the best these data allow; "
                "try --orders auto or more data")
    return ("the fit is fine, but some coefficients are not determined by these data (near-cancelling poles "
            "and zeros); consider --orders auto")


def diagnosed(path: str) -> tuple[list[str], float]:
    """(the effects a saved `fuelid diagnose --json` result says to add, the fuel lag [s] of the data it diagnosed):
    the effects as ident.diagnosis.effects_to_add gives them (the engine map when it advises the engine model, then
    the candidates with `recommended` true; a result without that field recommends none), the lag its data
    summary's fuel_lag_s (0 for a result without one)."""
    try:
        result = json.loads(Path(path).read_text())
        return effects_to_add(result), float(result["data"].get("fuel_lag_s", 0.0))
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise FuelidError(f"--effects-from {path}: not a `fuelid diagnose --json` result ({exc})") from exc


def run(args) -> int:
    t_start = time.perf_counter()
    if args.effects_from:
        effects, lag = diagnosed(args.effects_from)
        args.effect += [e for e in effects if e not in args.effect]
        if args.fuel_lag == "auto":  # the effects were found on the data binned so
            args.fuel_lag = lag
    structure = None if args.orders == "auto" else Structure(**parse_orders(args.orders))
    defined = defined_effects(args.effects_file)
    ds = build(args, args.inputs, 0.0 if args.fuel_lag == "auto" else None)
    t_data = time.perf_counter()
    search = None
    if structure is None:  # the lowest orders passing the paper's residual tests, then the fit with effects
        search = search_dataset_orders(ds, args.min_segment)
        structure = search.structure
    fit = dict(kind=ModelKind(args.model_kind), min_segment_s=args.min_segment, files=args.inputs, defined=defined)
    if args.fuel_lag == "auto":
        model, ds = identify_lag_chosen(lambda lag: ds if lag == 0 else build(args, args.inputs, lag), structure,
                                        args.effect, **fit)
    else:
        model = identify_chosen(ds, structure, args.effect, **fit)
    choice = model.info["model_choice"]
    save_model(model, args.output)
    t_end = time.perf_counter()

    plain = model.info["data_warnings"] + (
        [] if search is None or search.passed else
        [f"--orders auto: none of {len(search.trials)} candidates passed the residual tests; the last one tried "
         "is used"])
    summary = estimator_summary(model.info)
    structure, metrics, n_train = model.structure, model.validation, model.training["identification_samples"]
    n_segs = model.training["identification_stretches"]
    result = {
        "model": args.output,
        "orders": args.orders,
        "structure": dataclasses.asdict(structure),
        "effects": list(model.effects),
        "model_choice": choice,
        "fuel_lag_choice": model.info.get("fuel_lag_choice"),
        "training": {"samples": n_train, "stretches": n_segs, "Ts": ds.Ts, "fuel_lag_s": ds.fuel_lag_s,
                     "operating_point": {"u0": [float(v) for v in ds.u0], "y0": float(ds.y0)},
                     "warnings": ds.notes + list(model.info.get("warnings", [])) + plain,
                     "advice": plain + ([summary] if summary else [])},
        "order_search": None if search is None else {
            "passed": search.passed,
            "trials": [{**dataclasses.asdict(t.structure), "loss_V": t.loss_V, "autocorr_pass": t.autocorr_pass,
                        "crosscorr_pass": list(t.crosscorr_pass)} for t in search.trials]},
        "estimation": {key: model.info[key] for key in
                       ("converged", "stop_reason", "iterations", "gauss_newton_step_se", "loss_V", "segments")},
        **metrics,
        "wall_time_s": {"dataset": t_data - t_start, "pem": model.info["wall_time_s"], "total": t_end - t_start},
    }
    if args.json:
        print_json(result)
    else:
        print(f"{args.output}: BJ {structure.nb}/{structure.nf}/{structure.nk} nc={structure.nc} nd={structure.nd}"
              f" on {n_train * ds.Ts / 60:.1f} min ({n_segs} stretches)"
              + (f", fuel binned {ds.fuel_lag_s:g} s earlier than logged" if ds.fuel_lag_s else "")
              + f", {t_end - t_start:.1f} s")
        print(ModelChoice.from_json(choice).line(ds.output_unit))
        if "fuel_lag_choice" in model.info:
            print(LagChoice.from_json(model.info["fuel_lag_choice"]).line(ds.output_unit))
        print(format_table([(args.output, metrics)], ds.output_unit))
        for w in ds.notes + plain:
            print(f"warning: {w}", file=sys.stderr)
        if summary:
            print(f"note: {summary}" + ("" if args.verbose else " (details: --verbose)"), file=sys.stderr)
        if args.verbose:
            for w in model.info.get("warnings", []):
                print(f"  {w}", file=sys.stderr)
    return 0


def format_table(rows, unit: str) -> str:
    """A short human table of evaluate()/evaluate_static() results: [(label, metrics), ...]."""
    def f(v, fmt="{:.1f}"):
        return "-" if v is None or v != v else fmt.format(v)

    lines = [f"{'model':<28} {'fit sim %':>9} {'fit pred %':>10} {'RMSE ' + unit:>10} {'white':>6} "
             f"{'xcorr':>8} {'cycle mean %':>12} {'cycle RMS %':>11}"]
    for label, m in rows:
        w = m.get("whiteness")
        white = "-" if w is None else ("yes" if w["autocorr_pass"] else "no")
        xcorr = "-" if w is None else "/".join("y" if p else "n" for p in w["crosscorr_pass"].values())
        cyc = m["cycle_fuel_error_percent"]
        lines.append(f"{label[-28:]:<28} {f(m['fit_percent']['simulation']):>9} "
                     f"{f(m['fit_percent'].get('prediction')):>10} {f(m['rmse']['simulation'], '{:.3f}'):>10} "
                     f"{white:>6} {xcorr:>8} {f(cyc['mean'], '{:+.2f}'):>12} {f(cyc['rms'], '{:.2f}'):>11}")
    return "\n".join(lines)
