"""fuelid diagnose: where a fuel model fails on measurements, and which physical effect it is missing."""
import os

from fuelid.commands.dataset import add_dataset_arguments, build_for_models
from fuelid.ident.diagnosis import diagnose
from fuelid.ident.diagnosis.candidate import ENGINE_MAP
from fuelid.ident.effectfile import defined_effects
from fuelid.ident.hammerstein import map_summary
from fuelid.ident.modelfile import load_model
from fuelid.output import print_json


def add_arguments(p):
    p.add_argument("model", metavar="MODEL.json", help="model file (fuelid identify)")
    p.add_argument("inputs", nargs="+", metavar="DATA.mcap", help="MCAP recordings to diagnose it on")
    p.add_argument("--alpha", type=float, default=0.05,
                   help="family-wise false-alarm rate over all candidate effects (Holm; default 0.05)")
    p.add_argument("--verify", type=int, default=10, metavar="N",
                   help="verify up to N candidates that pass the tests: the held-out error drop of a linearised "
                        "refit, scored on 60-s blocks left out of it (default 10; the fuel delay besides; 0 skips, "
                        "and names effects on the tests alone, none recommended)")
    p.add_argument("--min-drop", type=float, default=2.0, metavar="PERCENT",
                   help="smallest fall of the held-out RMS error [%%] that confirms a verified effect (default 2)")
    p.add_argument("--min-effect", type=float, default=1.0, metavar="PERCENT",
                   help="smallest share of the simulation error [%%] an effect must explain to be named "
                        "(default 1; smaller ones are detectable but not worth an input)")
    p.add_argument("--effects-file", action="append", default=[], metavar="EFFECTS.toml",
                   help="also test the effects defined in this file (docs/reference/formats.md; docs/effects-example.toml); "
                        "repeatable")
    p.add_argument("--top", type=int, default=8, metavar="N", help="candidates shown in the report (default 8)")
    add_workers_argument(p)
    add_dataset_arguments(p)
    p.add_argument("--json", action="store_true", help="print the full result as JSON")


def add_workers_argument(p):
    """--workers: the worker process the diagnosis builds the models `fuelid identify` would build in, ahead."""
    default = 1 if (os.cpu_count() or 1) > 1 else 0
    p.add_argument("--workers", type=int, choices=(0, 1), default=default,
                   help="1: build the models `fuelid identify --effects-from` would build (on which what is "
                        "recommended is checked) ahead, in a worker process, while the diagnosis goes on; 0: build "
                        "each when needed, in this process; the same diagnosis either way (default 1 with two cores or "
                        "more, else 0)")


def plural(n: int, noun: str) -> str:
    """'1 candidate', '2 candidates'."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


def format_report(result: dict, top: int = 8) -> str:
    """The short human-readable report."""
    c = result["compare"]
    unit = c["unit"]
    w = result["where_it_fails"]["whiteness"]
    lines = [
        f"fit: simulation {c['fit_percent']['simulation']:.1f} %, 1-step prediction {c['fit_percent']['prediction']:.1f} %;"
        f" RMS error {c['rmse']['simulation']:.2f} {unit} (simulation)",
        f"cycle fuel error: mean {c['cycle_fuel_error_percent']['mean']:+.2f} %, "
        f"RMS {c['cycle_fuel_error_percent']['rms']:.2f} %",
        "residual whiteness (99 %): " + ("pass" if w["autocorr_pass"] else "FAIL") + "; input cross-correlation: "
        + ", ".join(f"{k} {'pass' if v else 'FAIL'}" for k, v in w["crosscorr_pass"].items())
        + " (a pass: no dynamics of speed and torque left in the errors; not that nothing is missing)",
        "worst stretches (minutes since the start of the data):",
    ]
    for s in result["where_it_fails"]["worst_segments"][:3]:
        differs = f" — {', '.join(s['context'])}" if s["context"] else ""
        lines.append(f"  {s['t_start_min']:.2f}–{s['t_end_min']:.2f} min: RMS {s['rmse']:.2f} {unit}, "
                     f"bias {s['bias']:+.2f} {unit}, {s['speed_rpm']:.0f} rpm{differs}")
    tested = result["test"]["candidates_tested"]
    lines.append(f"candidate effects ({plural(tested, 'candidate')} tested, Holm α = {result['test']['alpha']:g}):")
    shown = [r for r in result["candidates"] if r.get("testable")][:top]
    width = max([len("effect"), *(len(r["effect"]) for r in shown)])
    lines.append(f"  {'effect':{width}s} {'LM':>9s} {'p':>9s} {'explains':>9s} {'sig':>4s} {'RMS drop':>9s}")
    for r in shown:
        drop = "" if r["rmse_drop_percent"] is None else f"{r['rmse_drop_percent']:.0f} %"
        sig = "map" if r.get("role") == ENGINE_MAP else "yes" if r["significant"] else "no"
        lines.append(f"  {r['effect']:{width}s} {r['statistic']:9.1f} {r['p_value']:9.1e} "
                     f"{r['estimated_drop_percent']:7.1f} % {sig:>4s} {drop:>9s}")
    if result.get("engine_map"):
        lines.append(f"  (map: {result['engine_map']}, the engine map term — a property of the engine, tested first; "
                     f"the missing effects are tested on the model with it)")
    lines.append(result["verdict"])
    summary = result["model"].get("engine_map")
    if summary:
        u = summary["units"]
        lines.insert(0, f"engine map (part of the model): {summary['speed_range'][0]:.0f}–{summary['speed_range'][1]:.0f}"
                        f" {u['speed']} × {summary['torque_range'][0]:.0f}–{summary['torque_range'][1]:.0f} "
                        f"{u['torque']}, {100 * summary['covered_share']:.0f} % of it covered by the identification "
                        f"data; steady-state fuel there {summary['steady_state_range'][0]:.1f}–"
                        f"{summary['steady_state_range'][1]:.1f} {u['fuel']}")
    return "\n".join(lines)


def run(args) -> int:
    effects = defined_effects(args.effects_file)  # a bad effect file fails before any work
    model = load_model(args.model)
    ds = build_for_models(args, args.inputs, [(args.model, model)])
    result = diagnose(model, ds, alpha=args.alpha, n_verify=args.verify, min_effect_percent=args.min_effect,
                      min_drop_percent=args.min_drop, effects=effects, workers=args.workers).to_json()
    result["data"]["files"] = list(map(str, args.inputs))
    result["model"]["file"] = args.model
    result["model"]["engine_map"] = map_summary(model)
    if args.json:
        print_json(result)
    else:
        print(format_report(result, args.top))
    return 0
