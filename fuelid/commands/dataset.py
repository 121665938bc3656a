"""fuelid dataset: MCAP recordings to a resampled identification data set (.csv or .mat) for cross-checks."""
import argparse
import sys
import warnings

from fuelid.errors import FuelidError
from fuelid.ident.datacache import cached_dataset
from fuelid.ident.dataset import build_dataset, csv_sidecar, save_dataset
from fuelid.output import print_json


def lag_argument(text: str) -> float:
    """--fuel-lag: seconds ≥ 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {text!r}") from None
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"must be at least 0 s, got {text}")
    return value


def lag_or_auto(text: str) -> float | str:
    """identify's --fuel-lag: seconds ≥ 0, or auto."""
    if text == "auto":
        return text
    try:
        return lag_argument(text)
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"{exc} (or auto)") from None


LAG_HELP = ("the fuel signal's reporting lag [s], below --ts: each fuel sample is binned at its log time minus it, "
            "e.g. 0.1 for an ECU that reports the mean fuel of its last 100 ms (docs/guide/identify-and-compare.md)")


def add_dataset_arguments(p, lag_auto: bool = False):
    """The data-set options shared by the commands that read recordings into a Dataset; lag_auto: --fuel-lag also
    takes auto, its default (identify)."""
    p.add_argument("--ts", type=float, metavar="S",
                   help="sampling interval [s] (default 0.3, as Madhusudhanan et al.; compare: the model's)")
    p.add_argument("--fuel", choices=["auto", "flowmeter", "lfe1"], default="auto",
                   help="output signal: the flow meter [kg/h], LFE1 fuel rate [L/h], or auto (meter when logged)")
    if lag_auto:
        p.add_argument("--fuel-lag", type=lag_or_auto, default="auto", metavar="S|auto",
                       help=LAG_HELP + "; auto (default): 0 or the fuel signal's report period, whichever the model "
                                       "simulates held-out blocks of the data better with, by more than the fits' "
                                       "spread")
    else:
        p.add_argument("--fuel-lag", type=lag_argument, metavar="S",
                       help=LAG_HELP + "; default 0, and for compare, diagnose, report and online with a prior the "
                                       "models'")
    p.add_argument("--max-gap", type=float, default=1.0, metavar="S",
                   help="longest gap [s] a signal is held over; longer gaps split the data (default 1)")
    p.add_argument("--cycle", type=float, default=1800.0, metavar="S",
                   help="drive-cycle length [s] for the cumulative fuel error (default 1800, the 30 min of Madhusudhanan et al.'s Table I)")
    p.add_argument("--skip-damaged", action="store_true",
                   help="leave out chunks of a recording that fail their CRC (a gap, listed in the warnings) "
                        "instead of stopping with an error")
    p.add_argument("--no-cache", action="store_true",
                   help="build the data set again instead of reusing the one in the user cache directory "
                        "(FUELID_CACHE_DIR, else $XDG_CACHE_HOME/fuelid or ~/.cache/fuelid; rebuilt whenever a "
                        "file's content or an option differs; FUELID_DATASET_CACHE=0 turns it off too)")


def build(args, paths, fuel_lag_s: float | None = None):
    """The Dataset of `paths` with the options of add_dataset_arguments (cached, see ident.datacache), the fuel
    binned fuel_lag_s [s] earlier (default: --fuel-lag's seconds, 0 without)."""
    if fuel_lag_s is None:
        fuel_lag_s = args.fuel_lag or 0.0
    options = {"Ts": args.ts or 0.3, "fuel": args.fuel, "max_gap_s": args.max_gap, "cycle_s": args.cycle,
               "skip_damaged": args.skip_damaged, "fuel_lag_s": fuel_lag_s}
    with warnings.catch_warnings():  # the notes are reported in the summary, not as Python warnings
        warnings.simplefilter("ignore", UserWarning)
        return cached_dataset(paths, options, lambda: build_dataset(paths, **options),
                              enabled=not getattr(args, "no_cache", False))


def build_for_models(args, paths, models):
    """The Dataset of `paths` to evaluate `models` [(path, PolyModel)] on: --ts and --fuel-lag default to the
    models' Ts and fuel lag (training.fuel_lag_s, 0 for a model without it) and --fuel auto to the signal of their
    output unit (meter for kg/h, LFE1 for L/h); every model's Ts and fuel lag must be the data's (FuelidError
    otherwise)."""
    ts = {m.Ts for _, m in models}
    if args.ts is None:
        if len(ts) > 1:
            raise FuelidError(f"the models have different sampling intervals {sorted(ts)} s; choose one with --ts")
        args.ts = ts.pop()
    lags = {m.fuel_lag_s for _, m in models}
    if args.fuel_lag is None:
        if len(lags) > 1:
            raise FuelidError(f"the models were identified with different fuel lags {sorted(lags)} s; "
                              "choose one with --fuel-lag")
        args.fuel_lag = lags.pop()
    if args.fuel == "auto":
        units = {m.output_unit for _, m in models}
        args.fuel = {"kg/h": "flowmeter", "L/h": "lfe1"}.get(units.pop(), "auto") if len(units) == 1 else "auto"
    ds = build(args, paths)
    for path, model in models:
        if abs(model.Ts - ds.Ts) > 1e-9:
            raise FuelidError(f"{path}: model Ts {model.Ts:g} s differs from the data's {ds.Ts:g} s")
        if abs(model.fuel_lag_s - ds.fuel_lag_s) > 1e-9:
            raise FuelidError(f"{path}: the model was identified with --fuel-lag {model.fuel_lag_s:g}, the data "
                              f"are built with --fuel-lag {ds.fuel_lag_s:g}")
    return ds


def add_arguments(p):
    p.add_argument("inputs", nargs="+", metavar="DATA.mcap", help="MCAP recordings (fuelid convert / fuelid log)")
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="data set to write: .csv or .mat")
    add_dataset_arguments(p)
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def run(args) -> int:
    if not args.output.endswith((".csv", ".mat")):
        raise FuelidError(f"{args.output}: output must end in .csv or .mat")
    ds = build(args, args.inputs)
    save_dataset(ds, args.output)
    summary = {"output": args.output, **ds.summary()}
    if args.output.endswith(".csv"):
        summary["metadata"] = str(csv_sidecar(args.output))
    if args.json:
        print_json(summary)
    else:
        op = summary["operating_point"]
        print(f"{args.output}: {summary['samples']} samples every {ds.Ts:g} s, "
              f"{summary['valid_duration_s'] / 60:.1f} min valid in {summary['segments']} segments, "
              f"{len(summary['cycles'])} drive cycles"
              + (f"; units and metadata in {summary['metadata']}" if "metadata" in summary else ""))
        print(f"inputs {', '.join(f'{n} [{u}]' for n, u in zip(ds.input_names, ds.input_units))}; "
              f"output {ds.output_name} [{ds.output_unit}]")
        print(f"operating point u0 = ({op['u0'][0]:.1f}, {op['u0'][1]:.1f}), y0 = {op['y0']:.3f}")
        for note in ds.notes:
            print(f"warning: {note}", file=sys.stderr)
    return 0
