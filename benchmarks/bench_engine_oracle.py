"""Where the engine model's validation error comes from, on the VECTO map truth: oracles built from the simulator's
own truth, each RMS [L/h] on the validation trip of `sim.catalog.validation_pair(seed)` against the noise-free fuel
the dataset sees (the measured fuel minus the trip's per-bin noise, truth.npz `fuel_noise_bin`):

    (a)  the true VECTO map at the bins' mean logged speed and torque (flywheel torque = bus torque − friction,
         as sim.mapfuel), no dynamics;
    (a2) the bins' mean of the true map on the simulator's fine grid (the Jensen gap of (a) removed);
    (a3) (a2) with the true transient factor k_tr;
    (b)  (a3) through the ECU's 0.1 s mean-and-hold (sim.mapfuel.ecu_reported): the fuel itself, a check;
    (s)  the best static P-spline of the bins' mean speed and torque, fitted to this very fuel (in-sample);
    (c)  the identified engine model's map s against the true map, over the validation samples in covered cells;
    (f)  the model's steady state f (hammerstein.steady_state_map) against the true map, there;
    (d)  the identified engine model (`fuelid identify --model engine --fuel-lag 0` on the identification trip: the
         fuel as logged), simulated.

The same with both trips' fuel binned at its log time minus the ECU's update period (build_dataset's fuel_lag_s =
sim.mapfuel.LFE1_UPDATE_S, the simulator's own reporting lag; each bin's fuel is then the fuel of the interval of its
speed and torque), against that dataset's noise-free fuel:

    (a'), (a2'), (a3')  as (a), (a2), (a3);
    (j')  the Jensen gap: (a2') − (a'), the bins' mean of the true map against the true map at the bins' means;
    (s')  the static P-spline (ident.enginemap.fit_map) of the identification trip, on the validation trip;
    (d')  the engine model identified on the identification trip (ident.modelchoice.identify_chosen, the model
          `fuelid identify --model engine` builds), simulated on the validation trip.

    .venv/bin/python benchmarks/bench_engine_oracle.py [--seeds 1 2] [--engines LIST] [--noise STD] [--json]

The model also scores against the measured fuel (the number bench_engine_model reports) beside the noise floor.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parent)]
import bench_engine_model as bem  # noqa: E402  (benchmarks/ on the path: its simulation and CLI helpers)


def _rms(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x ** 2)))


def run_case(label: str, engine: str, seed: int, noise: float) -> dict:
    """The oracle rows of the module docstring for one engine and seed."""
    from fuelid.ident.dataset import build_dataset
    from fuelid.ident.enginemap import fit_map
    from fuelid.ident.hammerstein import engine_map_of, steady_state_map
    from fuelid.ident.modelfile import load_model
    from fuelid.ident.modelrun import run_model
    from fuelid.sim import mapfuel, vecto
    from fuelid.sim.catalog import validation_pair
    from fuelid.sim.trip import bin_means

    ident_cfg, valid_cfg = validation_pair(seed, "map", engine, noise)
    with tempfile.TemporaryDirectory(prefix="bench_oracle_") as tmp:
        folder = Path(tmp)
        ident_mcap, _ = bem._recording(ident_cfg, folder, "ident")
        valid_mcap, trip = bem._recording(valid_cfg, folder, "valid")
        bem._cli_json("identify", ident_mcap, "-o", folder / "model.json", "--model", "engine", "--fuel-lag", "0")
        model = load_model(folder / "model.json")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = build_dataset([valid_mcap])
            lagged = [build_dataset([p], fuel_lag_s=mapfuel.LFE1_UPDATE_S) for p in (ident_mcap, valid_mcap)]
    v = vecto.read_engine(engine)
    eng = mapfuel.sim_engine(v)
    to_l_h = 1.0 / (1000.0 * v.fuel_density_kg_l)
    noise_bin = trip.truth["fuel_noise_bin"]

    step = int(round(ds.Ts / valid_cfg.dt_s))
    starts = np.arange(0, len(trip.t_s), step)
    n_fine = trip.signals["engine_speed_rpm"]
    T_fine = trip.signals["torque_reported_pct"] / 100.0 * eng.reference_torque_nm
    map_fine = v.fuel_g_h(n_fine, T_fine - eng.friction_torque_nm(n_fine)) * to_l_h
    k_tr = mapfuel.transient_factor(v, T_fine, valid_cfg.dt_s)
    per_bin = {"a2_bin_mean_of_true_map": bin_means(map_fine, starts),
               "a3_with_transient_factor": bin_means(map_fine * k_tr, starts),
               "b_with_ecu_hold": bin_means(mapfuel.ecu_reported(map_fine * k_tr, valid_cfg.dt_s), starts)}

    def true_map(d) -> np.ndarray:  # at the bins' mean logged speed and torque (flywheel torque = bus − friction)
        n, T = np.nan_to_num(d.u[:, 0]), np.nan_to_num(d.u[:, 1])
        T_nm = T if d.input_units[1] == "Nm" else T / 100.0 * eng.reference_torque_nm
        return v.fuel_g_h(n, T_nm - eng.friction_torque_nm(n)) * to_l_h

    noise = bem.on_bins(ds, noise_bin, valid_cfg.start_unix_s)
    clean = ds.y - noise
    n, T = ds.u[:, 0], ds.u[:, 1]  # rpm, the model's torque unit
    run = run_model(model, ds)
    ok = np.isfinite(noise)
    settled = np.isfinite(run.settled(run.ysim)) & ok
    emap = engine_map_of(model)
    covered = settled & emap.covered(n, T) & (T > 0)
    best = fit_map(n[ok], T[ok], clean[ok], emap.operating_point, model.y0, ("rpm", ds.input_units[1], "L/h"))
    rows = {"a_true_map_at_bin_means": true_map(ds),
            **{name: bem.on_bins(ds, x, valid_cfg.start_unix_s) for name, x in per_bin.items()},
            "s_best_static_pspline": best(n, T)}
    out = {"engine": label, "seed": seed, "noise_floor_l_h": _rms(noise[settled])}
    out.update({name: _rms((x - clean)[settled]) for name, x in rows.items()})
    out["c_model_map_vs_true_map"] = _rms((emap(n, T) - rows["a_true_map_at_bin_means"])[covered])
    out["f_steady_state_vs_true_map"] = _rms((steady_state_map(model, n, T) - rows["a_true_map_at_bin_means"])[covered])
    out["d_model_vs_clean"] = _rms((run.y - run.ysim - noise)[settled])
    out["d_model_vs_measured"] = _rms((run.y - run.ysim)[settled])
    out.update(_rebinned(*lagged, noise_bin, valid_cfg.start_unix_s, true_map, per_bin))
    return out


def _rebinned(ident, valid, noise_bin: np.ndarray, start_unix_s: float, true_map, per_bin: dict) -> dict:
    """The primed rows of the module docstring on the datasets built with the fuel's lag taken out: RMS [L/h]
    against the validation trip's noise-free fuel over the engine model's settled samples, and the model's against
    the measured fuel. true_map(dataset): the true map at its bins' means; per_bin: the truth's rows (a2), (a3)
    per bin of the trip."""
    from fuelid.ident.enginemap import fit_map
    from fuelid.ident.identify import MIN_SEGMENT_S
    from fuelid.ident.modelchoice import ModelKind, identify_chosen
    from fuelid.ident.modelrun import run_model
    from fuelid.ident.polymodel import Structure, parse_orders

    noise = bem.on_bins(valid, noise_bin, start_unix_s)
    ok = np.isfinite(noise)
    v = ident.valid
    static = fit_map(ident.u[v, 0], ident.u[v, 1], ident.y[v], ident.u0, ident.y0,
                     ("rpm", ident.input_units[1], ident.output_unit))
    model = identify_chosen(ident, Structure(**parse_orders("paper")), kind=ModelKind.ENGINE,
                            min_segment_s=MIN_SEGMENT_S)
    run = run_model(model, valid)
    settled = np.isfinite(run.settled(run.ysim)) & ok
    n, T = valid.u[:, 0], valid.u[:, 1]
    clean = valid.y - noise
    a = true_map(valid)
    a2, a3 = (bem.on_bins(valid, per_bin[k], start_unix_s)
              for k in ("a2_bin_mean_of_true_map", "a3_with_transient_factor"))
    return {"a'_true_map_at_bin_means_rebinned": _rms((a - clean)[settled]),
            "a2'_bin_mean_of_true_map_rebinned": _rms((a2 - clean)[settled]),
            "a3'_with_transient_factor_rebinned": _rms((a3 - clean)[settled]),
            "j'_jensen_gap_rebinned": _rms((a2 - a)[settled]),
            "s'_static_pspline_rebinned": _rms((np.where(T > 0, static(n, T), 0.0) - clean)[settled]),
            "d'_model_rebinned_vs_clean": _rms((run.y - run.ysim - noise)[settled]),
            "d'_model_rebinned_vs_measured": _rms((run.y - run.ysim)[settled])}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    p.add_argument("--engines", help="comma-separated VECTO engines (folder names in ../shared/engines; default all)")
    p.add_argument("--noise", type=float, default=0.5, help="fuel noise std [L/h] (0.5)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    engines = {k: e for k, e in bem.engine_sets(args.engines).items() if k != bem.PAPER}
    rows = [run_case(label, engine, s, args.noise) for label, engine in engines.items() for s in args.seeds]
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    keys = [k for k in rows[0] if k not in ("engine", "seed")]
    print("RMS [L/h] on the validation trip, per engine / seed:")
    print(f"{'':32}" + "".join(f"{r['engine'].split('_')[1] + '/' + str(r['seed']):>12}" for r in rows))
    for key in keys:
        print(f"{key:32}" + "".join(f"{r[key]:12.3f}" for r in rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
