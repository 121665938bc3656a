"""fuelid simulate: synthetic truck trips with a known fuel truth (candump log, flow capture, truth files)."""
import time
from pathlib import Path

from fuelid.errors import FuelidError
from fuelid.output import print_json
from fuelid.progress import progress
from fuelid.sim import catalog, effects, route, trip
from fuelid.sim.effects import parse_effects
from fuelid.sim.trip import MAP_TRUTH, TRUTH_NAMES, TripConfig
from fuelid.sim.vecto import SHIPPED, read_engine

DEFAULT_TRUTH = "diesel_p320"
TRUTH_ALIASES = {"paper_p320": "diesel_p320"}
STAGES = ("route", "drive", "engine", "fuel", "signals", "frames", "log", "truth")


def add_arguments(p):
    p.add_argument("--truth", default=None,
                   help="fuel truth: diesel_p320 (default; alias paper_p320) or gas_p340, the Box-Jenkins "
                        "models of Madhusudhanan et al.'s appendix; map, a VECTO engine's fuel map at the instantaneous speed and torque (--engine)")
    p.add_argument("--engine", default="", metavar="ENGINE.veng|NAME",
                   help="engine set for --truth map: a VECTO .veng file (its .vmap/.vfld beside it) or a shipped "
                        "set's name (default vecto_325kW); implies --truth map when --truth is not given; with "
                        "--catalog, makes the catalog's diesel trips on this engine")
    p.add_argument("--noise", type=float, default=None, metavar="STD",
                   help="std of the fuel signal's noise H e [L/h, kg/h for gas] (default: the paper truths' own, "
                        "1.8 L/h diesel and 2.4 kg/h gas; 0 for --truth map); the truth file states the resulting "
                        "noise floor")
    p.add_argument("--cycle", default="mixed", help="route: urban, rural, motorway or mixed (default mixed)")
    p.add_argument("--duration", type=float, default=1800.0, metavar="S", help="trip length [s] (default 1800)")
    p.add_argument("--seed", type=int, default=1, help="random seed; the same seed gives the same bytes (default 1)")
    p.add_argument("--mass", type=float, default=40000.0, metavar="KG", help="gross mass [kg] (default 40000)")
    p.add_argument("--effect", action="append", default=[], metavar="NAME[=MAGNITUDE]",
                   help="switch on a physical effect, repeatable; --list shows names, units and defaults")
    p.add_argument("--ambient", type=float, default=12.0, metavar="DEGC", help="ambient temperature at the start [°C] (default 12)")
    p.add_argument("--ambient-drift", type=float, default=0.0, metavar="K", help="ambient temperature change over the trip [K] (default 0)")
    p.add_argument("--altitude", type=float, default=60.0, metavar="M", help="altitude at the start [m] (default 60)")
    p.add_argument("--hilliness", type=float, default=1.0, help="scale of the road grades [-] (default 1)")
    p.add_argument("-o", "--output", metavar="OUT.log.gz", help="log to write (.log or .log.gz); the truth files "
                   "(and the gas truck's .flow capture) go next to it")
    p.add_argument("--catalog", metavar="NAME", action="append", default=[],
                   help="regenerate a shipped replay log by name (repeatable)")
    p.add_argument("--all", action="store_true", help="regenerate every shipped replay log (not the map engine's cycles)")
    p.add_argument("--dir", default="replay_logs", metavar="DIR", help="folder for --catalog/--all (default replay_logs)")
    p.add_argument("--list", action="store_true", help="list truths, cycles, effects and catalog entries")
    p.add_argument("--json", action="store_true", help="print a JSON summary")


def _listing() -> dict:
    return {"truths": list(TRUTH_NAMES), "engines": list(SHIPPED), "cycles": list(route.CYCLE_NAMES),
            "effects": {n: {"default": e.default, "unit": e.unit, "spns": list(e.spns),
                            **({"generic": True} if n in effects.GENERIC_EFFECTS else {})}
                        for n, e in effects.ALL_EFFECTS.items()},
            "catalog": {n: catalog.command_line(n) for n in catalog.CATALOG}}


def _config(args):
    truth = TRUTH_ALIASES.get(args.truth, args.truth) or (MAP_TRUTH if args.engine else DEFAULT_TRUTH)
    cfg = TripConfig(truth=truth, engine=args.engine, cycle=args.cycle, duration_s=args.duration, seed=args.seed,
                     effects=tuple(parse_effects(args.effect).items()), mass_kg=args.mass, ambient_c=args.ambient,
                     ambient_drift_c=args.ambient_drift, altitude_m=args.altitude, hilliness=args.hilliness,
                     noise=args.noise)
    _check_engine(cfg.engine)
    return cfg


def _check_engine(engine: str) -> None:
    """A broken engine set, or one whose fuel is a gas, fails here in one line, before any simulation."""
    if engine:
        read_engine(engine).fuel_density_kg_l


def _run_one(cfg, output: Path, label: str) -> dict:
    bar = progress(total=len(STAGES) + (not cfg.diesel), desc=label, unit="step")  # + meter stage (gas)
    t0 = time.perf_counter()
    try:
        result = trip.simulate(cfg, progress=lambda stage: bar.update(1))
        paths = trip.write(result, output, progress=lambda stage: bar.update(1))
    finally:
        bar.close()
    s = result.summary
    return {"name": label, "files": {k: str(p) for k, p in paths.items()},
            "bytes": {k: p.stat().st_size for k, p in paths.items()}, "seconds": round(time.perf_counter() - t0, 2),
            "truth": cfg.truth, "cycle": cfg.cycle, "duration_s": cfg.duration_s, "seed": cfg.seed,
            "effects": dict(cfg.effects), "distance_km": s["route"]["distance_km"],
            "mean_fuel": s["fuel"]["mean_true"], "fuel_unit": s["fuel"]["unit"], "frames": s["frames"]["total"]}


def run(args) -> int:
    if args.list:
        listing = _listing()
        if args.json:
            print_json(listing)
        else:
            print("truths:  " + ", ".join(listing["truths"]))
            print("engines: " + ", ".join(listing["engines"]) + " (or a VECTO .veng file)")
            print("cycles:  " + ", ".join(listing["cycles"]))
            print("effects:")
            for n, e in listing["effects"].items():
                print(f"  {n:20s} default {e['default']:g} {e['unit']} (SPN {', '.join(map(str, e['spns']))})")
            print("catalog:")
            for n, c in listing["catalog"].items():
                print(f"  {n:34s} {c}")
        return 0

    if args.all or args.catalog:
        names = list(catalog.SHIPPED) if args.all else args.catalog
        unknown = [n for n in names if n not in catalog.CATALOG]
        if unknown:
            raise FuelidError(f"unknown catalog entry {unknown[0]!r}; see fuelid simulate --list")
        _check_engine(args.engine)
        jobs = [(catalog.on_engine(catalog.CATALOG[n], args.engine, args.noise), Path(args.dir) / f"{n}.log.gz", n)
                for n in names]
    else:
        if not args.output:
            raise FuelidError("give -o OUT.log.gz, or --catalog NAME / --all")
        if not (args.output.endswith(".log") or args.output.endswith(".log.gz")):
            raise FuelidError(f"output must end in .log or .log.gz: {args.output}")
        jobs = [(_config(args), Path(args.output), Path(args.output).name)]

    results = [_run_one(cfg, out, label) for cfg, out, label in jobs]
    if args.json:
        print_json(results if len(results) > 1 else results[0])
    else:
        for r in results:
            size = sum(r["bytes"].values()) / 1e6
            print(f"{r['files']['log']}: {r['truth']} {r['cycle']} {r['duration_s']:g} s, {r['distance_km']:.1f} km, "
                  f"mean fuel {r['mean_fuel']:.1f} {r['fuel_unit']}, {r['frames']} frames, {size:.1f} MB, "
                  f"{r['seconds']:.1f} s")
    return 0
