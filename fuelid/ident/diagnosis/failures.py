"""Where the model fails: residual whiteness and input cross-correlation (paper 000 eqs. 18–19, as
ident.validation computes them), the worst stretches of the simulation error with the driving context that
covers them, and the error over the speed × torque plane. The compare section is ident.validation.metrics."""
from __future__ import annotations

import numpy as np

from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.run import Run
from fuelid.ident.polymodel import PolyModel
from fuelid.ident.validation import autocorr_test, crosscorr_test

CONTEXT_EFFECTS = ("gear_shift", "overrun_cutoff", "idle_fuelling", "dpf_regeneration", "cold_engine", "pto",
                   "retarder", "engine_fan")


def context_flags(ds) -> dict[str, np.ndarray]:
    """Per sample, whether each driving context (gear shift, overrun, idle, DPF regeneration, cold engine, PTO,
    retarder, fan) holds, from the bus signals that are logged."""
    flags = {}
    for eid in CONTEXT_EFFECTS:
        reg = fx.EFFECTS[eid].build(ds)
        if reg is not None:
            flags[fx.EFFECTS[eid].name] = reg.x[:, 0] > 1e-3
    return flags


def worst_segments(ds, run: Run, window_s: float = 30.0, n: int = 5, share: float = 0.2) -> list[dict]:
    """The n non-overlapping windows of window_s [s] with the largest RMS simulation error, each with its start
    and end (log time [s] and minutes since the first sample), bias, mean speed and torque, and the contexts
    that set it apart from the trip: a context is named when it covers at least `share` more of the window than
    of the trip's valid samples (a fan running all trip says nothing about where the model fails)."""
    err = run.ysim - run.y
    ok = np.isfinite(err)
    w = max(int(round(window_s / ds.Ts)), 1)
    kernel = np.ones(w)
    cnt = np.convolve(ok, kernel, "same")
    ms = np.convolve(np.where(ok, err**2, 0.0), kernel, "same") / np.maximum(cnt, 1)
    ms[cnt < 0.8 * w] = -1.0
    flags = context_flags(ds)
    trip_share = {name: f[ok].mean() if ok.any() else 0.0 for name, f in flags.items()}
    out = []
    for _ in range(n):
        c = int(np.argmax(ms))
        if ms[c] < 0:
            break
        sl = slice(max(c - w // 2, 0), c + w - w // 2)
        m = ok[sl]
        ctx = [name for name, f in flags.items() if f[sl][m].mean() - trip_share[name] >= share]
        t_start, t_end = float(ds.t[sl.start]), float(ds.t[min(sl.stop, len(ds.t)) - 1])
        out.append({
            "t_start_s": t_start, "t_end_s": t_end,
            "t_start_min": (t_start - float(ds.t[0])) / 60.0, "t_end_min": (t_end - float(ds.t[0])) / 60.0,
            "rmse": float(np.sqrt(ms[c])), "bias": float(np.mean(err[sl][m])),
            "speed_rpm": float(np.mean(ds.u[sl, 0][m])), "torque": float(np.mean(ds.u[sl, 1][m])),
            "context": ctx,
        })
        ms[max(c - w, 0): c + w] = -1.0
    return out


def error_map(ds, run: Run, bins: int = 8, min_count: int = 20) -> dict:
    """Simulation error (model − measured) over the speed × torque plane: equal-width bins over the valid
    range; per cell the sample count, mean error (bias) and RMS error [output unit], null under min_count."""
    err = run.ysim - run.y
    ok = np.isfinite(err)
    n, T = ds.u[ok, 0], ds.u[ok, 1]
    e_n = np.linspace(n.min(), n.max() + 1e-9, bins + 1)
    e_T = np.linspace(T.min(), T.max() + 1e-9, bins + 1)
    cnt = np.histogram2d(n, T, [e_n, e_T])[0]
    s1 = np.histogram2d(n, T, [e_n, e_T], weights=err[ok])[0]
    s2 = np.histogram2d(n, T, [e_n, e_T], weights=err[ok] ** 2)[0]
    good = cnt >= min_count
    mean = np.where(good, s1 / np.maximum(cnt, 1), np.nan)
    rms = np.where(good, np.sqrt(s2 / np.maximum(cnt, 1)), np.nan)
    nul = lambda a: [[None if not np.isfinite(v) else float(v) for v in row] for row in a]  # noqa: E731
    return {"speed_edges_rpm": e_n.tolist(), "torque_edges": e_T.tolist(), "torque_unit": ds.input_units[1],
            "count": cnt.astype(int).tolist(), "mean_error": nul(mean), "rms_error": nul(rms)}


def where_it_fails(model: PolyModel, ds, run: Run, max_lag: int = 25) -> dict:
    """Residual whiteness and input cross-correlation (paper eqs. 18–19, 99 % bounds), the worst segments with
    their context, and the error map."""
    auto = autocorr_test(run.eps, max_lag)
    cross = crosscorr_test(run.eps, np.where(np.isfinite(run.eps)[:, None], run.u, np.nan), max_lag)
    test = lambda c: {"passed": c.passed, "bound": c.bound, "lags": c.lags.tolist(), "r": c.r.tolist(),  # noqa: E731
                      "outside_lags": c.outside().tolist()}
    return {
        "whiteness": {"autocorr_pass": auto.passed, "autocorr": test(auto),
                      "crosscorr_pass": {name: c.passed for name, c in zip(model.input_names, cross)},
                      "crosscorr": {name: test(c) for name, c in zip(model.input_names, cross)}},
        "worst_segments": worst_segments(ds, run),
        "error_map": error_map(ds, run),
    }
