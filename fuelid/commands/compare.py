"""fuelid compare: validation metrics of model files on MCAP recordings, next to static baselines: the steady-state
engine map of paper 000 and the locally weighted regressions VB, EB, EB* of paper 001 (ident.baseline)."""
import sys

from fuelid.commands.dataset import add_dataset_arguments, build, build_for_models
from fuelid.commands.identify import format_table
from fuelid.errors import FuelidError
from fuelid.ident.baseline import engine_map, seed2_baselines
from fuelid.ident.modelfile import load_model
from fuelid.ident.report import improvement_sentence
from fuelid.ident.validation import evaluate, evaluate_static
from fuelid.output import print_json

STATIC = {"vb": "VB", "eb": "EB", "ebstar": "EB*"}  # --baselines id → ident.baseline kind
BASELINES = ("map", *STATIC)


def add_arguments(p):
    p.add_argument("inputs", nargs="+", metavar="FILE",
                   help="model files (*.json) and MCAP recordings (anything else), in any order")
    p.add_argument("--horizon", type=int, default=1, metavar="K", help="prediction horizon [samples] (default 1)")
    p.add_argument("--baselines", default="map", metavar="LIST",
                   help="comma-separated static baselines: map (the steady-state engine map of "
                        "Madhusudhanan et al.), vb, eb, ebstar (the hub-dyno study's locally weighted regressions in "
                        "vehicle and engine coordinates and "
                        "with the inertia term; they add its fuel-shift and J1 sweeps; ~10-60 s) (default: map)")
    p.add_argument("--map-from", nargs="+", metavar="DATA.mcap", default=[],
                   help="build the baselines from these recordings (e.g. the identification trip; default: from "
                        "the compared data itself, which flatters them)")
    add_dataset_arguments(p)
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def run(args) -> int:
    wanted = [b.strip().lower() for b in args.baselines.split(",") if b.strip()]
    unknown = sorted(set(wanted) - set(BASELINES))
    if unknown:
        raise FuelidError(f"--baselines: unknown {', '.join(unknown)} (choose from {', '.join(BASELINES)})")
    model_paths = [p for p in args.inputs if p.endswith(".json")]
    data_paths = [p for p in args.inputs if not p.endswith(".json")]
    if not model_paths or not data_paths:
        raise FuelidError("give at least one model file (.json) and one recording (.mcap)")
    models = [(path, load_model(path)) for path in model_paths]
    ds = build_for_models(args, data_paths, models)

    results = [{"model": path, **evaluate(model, ds, k=args.horizon)} for path, model in models]
    cal = build(args, args.map_from) if args.map_from else ds
    built = {"built_from": args.map_from or data_paths, "in_sample": not args.map_from}
    baselines, sweeps = {}, None
    if "map" in wanted:
        try:
            fmap = engine_map(cal)
            baselines["map"] = {"points": len(fmap.fuel), **built, **evaluate_static(fmap(ds.u), ds)}
        except FuelidError as exc:
            baselines["map"] = {"error": str(exc)}
    kinds = [STATIC[b] for b in wanted if b in STATIC]
    if kinds:
        try:
            s2 = seed2_baselines(cal, ds, kinds)
        except FuelidError as exc:
            s2 = {"predictions": {}, "errors": dict.fromkeys(kinds, str(exc)), "fuel_shift": None, "J1": None}
        sweeps = {"fuel_shift": s2["fuel_shift"], "J1": s2["J1"], "built_from": built["built_from"]}
        for b in wanted:
            if b in STATIC:
                kind = STATIC[b]
                baselines[b] = ({"error": s2["errors"][kind]} if kind in s2["errors"] else
                                {**built, "outside_calibration_share": s2["outside"][kind],
                                 **evaluate_static(s2["predictions"][kind], ds)})

    out = {"data": {"files": data_paths, **ds.summary()}, "models": results, "baselines": baselines,
           "baseline_sweeps": sweeps}
    if args.json:
        print_json(out)
    else:
        rows = [(r["model"], r) for r in results]
        for b, res in baselines.items():
            if "error" not in res:
                label = f"baseline map ({res['points']} pts)" if b == "map" else f"baseline {STATIC[b]} (LWR)"
                rows.append((label, res))
        print(f"{len(ds.segments())} segments, {ds.valid.sum() * ds.Ts / 60:.1f} min valid, "
              f"{len(out['data']['cycles'])} drive cycles")
        print(format_table(rows, ds.output_unit))
        for r in results[1:]:
            print(f"{r['model']} against {results[0]['model']}: "
                  f"{improvement_sentence(results[0], r, ds.output_unit)}")
        if sweeps and sweeps["fuel_shift"]:
            print(format_sweeps(sweeps, ds.output_unit))
        for b, res in baselines.items():
            if "error" in res:
                print(f"baseline {b}: {res['error']}", file=sys.stderr)
        for note in ds.notes:
            print(f"warning: {note}", file=sys.stderr)
    return 0


def format_sweeps(sweeps: dict, unit: str) -> str:
    """One line per paper-001 sweep: the best value and its RMSE, flagged when it is the edge of the range."""
    lines = []
    for name, key, label, u in (("fuel_shift", "shift_s", "fuel shift", "s"), ("J1", "J1", "J1 (EB*)", "kg m^2")):
        sw = sweeps.get(name)
        if sw:
            i = sw[key].index(sw[f"best_{key}"])
            edge = f" (edge of the swept {sw[key][0]:g}..{sw[key][-1]:g})" if sw["best_at_edge"] else ""
            lines.append(f"best {label}: {sw[f'best_{key}']:+.2f} {u}{edge}, RMSE {sw['rmse'][i]:.3f} {unit}")
    return "\n".join(lines)
