"""fuelid diagnose: where a fuel model fails on measurements, which physical effect it is missing, and whether adding
it helps on data the fit did not see."""
import argparse

from fuelid.commands.dataset import add_dataset_arguments, build_for_models
from fuelid.errors import InputError
from fuelid.ident.diagnosis import Settings, diagnose
from fuelid.ident.effectfile import defined_effects
from fuelid.ident.hammerstein import map_summary
from fuelid.ident.modelfile import load_model
from fuelid.output import print_json
from fuelid.parallel import available_cpus, jobs
from fuelid.progress import progress

DEFAULTS = Settings()


def add_settings_arguments(p):
    """The diagnosis's thresholds (ident.diagnosis.Settings) as options."""
    p.add_argument("--alpha", type=float, default=DEFAULTS.alpha,
                   help=f"family-wise false-alarm rate of the screening (Holm; default {DEFAULTS.alpha:g})")
    p.add_argument("--margin", type=float, default=DEFAULTS.margin_se, metavar="K",
                   help="a candidate is recommended when its mean paired per-block held-out gain exceeds K standard "
                        f"errors (default {DEFAULTS.margin_se:g})")
    p.add_argument("--min-drop", type=float, default=DEFAULTS.min_drop_percent, metavar="PERCENT",
                   help="... and the held-out RMS simulation error falls by at least PERCENT "
                        f"(default {DEFAULTS.min_drop_percent:g})")
    p.add_argument("--min-effect", type=float, default=DEFAULTS.min_effect_percent, metavar="PERCENT",
                   help="smallest share of the simulation error [%%] a significant candidate must explain to be built "
                        f"(default {DEFAULTS.min_effect_percent:g})")
    p.add_argument("--builds", type=int, default=DEFAULTS.max_builds, metavar="N",
                   help=f"candidates built and held out per round (default {DEFAULTS.max_builds})")


def settings_from(args) -> Settings:
    """The Settings the options give; InputError for values outside their meaning."""
    if not 0 < args.alpha < 1:
        raise InputError(f"--alpha must be between 0 and 1, got {args.alpha:g}")
    if args.margin < 0 or args.min_drop < 0 or args.min_effect < 0 or args.builds < 0:
        raise InputError("--margin, --min-drop, --min-effect and --builds must not be negative")
    return Settings(alpha=args.alpha, margin_se=args.margin, min_drop_percent=args.min_drop,
                    min_effect_percent=args.min_effect, max_builds=args.builds)


DEFAULT_JOBS = min(4, available_cpus())  # a round of the diagnosis builds at most 4 models; its folds are 4


def jobs_argument(text: str) -> int:
    """--jobs: a whole number ≥ 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def add_jobs_argument(p):
    """--jobs, for the commands that diagnose (fuelid.parallel)."""
    p.add_argument("--jobs", type=jobs_argument, default=DEFAULT_JOBS, metavar="N",
                   help="fits run side by side in up to N processes: this one and N-1 workers, each holding a copy of "
                        "the data (default: the CPUs available, at most 4; 1 runs everything here)")


def add_arguments(p):
    p.add_argument("model", metavar="MODEL.json", help="model file (fuelid identify)")
    p.add_argument("inputs", nargs="+", metavar="DATA.mcap",
                   help="MCAP recordings to diagnose it on (several trips: each is held out in turn)")
    add_settings_arguments(p)
    p.add_argument("--effects-file", action="append", default=[], metavar="EFFECTS.toml",
                   help="also test the effects defined in this file (docs/reference/formats.md; docs/effects-example.toml); "
                        "repeatable")
    p.add_argument("--top", type=int, default=8, metavar="N", help="candidates shown in the report (default 8)")
    add_dataset_arguments(p)
    add_jobs_argument(p)
    p.add_argument("--json", action="store_true", help="print the full result as JSON")


def format_report(result: dict, top: int = 8) -> str:
    """The short human-readable report, laid out from the JSON (whose texts the diagnosis rendered)."""
    c = result["compare"]
    unit = c["unit"]
    w = result["where_it_fails"]["whiteness"]
    lines = [
        f"fit: simulation {c['fit_percent']['simulation']:.1f} %, 1-step prediction {c['fit_percent']['prediction']:.1f} %;"
        f" RMS error {c['rmse']['simulation']:.2f} {unit} (simulation)",
        "residual whiteness (99 %): " + ("pass" if w["autocorr_pass"] else "FAIL") + "; input cross-correlation: "
        + ", ".join(f"{k} {'pass' if v else 'FAIL'}" for k, v in w["crosscorr_pass"].items()),
    ]
    if result["held_out"]:
        lines.append(f"held-out RMS simulation error (refitted without each fold): {result['held_out']['rmse']:.3f} "
                     f"{unit}")
    lines.append("worst stretches (minutes since the start of the data):")
    for s in result["where_it_fails"]["worst_segments"][:3]:
        differs = f" — {', '.join(s['context'])}" if s["context"] else ""
        lines.append(f"  {s['t_start_min']:.2f}–{s['t_end_min']:.2f} min: RMS {s['rmse']:.2f} {unit}, "
                     f"bias {s['bias']:+.2f} {unit}, {s['speed_rpm']:.0f} rpm{differs}")
    lines.append(f"engine map: {result['engine_map']['status']} — {result['engine_map']['explanation']}")
    shown = [r for r in result["candidates"] if r["testable"]][:top]
    lines.append(f"candidate effects ({result['test']['candidates_tested']} tested, Holm α = "
                 f"{result['test']['alpha']:g}):")
    width = max([len("effect"), *(len(r["effect"]) for r in shown)])
    lines.append(f"  {'effect':{width}s} {'p (Holm)':>9s} {'explains':>9s} {'held-out':>9s}  status")
    for r in shown:
        drop = "" if r["rmse_drop_percent"] is None else f"{-r['rmse_drop_percent']:+.1f} %"
        lines.append(f"  {r['effect']:{width}s} {r['p_holm']:9.1e} {r['estimated_drop_percent']:7.1f} % {drop:>9s}"
                     f"  {r['explanation']}")
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


PRELOAD = ("fuelid.ident.diagnosis",)  # the package of the workers' calls


def diagnosed(model, ds, settings, effects=()):
    """diagnose(model, ds, settings, effects=effects) with a progress bar on a terminal: a step per model built (in
    the `fuelid.parallel.jobs` context the command opened)."""
    with progress(desc="diagnose", unit="build") as bar:
        def told(step):
            bar.set_postfix_str(str(step), refresh=False)
            bar.update(1)

        return diagnose(model, ds, settings, effects=effects, progress=told)


def run(args) -> int:
    settings = settings_from(args)
    effects = defined_effects(args.effects_file)  # a bad effect file fails before any work
    model = load_model(args.model)
    with jobs(args.jobs, PRELOAD):  # the workers start while the data are read
        ds = build_for_models(args, args.inputs, [(args.model, model)])
        result = diagnosed(model, ds, settings, effects).to_json()
    result["data"]["files"] = list(map(str, args.inputs))
    result["model"]["file"] = args.model
    result["model"]["engine_map"] = map_summary(model)
    if args.json:
        print_json(result)
    else:
        print(format_report(result, args.top))
    return 0
