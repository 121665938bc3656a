"""The yardstick: does the model `fuelid identify` builds with a candidate simulate data it was not fitted on better
than the base model, by more than the spread of fits?

Folds. With several trips (breaks of the log of at least trip_break_s: other files, other days) each trip is a fold;
on one trip, fold k holds the chunks c ≡ k (mod folds) of chunk_s seconds (interleaved: every fit sees every part
of the trip). Scoring blocks are block_s long. For each fold the base model is refitted by PEM on the other folds'
samples from itself, and the candidate's model from that fold base with the candidate's coefficients at zero
(ident.identify.refit_with_effects: a warm start, so the two fits are nested and paired), or on an engine-model base
from the candidate's model identified on all the data (ident.diagnosis.selection); both are simulated over
the whole data from rest, and the simulation errors on the held-out samples, after each segment's first n_start, are summed per block b:

    d_b = (SSE_b(base) − SSE_b(with)) / n_b          [(output unit)²], one pair per block,

and the candidate passes when

    max(d̄ / SE(d̄), d̄_γ / SE(d̄_γ)) > k,     100 (1 − RMSE_with / RMSE_without) ≥ min_drop_percent
    and     100 √(RMSE_without² − RMSE_with²) / ȳ ≥ min_fuel_percent,

k = margin_se, the RMSEs pooled over every held-out sample, ȳ the mean fuel there (the last floor: the RMS of the fuel
the candidate explains beyond the base, as a share of the fuel). d̄ is the mean of the B block gains, SE(d̄) = s_d/√B;
d̄_γ their γ-trimmed mean (γ = trim: the mean of the sorted d_(b) with g = ⌊γ B⌋ left out at each end) and
SE(d̄_γ) = s_w / ((1 − 2g/B) √B) its standard error (Yuen 1974), s_w/√B that of the mean of the winsorised gains w_b
(each d_b clipped to [d_(g+1), d_(B−g)]). The gains are heavy-tailed: a few blocks with a transient (a cold start's
first minutes, a regeneration's start) hold most of the squared error. An effect that acts in a few blocks (a
regeneration) is carried by the mean, and the trimmed mean trims it away; one that acts on most blocks while one or
two transient blocks decide the spread (a cold start) is carried by the trimmed mean, whose spread those blocks do
not inflate. Either says that the candidate's model simulates held-out data better beyond the spread of the fits; the
floors, on the pooled errors, that it does so by enough.

An effect that acts in so few blocks (a warm-up's first minutes, two effects where one masks the other but there)
decides its own spread: with its gain in K blocks, d̄ / SE(d̄) cannot much exceed √K whatever the gain, and the
trimmed mean trims it away. When the floors are met and neither t clears k, the candidate's placebo is built: the
same candidate on its bus signals shifted together circularly by half the data (`placebo`), a column of its own
shape, levels and dynamics, unrelated in time to the fuel, built and refitted as the candidate is. Its block gains
d_p,b are what such a column gains by the fits and the noise alone, and the candidate passes on

    (d̄ − d̄_p) / (√2 SE(d̄_p)) > k

as well (d̄ − d̄_p the difference of two draws of the same mean when the candidate is no better than its placebo).
A candidate on engine speed, torque or the fuel (inertia, the fuel delay, the injection cut) has no placebo. With
no gain, the larger of the first two t clears k = 2 on about 8 % of 40 AR(1) blocks with ρ = 0.4 (the mean's alone
on about 6 %), the placebo's on about 6 %, and the largest of the three on about 12 %
(tests/ident/diagnosis/test_yardstick.py).

s_d/√B and s_w/√B are Newey–West's standard errors (`long_run_se`), since neighbouring blocks are not independent
pairs (the blocks of one held-out chunk share its fold model, and a slow error spans several blocks), with the
Bartlett kernel and the bandwidth L = ⌊4 (B/100)^(2/9)⌋ of Newey & West (1994) (3 for 40 blocks):

    s_d² = γ_0 + 2 Σ_{l=1..L} (1 − l/(L + 1)) γ_l,    γ_l = 1/B Σ_b (d_b − d̄)(d_{b−l} − d̄),

times B/(B − 1) (s_w the same of the w_b). They hold both what the noise moves in a block and what the fits move
(each block is scored by the fold fitted without it).

Yuen, K. K. (1974). The two-sample trimmed t for unequal population variances. Biometrika 61(1), 165–170;
Wilcox, R. R. (2012). Introduction to Robust Estimation and Hypothesis Testing, 3rd ed., Academic Press, sec. 4.4.
Newey, W. K. & West, K. D. (1987). A simple, positive semi-definite, heteroskedasticity and autocorrelation
consistent covariance matrix. Econometrica 55(3), 703–708; (1994) Automatic lag selection in covariance matrix
estimation. Review of Economic Studies 61(4), 631–653.
"""
from __future__ import annotations

import dataclasses
import functools
import warnings
from dataclasses import dataclass

import numpy as np

from fuelid.errors import FuelidError
from fuelid.ident.diagnosis.candidate import HeldOut
from fuelid.ident.diagnosis.settings import Settings
from fuelid.ident.diagnosis.statistics import newey_west, newey_west_lags
from fuelid.ident.identify import MIN_SEGMENT_S, refit_with_effects
from fuelid.ident.fueldelay import shift_signal
from fuelid.ident.modeldata import fuel_shift_s, model_data
from fuelid.ident.polymodel import PolyModel, simulate
from fuelid.ident.validation import cycle_fuel_error, error_table
from fuelid.parallel import side_by_side

BUILD_ERRORS = (FuelidError, ValueError, np.linalg.LinAlgError)  # a refit that fails: the candidate is not built


def trip_masks(ds, break_s: float) -> list[np.ndarray]:
    """A mask of ds's valid samples per trip: the valid samples split where the clock jumps by ≥ break_s [s]."""
    idx = np.flatnonzero(ds.valid)
    cuts = np.flatnonzero(np.diff(ds.t[idx]) >= break_s) + 1
    masks = []
    for part in np.split(idx, cuts):
        m = np.zeros(len(ds.t), bool)
        m[part] = True
        masks.append(m)
    return masks


@dataclass(frozen=True)
class Folds:
    """held: per fold, the mask of the samples it leaves out; block: each sample's scoring block; kind: "trips" or
    "blocks"."""

    held: tuple
    block: np.ndarray
    kind: str


def make_folds(ds, settings: Settings) -> Folds:
    """The folds of ds (module docstring)."""
    block = np.floor((ds.t - ds.t[0]) / settings.block_s).astype(int)
    trips = trip_masks(ds, settings.trip_break_s)
    if len(trips) >= 2:
        return Folds(tuple(trips), block, "trips")
    chunk = np.floor((ds.t - ds.t[0]) / settings.chunk_s).astype(int)
    held = tuple(ds.valid & (chunk % settings.folds == k) for k in range(settings.folds))
    return Folds(held, block, "blocks")


@dataclass(frozen=True)
class Scored:
    """Fold models of one effect set and their held-out simulation: models (one per fold), ysim [output unit] each
    sample's simulation by the fold that left it out (NaN where none did or within a segment's first n_start), as the
    bus reports the fuel (delayed by a fuel delay's τ), y the fuel the bus reported."""

    models: tuple
    ysim: np.ndarray
    y: np.ndarray


def _simulated(model: PolyModel, ds, fitted_on) -> tuple[np.ndarray, np.ndarray]:
    """(the fuel the bus reported [output unit], the model's simulation from rest on each valid segment of ds with
    the first n_start samples NaN). Its inputs are built as on `fitted_on` (ds with the fold's samples invalid): an
    effect whose columns depend on the valid data (a generic state signal's states) then has the columns the fit had.
    A model fitted to the fuel advanced by a fuel delay τ (ident.modeldata.fuel_shift_s) has its simulation delayed
    by τ: every model is scored against the same measured fuel, not against an interpolated (smoother) one."""
    u = model_data(model, fitted_on)[0]
    tau = fuel_shift_s(model)
    ysim = np.full(len(ds.y), np.nan)
    n0 = model.structure.n_start
    for seg in ds.segments():
        sim = simulate(model, u[seg])
        ysim[seg] = shift_signal(sim, -tau / ds.Ts) if tau else sim
        ysim[seg.start:seg.start + n0] = np.nan
    return np.asarray(ds.y, float), ysim


def score(fold_models, ds, folds: Folds) -> Scored:
    """Scored of the fold models (one per fold of `folds`)."""
    ysim, y = np.full(len(ds.t), np.nan), np.full(len(ds.t), np.nan)
    for model, held in zip(fold_models, folds.held):
        yk, sk = _simulated(model, ds, dataclasses.replace(ds, valid=ds.valid & ~held))
        ysim[held], y[held] = sk[held], yk[held]
    return Scored(tuple(fold_models), ysim, y)


def training(ds, held: np.ndarray):
    """ds without the held-out samples; FuelidError when no stretch long enough to fit on is left."""
    fit_on = dataclasses.replace(ds, valid=ds.valid & ~held)
    if not fit_on.segments(MIN_SEGMENT_S):
        raise FuelidError(f"no valid stretch of {MIN_SEGMENT_S:g} s is left to fit on beside a held-out fold")
    return fit_on


def refits(start, ds, folds: Folds, effects, settings: Settings, defined=()) -> Scored:
    """Scored of the models refitted on each fold's training data with `effects` added ("ID" or "ID=VALUE"), each
    warm-started from `start`: a model (the same for every fold) or one model per fold. Raises BUILD_ERRORS."""
    starts = start if isinstance(start, (list, tuple)) else [start] * len(folds.held)
    models = side_by_side([functools.partial(_refit, m, training(ds, held), list(effects), defined,
                                             settings.refit_max_iter) for m, held in zip(starts, folds.held)])
    return score(models, ds, folds)


def _refit(model: PolyModel, ds, effects: list[str], defined, max_iter: int) -> PolyModel:
    """refit_with_effects(model, ds, effects, defined=defined, max_iter=max_iter), its warnings left out (one fold's
    fit: a pure call for fuelid.parallel)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return refit_with_effects(model, ds, effects, defined=defined, max_iter=max_iter)


def compare(without: Scored, with_: Scored, folds: Folds, settings: Settings, null: Scored | None = None) -> HeldOut:
    """The yardstick of `with_` against `without` (module docstring), on the held-out samples both (and the placebo
    `null`, when given: `placebo`) simulate; the blocks holding at least half as many of them as the fullest block
    are the pairs."""
    scored = (without, with_) + ((null,) if null is not None else ())
    ok = np.logical_and.reduce([np.isfinite(s.ysim) & np.isfinite(s.y) for s in scored])
    b = folds.block[ok]
    n = np.bincount(b, minlength=folds.block.max() + 1)
    sse = [np.bincount(b, weights=(s.y[ok] - s.ysim[ok]) ** 2, minlength=n.size) for s in scored]
    keep = (n > 0) & (n >= 0.5 * n.max()) if n.size else n > 0
    B = int(keep.sum())
    if B < 2:
        return HeldOut(float("nan"), float("nan"), 0.0, 0.0, 0.0, float("inf"), B, folds.kind, False)
    d = (sse[0][keep] - sse[1][keep]) / n[keep]
    rmse0, rmse1 = (float(np.sqrt(s[keep].sum() / n[keep].sum())) for s in sse[:2])
    fuel = float(np.bincount(b, weights=without.y[ok], minlength=n.size)[keep].sum() / n[keep].sum())
    mean, se = float(d.mean()), long_run_se(d)
    trimmed, trimmed_se = trimmed_mean(d, settings.trim)
    drop = 100.0 * (1.0 - rmse1 / rmse0)
    explained = 100.0 * np.sqrt(max(rmse0 ** 2 - rmse1 ** 2, 0.0)) / abs(fuel) if fuel else float("inf")
    floors = bool(drop >= settings.min_drop_percent and explained >= settings.min_fuel_percent)
    null_gain = null_se = float("nan")
    if null is not None:
        d_null = (sse[0][keep] - sse[2][keep]) / n[keep]
        null_gain, null_se = float(d_null.mean()), long_run_se(d_null)
    held = HeldOut(rmse0, rmse1, drop, float(explained), mean, se, B, folds.kind, False, trimmed, trimmed_se, floors,
                   null_gain, null_se)
    # the mean carries an effect in a few blocks, the trimmed mean one on most blocks beside a few transients, and the
    # mean beyond a placebo's one in so few blocks that it decides its own spread
    k = settings.margin_se
    passes = floors and (mean > k * se or trimmed > k * trimmed_se or held.beyond_null_in_se > k)  # NaN: no placebo
    return dataclasses.replace(held, passes=bool(passes))


def placebo(ds, signals) -> object | None:
    """ds with the bus signals `signals` shifted together circularly by half its samples: a candidate built on it
    has its own column, of its own shape and levels, unrelated in time to the fuel (module docstring). None when one
    of them is not a bus signal of ds (engine speed, torque and the fuel are the model's own) or none of them varies."""
    if not signals or any(s not in ds.extra for s in signals):
        return None
    x = {s: np.asarray(ds.extra[s], float) for s in signals}
    if not any(np.nanmax(v) > np.nanmin(v) for v in x.values() if np.isfinite(v).any()):
        return None
    half = len(ds.t) // 2
    return dataclasses.replace(ds, extra={**ds.extra, **{s: np.roll(v, half) for s, v in x.items()}})


def trimmed_mean(d: np.ndarray, trim: float) -> tuple[float, float]:
    """(d̄_γ, its standard error) of the series d, γ = trim (module docstring: Yuen's trimmed mean, the winsorised
    series' Newey–West standard error over 1 − 2g/B). Written here: scipy.stats has the trimmed mean (trim_mean) and
    Yuen's two-sample test on independent samples (ttest_ind(trim=)), not this one-sample test on correlated blocks."""
    B = len(d)
    g = int(np.floor(trim * B))
    s = np.sort(d)
    w = np.clip(d, s[g], s[B - g - 1])
    return float(s[g:B - g].mean()), long_run_se(w) / (1.0 - 2.0 * g / B)


def long_run_se(d: np.ndarray) -> float:
    """Newey–West standard error of the mean of the series d (module docstring): the spread of d̄ when neighbouring
    d_b are correlated (ident.diagnosis.statistics' long-run covariance, the screening's)."""
    B = len(d)
    x = (d - d.mean())[:, None]
    omega = float(newey_west(x, min(newey_west_lags(B), B - 1))[0, 0])  # B s_d²
    return float(np.sqrt(max(omega, 0.0) / (B * (B - 1))))


def held_out_summary(s: Scored, ds) -> dict:
    """RMS held-out simulation error [output unit] and cycle fuel errors [%] (eq. 20: mean and RMS over the cycles) of
    the fold models, as `fuelid diagnose --json` reports the base model's."""
    ok = np.isfinite(s.ysim) & np.isfinite(s.y)
    return {"rmse": float(np.sqrt(np.mean((s.ysim[ok] - s.y[ok]) ** 2))),
            "cycle_fuel_error_percent": error_table(cycle_fuel_error(np.where(ok, s.y, np.nan), s.ysim, ds.cycle,
                                                                     ds.Ts))}
