"""A model's steady-state fuel (ident.steady) against the fuel the simulator burns in steady runs, for every VECTO
engine in ../shared/engines (or --engines DIR...), and the drift between two models of the same truck on the same
data against their error bars.

    .venv/bin/python benchmarks/bench_steady_state.py [--quick] [--seeds 1 2 3 4 5] [--minutes 60] [--json]

Per engine and seed: `fuelid simulate --truth map --engine E.veng` drives a mixed trip (no hidden effect), `fuelid
convert` records it, and the model is the one a fleet job and `fuelid identify` build by default
(ident.fuellag.identify_lag_chosen: `--fuel-lag auto --model auto`, the paper's orders), its reference values taken
from the trip as a fleet job takes them (ident.steady.data_reference). Made once into benchmarks/.cache/steady/ (git-ignored).
--quick: seeds 1 2 3 of 30-minute trips.

Points: engine speeds 1000, 1200, 1400, 1600 rpm × 30, 50, 70 % of the engine's largest full-load torque [N·m],
kept when the trip drove within 100 rpm and 5 % of that torque at least MIN_SAMPLES times (0.3 s samples), so the
model is judged where its data are.

The measured steady fuel at a point is the simulator's own in a steady run (`steady_run`: speed and reported
torque held for 60 s, fuel as sim.mapfuel computes it — the VECTO map at the combustion torque, the transient
surcharge, the ECU's LFE1 averaging — the last 30 s averaged); the reported torque is the indicated torque
(brake + friction + auxiliaries, as sim.trip reports it), so the map is read at the reported torque less the
engine's friction. Beside the model's steady state: the error of its fitted map s(n, T) read alone (the engine
model only), and of a static map fitted to the trip's own samples (ident.enginemap.fit_map of the fuel over speed
and torque: what the data say without dynamics), so an error can be placed in the data or in the model's fit.
Limit: |mean error| ≤ 2 % per engine (over its points and seeds); the spread (standard deviation over points and
seeds) and the worst point are printed beside it.

Drift on the same data (fleet.drift over the case's points): the same model identified again with PEM started from
the first (ident.identify.identify_model's init: another start of the same criterion) and the paper's linear model
(`--model linear`) against the default model, d = 100 (S₁/S₀ − 1) [%] with its standard error σ_d; a refit should
stay within 2 σ_d, while the linear model's plane differs from the engine's curved map by what it cannot represent.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
CACHE = REPO / "benchmarks" / ".cache" / "steady"
ENGINES = REPO.parent / "shared" / "engines"
SPEEDS_RPM = (1000.0, 1200.0, 1400.0, 1600.0)
TORQUE_SHARES = (0.3, 0.5, 0.7)
LIMIT_PERCENT = 2.0
MIN_SAMPLES = 50  # samples of the trip near a point for it to be judged
K_SIGMA = 2.0  # a drift within K_SIGMA σ_d is within the error bars


def steady_run(engine_file: Path, speed_rpm: float, torque_nm: float, seconds: float = 60.0, dt: float = 0.01) -> float:
    """The simulator's fuel [L/h] with engine speed [rpm] and reported torque [N·m] held: sim.mapfuel's injected
    fuel at the combustion torque (reported less friction), as the ECU reports it, averaged over the last half."""
    from fuelid.sim import mapfuel, vecto

    v = vecto.read_engine(engine_file)
    engine = mapfuel.sim_engine(v)
    n = int(seconds / dt)
    rpm = np.full(n, speed_rpm)
    flywheel = np.full(n, torque_nm) - engine.friction_torque_nm(rpm)
    fuel = mapfuel.ecu_reported(mapfuel.injected_fuel_l_h(v, rpm, flywheel, dt), dt)
    return float(fuel[n // 2:].mean())


def trip_models(engine_file: Path, seed: int, minutes: float):
    """(dataset, {"default", "refit", "linear": model with its reference values}) of a simulated trip, made once:
    the default model (`fuelid identify`), the same model identified again with PEM started from it (from its own
    engine map), and the linear model (`--model linear`), both on the default model's data (its fuel lag)."""
    from fuelid.ident.dataset import build_dataset
    from fuelid.ident.fuellag import identify_lag_chosen
    from fuelid.ident.identify import MIN_SEGMENT_S, identify_model
    from fuelid.ident.modelchoice import ModelKind, identify_chosen
    from fuelid.ident.modelfile import load_model, save_model
    from fuelid.ident.polymodel import Structure, parse_orders
    from fuelid.ident.steady import data_reference

    stem = f"{engine_file.parent.name}_s{seed}_{minutes:g}min"
    log, mcap = CACHE / f"{stem}.log.gz", CACHE / f"{stem}.mcap"
    CACHE.mkdir(parents=True, exist_ok=True)
    if not mcap.exists():
        run = [sys.executable, "-m", "fuelid.cli"]
        subprocess.run([*run, "simulate", "--truth", "map", "--engine", str(engine_file), "--cycle", "mixed",
                        "--duration", str(60.0 * minutes), "--seed", str(seed), "-o", str(log)], check=True,
                       cwd=REPO, stdout=subprocess.DEVNULL)
        subprocess.run([*run, "convert", str(log), "-o", str(mcap), "--json"], check=True, cwd=REPO,
                       stdout=subprocess.DEVNULL)
    def build(lag: float):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            return build_dataset([mcap], fuel_lag_s=lag)

    structure = Structure(**parse_orders("paper"))
    fit = dict(min_segment_s=MIN_SEGMENT_S, files=[str(mcap)])
    fits = {"default": lambda ds, done: identify_lag_chosen(build, structure, **fit)[0],
            "refit": lambda ds, done: identify_model(ds, structure, list(done["default"].effects),
                                                     init=done["default"], **fit),
            "linear": lambda ds, done: identify_chosen(ds, structure, kind=ModelKind.LINEAR, **fit)}
    models, ds = {}, None
    for name, make in fits.items():
        path = CACHE / f"{stem}.{name}.model.json"
        if path.exists():
            models[name] = load_model(path)
        else:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                models[name] = make(ds, models)
        if ds is None:  # the data of the default model: the others are fitted on the same
            ds = build(models["default"].fuel_lag_s)
        if not path.exists():
            models[name].info["steady_reference"] = data_reference(models[name], ds)
            save_model(models[name], path)
    return ds, models


def engine_case(engine_file: Path, seed: int, minutes: float) -> dict:
    """The default model and the simulator at every point the trip covers, and the drifts on the same data."""
    from fuelid.fleet.drift import ReferencePoint, drift, steady_fuel as fleet_steady_fuel
    from fuelid.ident.enginemap import fit_map
    from fuelid.ident.hammerstein import engine_map_of
    from fuelid.ident.steady import steady_fuel
    from fuelid.sim import vecto

    ds, models = trip_models(engine_file, seed, minutes)
    model = models["default"]
    emap = engine_map_of(model)
    ok = ds.valid & np.isfinite(ds.y)
    data_map = fit_map(ds.u[ok, 0], ds.u[ok, 1], ds.y[ok], tuple(ds.u0), ds.y0, (*ds.input_units, ds.output_unit))
    t_max = vecto.read_engine(engine_file).max_torque_nm
    points = []
    for n in SPEEDS_RPM:
        for share in TORQUE_SHARES:
            T = share * t_max
            near = ds.valid & (np.abs(ds.u[:, 0] - n) < 100.0) & (np.abs(ds.u[:, 1] - T) < 0.05 * t_max)
            if near.sum() < MIN_SAMPLES:
                continue
            s = steady_fuel(model, n, T)
            measured = steady_run(engine_file, n, T)
            fitted_map = float(emap(np.array([n]), np.array([T]))[0]) if emap is not None else None
            static = float(data_map(np.array([n]), np.array([T]))[0])
            points.append({"speed_rpm": n, "torque_nm": T, "model_l_h": s.value, "std_l_h": s.std_error,
                           "measured_l_h": measured, "error_percent": 100.0 * (s.value / measured - 1.0),
                           "map_error_percent": None if fitted_map is None else 100.0 * (fitted_map / measured - 1.0),
                           "data_map_error_percent": 100.0 * (static / measured - 1.0),
                           "samples_near": int(near.sum())})
    refs = tuple(ReferencePoint(p["speed_rpm"], p["torque_nm"], "Nm") for p in points)
    drifts = {}
    if refs:
        base = fleet_steady_fuel(model, refs)
        for name in ("refit", "linear"):
            d = drift(fleet_steady_fuel(models[name], refs), base)
            drifts[name] = {"percent": d.percent, "std_percent": d.std_error_percent,
                            "within_error_bars": d.std_error_percent is not None
                            and abs(d.percent) <= K_SIGMA * d.std_error_percent,
                            "chosen": "engine" if "engine_map" in models[name].effects else "linear"}
    return {"seed": seed, "chosen": model.info["model_choice"]["chosen"], "points": points, "drift": drifts}


def summary(cases: list[dict]) -> dict:
    """Per engine: mean error, spread and worst point over its points and seeds [%], the limit, the drifts."""
    rows = [dict(p, seed=c["seed"]) for c in cases for p in c["points"]]
    errors = np.array([p["error_percent"] for p in rows])
    worst = rows[int(np.argmax(np.abs(errors)))]
    maps = [p["map_error_percent"] for p in rows if p["map_error_percent"] is not None]
    return {"cases": cases, "points": len(rows), "mean_error_percent": float(errors.mean()),
            "spread_percent": float(errors.std(ddof=1)) if len(errors) > 1 else 0.0,
            "mean_abs_error_percent": float(np.abs(errors).mean()),
            "worst": {k: worst[k] for k in ("seed", "speed_rpm", "torque_nm", "error_percent")},
            "map_alone_mean_error_percent": float(np.mean(maps)) if maps else None,
            "data_map_mean_error_percent": float(np.mean([p["data_map_error_percent"] for p in rows])),
            "drift_within_error_bars": {k: [sum(c["drift"][k]["within_error_bars"] for c in cases if k in c["drift"]),
                                            sum(k in c["drift"] for c in cases)] for k in ("refit", "linear")},
            "engine_model_chosen": sum(c["chosen"] == "engine" for c in cases),
            "within_limit": bool(abs(errors.mean()) <= LIMIT_PERCENT)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--engines", nargs="+", default=None, help="engine folders (default: every one in ../shared/engines)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    ap.add_argument("--minutes", type=float, default=60.0, help="length of each simulated trip [min]")
    ap.add_argument("--quick", action="store_true", help="seeds 1 2 3 of 30-minute trips")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    seeds, minutes = ([1, 2, 3], 30.0) if args.quick else (args.seeds, args.minutes)
    folders = [Path(f) for f in args.engines] if args.engines else sorted(p for p in ENGINES.iterdir() if p.is_dir())
    results = {folder.name: summary([engine_case(next(folder.glob("*.veng")), seed, minutes) for seed in seeds])
               for folder in folders}
    if args.json:
        print(json.dumps(results, indent=1))
        return
    print(f"{'engine':>20} {'seed':>4} {'rpm':>5} {'N·m':>6} {'model L/h':>15} {'steady run L/h':>14} {'error %':>8} "
          f"{'map s %':>8} {'data map %':>10}")
    for name, r in results.items():
        for c in r["cases"]:
            for p in c["points"]:
                alone = "" if p["map_error_percent"] is None else f"{p['map_error_percent']:+8.2f}"
                print(f"{name:>20} {c['seed']:>4} {p['speed_rpm']:5.0f} {p['torque_nm']:6.0f} "
                      f"{p['model_l_h']:7.2f} ± {p['std_l_h']:5.2f} {p['measured_l_h']:14.2f} "
                      f"{p['error_percent']:+8.2f} {alone:>8} {p['data_map_error_percent']:+10.2f}")
    print(f"\ndrift on the same data over the case's points, d ± σ_d [%] "
          f"(within the error bars: |d| ≤ {K_SIGMA:g} σ_d)")
    for name, r in results.items():
        for c in r["cases"]:
            text = "; ".join(f"{k} ({d['chosen']} model) {d['percent']:+.2f} ± {d['std_percent']:.2f} "
                             f"{'within' if d['within_error_bars'] else 'OUTSIDE'}" for k, d in c["drift"].items())
            print(f"{name:>20} seed {c['seed']} ({c['chosen']} model): {text}")
    print()
    for name, r in results.items():
        w = r["worst"]
        alone = "" if r["map_alone_mean_error_percent"] is None else \
            f"; the fitted map s(n, T) alone {r['map_alone_mean_error_percent']:+.2f} %"
        alone += f"; a static map of the trip's data {r['data_map_mean_error_percent']:+.2f} %"
        within = r["drift_within_error_bars"]
        print(f"{name}: mean error {r['mean_error_percent']:+.2f} % ± {r['spread_percent']:.2f} % (spread) over "
              f"{r['points']} points of {len(r['cases'])} seeds (engine model on {r['engine_model_chosen']}), "
              f"mean |error| {r['mean_abs_error_percent']:.2f} %, worst {w['error_percent']:+.2f} % at "
              f"{w['speed_rpm']:.0f} rpm × {w['torque_nm']:.0f} N·m (seed {w['seed']}){alone} "
              f"(limit ±{LIMIT_PERCENT:g} % on the mean: {'met' if r['within_limit'] else 'NOT met'}); drift within "
              f"the error bars: the second start on {within['refit'][0]} of {within['refit'][1]}, the linear model on "
              f"{within['linear'][0]} of {within['linear'][1]}")


if __name__ == "__main__":
    main()
