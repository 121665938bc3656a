"""fuelid compare: validation metrics of model files on MCAP recordings, next to the steady-state map baseline."""
import sys

from fuelid.commands.dataset import add_dataset_arguments
from fuelid.output import print_json

HELP = "compare model files with measurements (fit, whiteness, cycle fuel error) and the engine-map baseline"


def add_arguments(p):
    p.add_argument("inputs", nargs="+", metavar="FILE",
                   help="model files (*.json) and MCAP recordings (anything else), in any order")
    p.add_argument("--horizon", type=int, default=1, metavar="K", help="prediction horizon [samples] (default 1)")
    p.add_argument("--map-from", nargs="+", metavar="DATA.mcap", default=[],
                   help="build the baseline engine map from these recordings (e.g. the identification trip; "
                        "default: from the compared data itself, which flatters the map)")
    add_dataset_arguments(p)
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def run(args) -> int:
    from fuelid.commands.dataset import build
    from fuelid.commands.identify import format_table
    from fuelid.errors import FuelidError
    from ident.baseline import engine_map
    from ident.modelfile import load_model
    from ident.validation import evaluate, evaluate_static

    model_paths = [p for p in args.inputs if p.endswith(".json")]
    data_paths = [p for p in args.inputs if not p.endswith(".json")]
    if not model_paths or not data_paths:
        raise FuelidError("give at least one model file (.json) and one recording (.mcap)")
    models = []
    for path in model_paths:
        try:
            models.append((path, load_model(path)))
        except FuelidError:
            raise
        except Exception as exc:
            raise FuelidError(f"{path}: unreadable model ({exc})") from exc
    ts = {m.Ts for _, m in models}
    if args.ts is None:
        if len(ts) > 1:
            raise FuelidError(f"the models have different sampling intervals {sorted(ts)} s; choose one with --ts")
        args.ts = ts.pop()
    if args.fuel == "auto":
        units = {m.output_unit for _, m in models}
        args.fuel = {"kg/h": "flowmeter", "L/h": "lfe1"}.get(units.pop(), "auto") if len(units) == 1 else "auto"
    ds = build(args, data_paths)

    results = []
    for path, model in models:
        if abs(model.Ts - ds.Ts) > 1e-9:
            raise FuelidError(f"{path}: model Ts {model.Ts:g} s differs from the data's {ds.Ts:g} s")
        results.append({"model": path, **evaluate(model, ds, k=args.horizon)})
    try:
        fmap = engine_map(build(args, args.map_from) if args.map_from else ds)
        baseline = {"points": len(fmap.fuel), "in_sample": not args.map_from, "built_from": args.map_from or data_paths,
                    **evaluate_static(fmap(ds.u), ds)}
    except FuelidError as exc:
        baseline = {"error": str(exc)}

    out = {"data": {"files": data_paths, **ds.summary()}, "models": results, "baseline_map": baseline}
    if args.json:
        print_json(out)
    else:
        rows = [(r["model"], r) for r in results]
        if "error" not in baseline:
            rows.append((f"baseline map ({baseline['points']} pts)", baseline))
        print(f"{len(ds.segments())} segments, {ds.valid.sum() * ds.Ts / 60:.1f} min valid, "
              f"{len(out['data']['cycles'])} drive cycles")
        print(format_table(rows, ds.output_unit))
        if "error" in baseline:
            print(f"baseline map: {baseline['error']}", file=sys.stderr)
        for note in ds.notes:
            print(f"warning: {note}", file=sys.stderr)
    return 0
