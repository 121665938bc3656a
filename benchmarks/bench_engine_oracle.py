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
    (jb') the part of (j') the bus's own samples show: the mean of the true map over each bin's EEC1 samples of
          speed and torque (as the recording holds them: every 20 ms, in the DBC's 0.125 rpm and 1 %), against the
          true map at the bins' means; what is left, (j') beside (jb'), is how 20 ms samples alias the torque's steps;
    (s')  the static P-spline (ident.enginemap.fit_map) of the identification trip, on the validation trip;
    (t')  the model class with a perfect map: the true map at the bins' means and the engine model's torque-rise
          columns with it (r, r·f, and both through a first-order lag of 1 s; ident.effects.torque_rise) as a static
          least-squares regression fitted to the identification trip's measured fuel, on the validation trip;
    (tb') (t') with the true map averaged over the bus's samples within each bin (as jb');
    (p')  what an identified map can do there: (t') with the P-spline (ident.enginemap) on the knots and smoothing of
          (d')'s map in place of the true map, its coefficients fitted with the other columns (penalised least
          squares, the torque-rise products with (d')'s map), basis at the bins' means;
    (pb') (p') with the basis averaged over the bus's samples within each bin;
    (p'i), (d'i)  (p') and (d') on the identification trip they were fitted to (in sample);
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


RISE_LAG_S = 1.0  # [s] the first-order lag of (t')'s lagged torque-rise columns


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
        ident_mcap, ident_trip = bem._recording(ident_cfg, folder, "ident")
        valid_mcap, trip = bem._recording(valid_cfg, folder, "valid")
        bus = [_eec1_samples(path) for path in (ident_mcap, valid_mcap)]
        bem._cli_json("identify", ident_mcap, "-o", folder / "model.json", "--model", "engine", "--fuel-lag", "0")
        model = load_model(folder / "model.json")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = build_dataset([valid_mcap])
            lagged = [build_dataset([p], fuel_lag_s=mapfuel.LFE1_UPDATE_S) for p in (ident_mcap, valid_mcap)]
    v = vecto.read_engine(engine)
    eng = mapfuel.sim_engine(v)
    to_l_h = 1.0 / (1000.0 * v.fuel_density_kg_l)

    def map_l_h(n_rpm, T_bus_nm):  # the true map [L/h] at the bus's speed and torque (flywheel = bus − friction)
        return v.fuel_g_h(n_rpm, T_bus_nm - eng.friction_torque_nm(n_rpm)) * to_l_h
    noise_bin = trip.truth["fuel_noise_bin"]

    step = int(round(ds.Ts / valid_cfg.dt_s))
    starts = np.arange(0, len(trip.t_s), step)
    n_fine = trip.signals["engine_speed_rpm"]
    T_fine = trip.signals["torque_reported_pct"] / 100.0 * eng.reference_torque_nm
    map_fine = map_l_h(n_fine, T_fine)
    k_tr = mapfuel.transient_factor(v, T_fine, valid_cfg.dt_s)
    per_bin = {"a2_bin_mean_of_true_map": bin_means(map_fine, starts),
               "a3_with_transient_factor": bin_means(map_fine * k_tr, starts),
               "b_with_ecu_hold": bin_means(mapfuel.ecu_reported(map_fine * k_tr, valid_cfg.dt_s), starts)}

    def true_map(d) -> np.ndarray:  # at the bins' mean logged speed and torque
        n, T = np.nan_to_num(d.u[:, 0]), np.nan_to_num(d.u[:, 1])
        return map_l_h(n, T if d.input_units[1] == "Nm" else T / 100.0 * eng.reference_torque_nm)

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
    ident_noise = bem.on_bins(lagged[0], ident_trip.truth["fuel_noise_bin"], ident_cfg.start_unix_s)
    out.update(_rebinned(*lagged, noise_bin, valid_cfg.start_unix_s, true_map, map_l_h, per_bin, bus,
                         eng.reference_torque_nm, ident_noise))
    return out


def _rise_columns(d, f: np.ndarray) -> np.ndarray:
    """The engine model's torque-rise columns on dataset d (r, r·f, and both through a first-order lag of
    RISE_LAG_S; ident.effects.torque_rise), f a map's fuel per sample [L/h]."""
    from scipy.signal import lfilter

    from fuelid.ident.effects import torque_rise

    r = np.nan_to_num(torque_rise(d.u[:, 1], d.t, d.input_units[1]))
    a = d.Ts / (RISE_LAG_S + d.Ts)
    lagged = lfilter([a], [1.0, a - 1.0], r)
    f = np.nan_to_num(f)
    return np.column_stack([r, r * f, lagged, lagged * f])


def _regression(ident, X_ident: np.ndarray, X_other: np.ndarray, penalty: np.ndarray | None = None):
    """Least squares of dataset ident's fuel on X_ident (valid samples, finite rows), plus λ'‖R c‖² on the leading
    columns with `penalty` = λ'RᵀR; the fitted columns' prediction X_other c [L/h] (another trip's columns, or
    X_ident's own)."""
    fit = ident.valid & np.isfinite(ident.y) & np.isfinite(X_ident).all(axis=1)
    X, y = X_ident[fit], ident.y[fit]
    A = X.T @ X
    if penalty is not None:
        A[: len(penalty), : len(penalty)] += penalty
    return X_other @ np.linalg.lstsq(A, X.T @ y, rcond=None)[0]


def _eec1_samples(mcap: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The recording's EEC1 samples from the engine (SA 0): log time [ns], speed [rpm] (SPN 190), actual torque [%]
    (SPN 513), both present."""
    from fuelid.logger.mcap_log import read_messages

    t, n, T = zip(*((log_time, r["EngSpeed"], r["ActualEngPercentTorque"])
                    for _, log_time, r in read_messages(mcap, "/j1939/EEC1")
                    if r.get("sa") == 0 and r.get("EngSpeed") is not None
                    and r.get("ActualEngPercentTorque") is not None))
    return np.array(t, np.int64), np.array(n, float), np.array(T, float)


def _bin_means(d, samples, values: np.ndarray) -> np.ndarray:
    """Per sample of dataset d (its bins [k Ts, (k + 1) Ts) on the log clock): the mean of `values` (per bus sample,
    1-D or N × K) over the bus samples in its bin, NaN where it has none."""
    ts_ns = int(round(d.Ts * 1e9))
    k0 = int(np.rint(d.t[0] / d.Ts))
    k = samples[0] // ts_ns - k0
    rows = np.rint(d.t / d.Ts).astype(np.int64) - k0  # each sample's bin, from the first (the grid may have gaps)
    size = int(rows[-1]) + 1
    inside = (k >= 0) & (k < size)
    count = np.bincount(k[inside], minlength=size)
    cols = values.reshape(len(k), -1)[inside]
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.column_stack([np.bincount(k[inside], c, minlength=size) for c in cols.T]) / count[:, None]
    out = out[rows]
    return out[:, 0] if values.ndim == 1 else out


def _rebinned(ident, valid, noise_bin: np.ndarray, start_unix_s: float, true_map, map_l_h, per_bin: dict, bus,
              reference_nm: float, ident_noise: np.ndarray) -> dict:
    """The primed rows of the module docstring on the datasets built with the fuel's lag taken out: RMS [L/h]
    against the validation trip's noise-free fuel over the engine model's settled samples, and the model's against
    the measured fuel. true_map(dataset): the true map at its bins' means; map_l_h(n [rpm], T [N m]): the true map;
    per_bin: the truth's rows (a2), (a3) per bin of the trip; bus: the EEC1 samples (`_eec1_samples`) of the
    identification trip, of the validation trip; reference_nm: the engine's reference torque (SPN 544) [N m];
    ident_noise: the identification trip's fuel noise per sample of ident [L/h]."""
    from fuelid.ident.enginemap import fit_map, penalty_gram
    from fuelid.ident.hammerstein import engine_map_of
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
    ab_ident, ab = (_bin_means(d, s, map_l_h(s[1], s[2] / 100.0 * reference_nm)) for d, s in zip((ident, valid), bus))

    def with_rise(d, f):
        return np.column_stack([np.ones(len(d.t)), f, _rise_columns(d, f)])

    t = _regression(ident, with_rise(ident, true_map(ident)), with_rise(valid, a))
    tb = _regression(ident, with_rise(ident, ab_ident), with_rise(valid, ab))
    emap = engine_map_of(model)  # (p'), (pb'): its knots and smoothing, the rise products with its map

    def unit(T_pct):  # bus torque [%] in the datasets' torque unit
        return T_pct / 100.0 * reference_nm if valid.input_units[1] == "Nm" else T_pct

    def spline_rise(d, basis):
        return np.column_stack([basis, _rise_columns(d, emap(d.u[:, 0], d.u[:, 1]))])

    phi_i, phi_v = (emap.basis(d.u[:, 0], d.u[:, 1]) for d in (ident, valid))
    P = penalty_gram(*emap.coef.shape)
    penalty = emap.smoothing * np.trace(phi_i[ident.valid].T @ phi_i[ident.valid]) / np.trace(P) * P  # λ' RᵀR
    p_ = _regression(ident, spline_rise(ident, phi_i), spline_rise(valid, phi_v), penalty)
    pb_i, pb_v = (_bin_means(d, s, emap.basis(s[1], unit(s[2]))) for d, s in zip((ident, valid), bus))
    pb = _regression(ident, spline_rise(ident, pb_i), spline_rise(valid, pb_v), penalty)
    p_in = _regression(ident, spline_rise(ident, phi_i), spline_rise(ident, phi_i), penalty)
    run_in = run_model(model, ident)
    settled_in = np.isfinite(run_in.settled(run_in.ysim)) & np.isfinite(ident_noise)
    return {"a'_true_map_at_bin_means_rebinned": _rms((a - clean)[settled]),
            "a2'_bin_mean_of_true_map_rebinned": _rms((a2 - clean)[settled]),
            "a3'_with_transient_factor_rebinned": _rms((a3 - clean)[settled]),
            "j'_jensen_gap_rebinned": _rms((a2 - a)[settled]),
            "jb'_jensen_gap_bus_samples": _rms((ab - a)[settled]),
            "s'_static_pspline_rebinned": _rms((np.where(T > 0, static(n, T), 0.0) - clean)[settled]),
            "t'_true_map_rise_columns": _rms((t - clean)[settled]),
            "tb'_bus_mean_map_rise_columns": _rms((tb - clean)[settled]),
            "p'_identified_spline_rise_columns": _rms((p_ - clean)[settled]),
            "pb'_bus_mean_spline_rise_columns": _rms((pb - clean)[settled]),
            "p'i_on_identification_trip": _rms((p_in - (ident.y - ident_noise))[settled_in]),
            "d'i_on_identification_trip": _rms((run_in.y - run_in.ysim - ident_noise)[settled_in]),
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
