"""Validation metrics of seed paper 000 (Section IV–V): fit, whiteness tests, cumulative fuel error.

Plain functions over arrays. Samples that are NaN (invalid stretches of a dataset) are left out of every
sum, so a signal with gaps can be passed as it is; a model is run per segment by ident.modelrun, whose
ModelRun `metrics` reads (``evaluate`` runs a PolyModel on a Dataset and reads it).

Correlations follow Ljung, *System Identification* (1999), §16.6, as MATLAB's ``resid`` does:

    R_e(h)  = 1/N Σ_k e(k+h) e(k)                       (biased estimate, N = number of valid samples)
    R_eu(h) = 1/N Σ_k e(k+h) u(k)                       (u(k) leads e(k+h) for h > 0)

and are reported normalised, r_e(h) = R_e(h)/R_e(0), r_eu(h) = R_eu(h)/sqrt(R_e(0) R_u(0)). The paper's
99 % bounds, eqs. (18)–(19), on the normalised values read

    |r_e(h)|  < z / sqrt(N)                              (18), h ≠ 0
    |r_eu(h)| < z sqrt(Σ_{|i|≤M} r_e(i) r_u(i) / N)       (19)

with z = 2.58 for 99 % (the normal quantile Φ⁻¹(0.995)); the infinite sum of (19) is truncated at the
tested lag range M, as MATLAB does.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtri

from fuelid.blas import in_one_blas_thread
from fuelid.errors import FuelidError, InputError
from fuelid.ident.modelrun import ModelRun, run_model
from fuelid.ident.polymodel import predict


@dataclass(frozen=True)
class CorrelationTest:
    """Result of a whiteness / independence test.

    lags   sample lags [samples] at which r was estimated
    r      normalised correlation at each lag [-]
    bound  the confidence bound on |r| [-] (same for all lags)
    passed True when |r| < bound at every tested lag (see the function for which lags are tested)
    """
    lags: np.ndarray
    r: np.ndarray
    bound: float
    passed: bool

    def outside(self) -> np.ndarray:
        """The lags [samples] where |r| ≥ bound (including untested ones, e.g. lag 0 of an autocorrelation)."""
        return self.lags[np.abs(self.r) >= self.bound]


def _z(confidence: float) -> float:
    return float(ndtri(0.5 + confidence / 2.0))  # the standard normal's quantile (scipy.stats.norm.ppf)


def _centred(x) -> tuple[np.ndarray, np.ndarray]:
    """x minus its mean over finite samples, with non-finite samples set to 0; and the finite mask."""
    x = np.asarray(x, dtype=float)
    ok = np.isfinite(x)
    if not ok.any():
        raise InputError("no finite samples")
    x = np.where(ok, x - x[ok].mean(), 0.0)
    return x, ok


def _xcov(a: np.ndarray, b: np.ndarray, lags: np.ndarray, n: int) -> np.ndarray:
    """R_ab(h) = 1/n Σ_k a(k+h) b(k) for each h in lags (a, b zero where invalid)."""
    out = np.empty(len(lags))
    N = len(a)
    for i, h in enumerate(lags):
        out[i] = a[h:] @ b[:N - h] / n if h >= 0 else a[:N + h] @ b[-h:] / n
    return out


@in_one_blas_thread  # its long dot products: BLAS threads cost more time than they save (fuelid.blas)
def autocorr_test(e, max_lag: int = 25, confidence: float = 0.99) -> CorrelationTest:
    """Whiteness of the prediction error e (any unit), eq. (18).

    r is returned for lags 0..max_lag (r(0) = 1); `passed` tests lags 1..max_lag.
    """
    e, ok = _centred(e)
    n = int(ok.sum())
    lags = np.arange(0, max_lag + 1)
    R = _xcov(e, e, lags, n)
    r = R / R[0] if R[0] > 0 else np.zeros_like(R)
    bound = _z(confidence) / np.sqrt(n)
    return CorrelationTest(lags, r, bound, bool(np.all(np.abs(r[1:]) < bound)))


@in_one_blas_thread
def crosscorr_test(e, u, max_lag: int = 25, confidence: float = 0.99, feedback: bool = True):
    """Independence of the prediction error e from one input u (any units), eq. (19).

    r is returned for lags -max_lag..max_lag; r at lag h > 0 correlates u(k) with the later e(k+h).
    With feedback=True (the paper's reading for engine torque: fuel flow drives future torque) only lags
    h ≥ 0 decide `passed`; with feedback=False all lags do. e and u must have the same length; a sample
    invalid in either is left out of both.
    u may be N×m: the result is then a list of m CorrelationTest, one per column.
    """
    u = np.asarray(u, dtype=float)
    if u.ndim == 2:
        return [crosscorr_test(e, u[:, j], max_lag, confidence, feedback) for j in range(u.shape[1])]
    e = np.asarray(e, dtype=float)
    if e.shape != u.shape:
        raise ValueError(f"e and u differ in length: {e.shape} vs {u.shape}")
    both = np.isfinite(e) & np.isfinite(u)
    e, _ = _centred(np.where(both, e, np.nan))
    u, _ = _centred(np.where(both, u, np.nan))
    n = int(both.sum())
    lags = np.arange(-max_lag, max_lag + 1)
    Re0, Ru0 = e @ e / n, u @ u / n
    scale = np.sqrt(Re0 * Ru0)
    r = _xcov(e, u, lags, n) / scale if scale > 0 else np.zeros(len(lags))
    re = _xcov(e, e, lags, n) / Re0 if Re0 > 0 else np.zeros(len(lags))
    ru = _xcov(u, u, lags, n) / Ru0 if Ru0 > 0 else np.zeros(len(lags))
    bound = _z(confidence) * np.sqrt(max(float(re @ ru), 0.0) / n)
    tested = lags >= 0 if feedback else np.ones(len(lags), bool)
    return CorrelationTest(lags, r, bound, bool(np.all(np.abs(r[tested]) < bound)))


@in_one_blas_thread
def fit_percent(y, yhat) -> float:
    """Normalised root-mean-square fit [%] as MATLAB's ``compare``: 100 (1 − ‖y − ŷ‖ / ‖y − ȳ‖).

    y, ŷ in the same unit; samples non-finite in either are left out. 100 is perfect, 0 is as good as the
    mean, negative is worse than the mean.
    """
    y, yhat = np.asarray(y, float), np.asarray(yhat, float)
    ok = np.isfinite(y) & np.isfinite(yhat)
    y, yhat = y[ok], yhat[ok]
    return float(100.0 * (1.0 - np.linalg.norm(y - yhat) / np.linalg.norm(y - y.mean())))


def rmse(y, yhat) -> float:
    """Root-mean-square error sqrt(mean((y − ŷ)²)) in the unit of y, over samples finite in both."""
    d = np.asarray(y, float) - np.asarray(yhat, float)
    return float(np.sqrt(np.mean(d[np.isfinite(d)] ** 2)))


def cycle_fuel_error(y, yhat, cycle, Ts: float) -> dict[int, float]:
    """Cumulative fuel error per drive cycle [%], eq. (20):

        E_c = (∫ f_model dt − ∫ f_measured dt) / ∫ f_measured dt × 100 %

    y, ŷ: absolute fuel flow (not deviations from the operating point) in one unit, e.g. L/h;
    cycle: per-sample drive-cycle id (int, negative = not in any cycle); Ts: sampling interval [s].
    The integrals are rectangle sums Σ f Ts over the samples finite in both y and ŷ, so gaps count for
    neither. Cycles whose measured integral is not positive are left out.
    """
    y, yhat, cycle = np.asarray(y, float), np.asarray(yhat, float), np.asarray(cycle)
    ok = np.isfinite(y) & np.isfinite(yhat) & (cycle >= 0)
    out = {}
    for c in np.unique(cycle[ok]):
        m = ok & (cycle == c)
        measured = y[m].sum() * Ts
        if measured > 0:
            out[int(c)] = float((yhat[m].sum() * Ts - measured) / measured * 100.0)
    return out


def error_table(errors) -> dict[str, float]:
    """Mean and RMS [%] of per-cycle errors [%], as in Table I of paper 000: mean = Σ E_c / n,
    rms = sqrt(Σ E_c² / n). Accepts a dict (cycle → error) or a sequence; NaN when empty."""
    v = np.asarray(list(errors.values()) if isinstance(errors, dict) else errors, float)
    if v.size == 0:
        return {"mean": float("nan"), "rms": float("nan")}
    return {"mean": float(v.mean()), "rms": float(np.sqrt(np.mean(v ** 2)))}


def evaluate(model, ds, k: int = 1, max_lag: int = 25) -> dict:
    """The validation metrics of a PolyModel on a Dataset, JSON-ready: `metrics` of its run (ident.modelrun).

    The model's inputs are the data's engine speed and torque plus those of the effects it includes
    (ident.modeldata.model_data; the fuel shifted when it includes the fuel delay). Raises FuelidError when its
    units are not the data's or the data lack its effects' signals."""
    check_units(model, ds)
    return metrics(run_model(model, ds), ds, k, max_lag)


def check_units(model, ds) -> None:
    """Raise FuelidError unless the model's speed, torque and fuel units are the dataset's."""
    if tuple(model.input_units[:2]) != tuple(ds.input_units) or model.output_unit != ds.output_unit:
        raise FuelidError(f"model units {list(model.input_units[:2])} -> {model.output_unit} do not match the "
                          f"data's {list(ds.input_units)} -> {ds.output_unit}")


def metrics(run: ModelRun, ds, k: int = 1, max_lag: int = 25) -> dict:
    """The validation metrics of a model run (ident.modelrun.ModelRun) on dataset ds, JSON-ready.

    The model ran on each segment of ds separately from zero initial state, and its first n_start samples per
    segment, where the state is unknown, are left out of every metric: simulation ŷ_s, k-step prediction ŷ_k,
    one-step residual ε.
    Returns
      fit_percent {simulation, prediction}   [%]   (fit_percent)
      rmse {simulation, prediction}          [output unit]
      whiteness {autocorr_pass, crosscorr_pass {input name: bool}, max_lag}   (eqs. 18–19 on ε)
      cycle_fuel_error_percent {cycle id: E, mean, rms}   (eq. 20 on ŷ_s, absolute flow)
    """
    check_units(run.model, ds)
    model, u, eps = run.model, run.u, run.eps
    ysim = run.settled(run.ysim)
    if k == 1:
        ypred = run.settled(run.ypred)
    else:
        ypred = np.full(len(run.y), np.nan)
        for s in run.segments:
            ypred[s] = predict(model, u[s], run.y[s], k)
        ypred = run.settled(ypred)
    used = np.isfinite(eps)
    y = np.where(used, run.y, np.nan)
    auto = autocorr_test(eps, max_lag)
    cross = crosscorr_test(eps, np.where(used[:, None], u, np.nan), max_lag)
    cycles = cycle_fuel_error(y, ysim, ds.cycle, ds.Ts)
    return {
        "fit_percent": {"simulation": fit_percent(y, ysim), "prediction": fit_percent(y, ypred)},
        "rmse": {"simulation": rmse(y, ysim), "prediction": rmse(y, ypred)},
        "prediction_horizon": k,
        "whiteness": {"autocorr_pass": auto.passed, "max_lag": max_lag,
                      "crosscorr_pass": {name: c.passed for name, c in zip(model.input_names, cross)}},
        "cycle_fuel_error_percent": {**{str(c): e for c, e in cycles.items()}, **error_table(cycles)},
    }


def evaluate_static(yhat, ds) -> dict:
    """fit, rmse and cycle fuel errors of a static prediction yhat (N) [output unit] on ds's valid samples."""
    y = np.where(ds.valid, ds.y, np.nan)
    cycles = cycle_fuel_error(y, yhat, ds.cycle, ds.Ts)
    return {
        "fit_percent": {"simulation": fit_percent(y, yhat)},
        "rmse": {"simulation": rmse(y, yhat)},
        "cycle_fuel_error_percent": {**{str(c): e for c, e in cycles.items()}, **error_table(cycles)},
    }


WHITENESS_MEANING = ("The residual tests ask whether the 1-step prediction errors are white and uncorrelated with "
                     "the inputs: a pass means no dynamics of speed and torque are left in the errors, not that "
                     "nothing is missing - an effect acting through another signal (a regeneration, the weather) "
                     "leaves them white; the candidate tests below ask that.")
