"""Screening: which candidate effects are worth building. Each candidate's columns as its entry kind makes them
(ident.effects.Effect.enters), both score tests of ident.diagnosis.statistics on the model's run, and Holm over the
family tested together.

    additive     y + Σ_l β_l x(t − l): the effect's columns at its lags
    scales_fuel  y (1 + m x): the columns x and x·ŷ (ŷ the model's simulated fuel: the gradient at m = 0)
    torque       a torque T + κ x the bus does not report: its fuel through the model's torque path, B_T/(A F_T) x,
                 on an engine model plus B_m/(A F_m) x·∂m/∂T (the map's input moves by ∂m/∂T κ x: the fuel of a
                 torque follows the map's marginal fuel, ident.modeldata.map_sloped)
    shift        the fuel signal's delay y(t − τ) ≈ y(t) − τ dy/dt: the column dŷ/dt of the model's simulated fuel;
                 τ̂ = −β̂ is what the yardstick builds (fuel_delay=τ̂)
"""
from __future__ import annotations

import math

import numpy as np

from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.candidate import Screening
from fuelid.ident.diagnosis.run import Run
from fuelid.ident.diagnosis.statistics import holm, lagged, level_test, score_test
from fuelid.ident.filters import lfilter
from fuelid.ident.hammerstein import MAP_COLUMN, MAP_EFFECT
from fuelid.ident.modeldata import at_operating_point, map_slope, map_sloped
from fuelid.ident.polymodel import PolyModel

MAX_DELAY_S = 2.0  # [s] |τ̂| beyond this is not a signal path's delay: the first-order estimate is clipped to it


def regressors(effect: fx.Effect, model: PolyModel, dsm, run: Run) -> fx.Regressors | None:
    """The regressors the screening tests for `effect` on the dataset grid (dsm the data at the model's operating
    point); None when its signals are not logged."""
    if effect.enters == "shift":
        slope = np.full(len(dsm.t), np.nan)
        for s in run.segs:
            slope[s] = np.gradient(run.ysim[s], dsm.Ts)
        return fx.Regressors(slope[:, None], ("d/dt model fuel",), (f"{dsm.output_unit}/s",))
    reg = effect.build(dsm)
    if reg is not None and effect.enters == "torque" and MAP_COLUMN in model.input_names:
        return map_sloped(reg, map_slope(dsm, model.info["effect_parameters"][MAP_EFFECT]), dsm.output_unit,
                          dsm.input_units[1])
    if reg is None or effect.enters != "scales_fuel":
        return reg
    x = reg.x[:, 0]
    return fx.Regressors(np.column_stack([x, x * run.ysim]), (reg.names[0], f"{reg.names[0]} x model fuel"),
                         (reg.units[0], f"{reg.units[0]}.{dsm.output_unit}"))


def columns(effect: fx.Effect, model: PolyModel, reg: fx.Regressors, run: Run) -> tuple[np.ndarray, np.ndarray]:
    """(ψ_x = D/C x, the columns of the prediction-error test; w = A x, those of the simulation-error test), x the
    lagged regressors in the fuel domain (a torque through the model's torque path, and on an engine model its
    map's slope: the module docstring), stacked like run.e."""
    lags = (0,) if effect.enters == "shift" else effect.lags
    j = model.input_names.index(MAP_COLUMN) if MAP_COLUMN in model.input_names else None
    psi, raw = [], []
    for seg in run.segs:
        x = np.nan_to_num(reg.x[seg])
        if effect.enters == "torque":  # the fuel of the torque x: through the torque path (and the map's slope)
            x = lfilter(model.B[1], np.convolve(model.A, model.F[1]), x[:, :1], axis=0) + (
                lfilter(model.B[j], np.convolve(model.A, model.F[j]), x[:, 1:], axis=0) if j is not None else 0.0)
        x = lagged(x, lags)
        psi.append(lfilter(model.D, model.C, x, axis=0)[run.warm:])
        raw.append(x[run.warm:])
    raw = np.vstack(raw)
    return np.vstack(psi), lfilter(model.A, [1.0], raw, axis=0)


def test(effect: fx.Effect, model: PolyModel, dsm, run: Run) -> tuple[float, int, float, tuple] | None:
    """(log p — Bonferroni over the two tests —, degrees of freedom, the larger statistic, share [%] of the
    simulation error the least-squares fit explains, the simulation-error test's coefficients) of `effect` on
    `model`; None when its signals are not logged."""
    reg = regressors(effect, model, dsm, run)
    if reg is None:
        return None
    psi, w = columns(effect, model, reg, run)
    pred = score_test(run.e, psi, run.Q, eps_projected=run.e_projected)
    level, left = level_test(run.r, w, run.lens, run.QG)
    log_p = min(0.0, math.log(2.0) + min(pred.log_p, level.log_p))
    stat = max(pred.statistic, level.statistic)
    return log_p, max(pred.df, level.df), stat, 100.0 * (1.0 - left), tuple(np.ravel(level.coef))


def screen(effects: list[fx.Effect], model: PolyModel, ds, run: Run, alpha: float) -> dict[str, Screening | None]:
    """Every effect's Screening on `model` (run: its Run on ds), Holm over those testable (df > 0) at alpha; None for
    an effect whose signals are not logged or whose columns the model's own span (df = 0)."""
    dsm = at_operating_point(ds, model)
    found = {e.id: test(e, model, dsm, run) for e in effects}
    family = [k for k, f in found.items() if f is not None and f[1] > 0]
    log_p = np.array([found[k][0] for k in family])
    adj, sig = holm(np.exp(log_p), alpha) if family else (np.zeros(0), np.zeros(0, bool))
    out: dict[str, Screening | None] = {k: None for k in found}
    for k, a, s, lp in zip(family, adj, sig, log_p):
        # p-values below ~1e-300 underflow: compare log p with Holm's first bound log(alpha / m) then
        rejected = bool(s or lp < math.log(alpha / len(family)))
        _, df, stat, explains, coef = found[k]
        out[k] = Screening(float(stat), int(df), float(math.exp(lp)), float(lp / math.log(10)), float(a), rejected,
                           float(explains), coef)
    return out


def delay_estimate(s: Screening) -> float:
    """τ̂ [s] of a fuel delay from its screening: y(t − τ) ≈ y(t) − τ dy/dt, so the coefficient of dŷ/dt is −τ."""
    return float(np.clip(-s.coef[0], -MAX_DELAY_S, MAX_DELAY_S)) if s.coef else 0.0
