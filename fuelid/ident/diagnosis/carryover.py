"""Whether a bus signal fuelid knows no physics for carries over to another trip once it is added with its own
dynamics, as `fuelid identify --effects-from` would add it: leave-one-trip-out by PEM, two ways.

The linearised refit's leave-one-trip-out (verification, 4) fits the candidate's test columns (an FIR basis, or
x and x·ŷ) with one Gauss–Newton step of the model's parameters on the other trips. Added to the model, a generic
bus-signal candidate (level, rate, scales, torque, state of a signal with no known physics) gets its own
dynamics instead, B_x/F_x per input column x_j, and the model's own parameters move with it; on a real engine
map such a column can stand in for the engine's transient fuelling on the trips it was fitted on and not on
another day's. So forward selection checks an accepted generic candidate both ways it will act, for each trip k
fitted on the other trips and scored on k:

    own dynamics     Σ_j B_j/F_j x_j fitted by PEM (output error) to the simulation errors r = y − ŷ of the model
                     (fitted on all the data and held fixed, so that only the candidate differs); scored: r
                     against r − Σ_j B_j/F_j x_j
    re-identified    the model re-identified by PEM on the other trips from itself, without the candidate and
                     then with it added (ident.identify.refit_with_effects, coefficients starting at 0, the same
                     iteration limit); scored: the two models' simulation errors

and it carries over when, both ways, the RMS error pooled over the held-out trips, √(Σ_k Σ_{t∈k} e_k²/N), is
lower with it than without by at least the diagnosis's relevance bar, min_drop_percent (`left_out_trips`): a signal
with no physics earns its place on the trips it was not fitted on, as any candidate does on held-out blocks (a
demand-torque level that barely lowered them raised another day's error once added: README). Each way
alone has let through a signal the other stopped and that raised another day's error once added (README). The
own-dynamics way does not need the model's own parameters to be determined by the other trips alone — on two trips
in different weather they are not (an ambient effect) — and the re-identified way feels that alike without and
with the candidate.
"""
from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable

import numpy as np

from fuelid.errors import FuelidError, InputError
from fuelid.ident.diagnosis.run import Run
from fuelid.ident.diagnosis.verification import trips
from fuelid.ident.effectfile import effects_of_model
from fuelid.ident.identify import MIN_SEGMENT_S, FitMemo, refit_with_effects, training_segments
from fuelid.ident.modeldata import apply_effects, at_operating_point
from fuelid.ident.modelrun import run_model
from fuelid.ident.pem import pem
from fuelid.ident.polymodel import PolyModel, Structure, simulate


def _held_out_masks(ds, run: Run) -> list[np.ndarray]:
    """A mask of ds's samples per trip (verification.trips: the run's segments grouped at breaks of the log)."""
    masks = []
    for trip in trips(ds, run):
        held = np.zeros(len(ds.t), bool)
        for k in trip:
            held[run.segs[k]] = True
        masks.append(held)
    return masks


def _other_trips(ds, held: np.ndarray):
    """ds with the held-out samples no longer valid; InputError when no stretch of MIN_SEGMENT_S is left to fit on."""
    fit_on = dataclasses.replace(ds, valid=ds.valid & ~held)
    if not fit_on.segments(MIN_SEGMENT_S):
        raise InputError(f"the other trips hold no valid stretch of {MIN_SEGMENT_S:g} s to fit on")
    return fit_on


def _own_dynamics_errors(effect: str, model: PolyModel, ds, run: Run, held: np.ndarray, defined, max_iter: int,
                         memo: FitMemo | None):
    """(r, r − Σ_j B_j/F_j x_j) on the held-out samples, the candidate's dynamics fitted to the model's simulation
    errors r on the others (module docstring)."""
    fx = apply_effects(at_operating_point(ds, model), [effect], model.info.get("effect_parameters"), defined=defined)
    r = run.y - run.ysim  # NaN off the tested segments
    segs = training_segments(_other_trips(ds, held), fx.u, r, MIN_SEGMENT_S)
    if not segs:
        raise InputError(f"the other trips hold no stretch of {MIN_SEGMENT_S:g} s where the candidate's signals "
                         "and the model's errors are all known")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        g = (memo.pem if memo is not None else pem)(fx.u, r, fx.extend(Structure(nb=(), nf=(), nk=())), ds.Ts,
                                                    segments=segs, u0=np.zeros(fx.u.shape[1]), y0=0.0,
                                                    max_iter=max_iter)
    fitted = np.full(len(r), np.nan)
    for seg in run.segs:
        if held[seg.start]:
            fitted[seg] = simulate(g, fx.u[seg])
    ok = held & np.isfinite(fitted) & np.isfinite(r)
    return r[ok], (r - fitted)[ok]


def _reidentified_errors(effect: str, model: PolyModel, ds, run: Run, held: np.ndarray, defined, max_iter: int,
                         memo: FitMemo | None):
    """The simulation errors on the held-out samples of the model re-identified on the others without and with the
    candidate (module docstring); the one without is every candidate's on this model and trip (memo)."""
    fit_on = _other_trips(ds, held)
    without = refit_with_effects(model, fit_on, [], defined=defined, max_iter=max_iter, memo=memo)
    with_ = refit_with_effects(without, fit_on, [effect], defined=defined, max_iter=max_iter, memo=memo)
    scored = dataclasses.replace(ds, valid=ds.valid & held)
    errors = []
    for m in (without, with_):
        mrun = run_model(m, scored)
        errors.append(mrun.settled(mrun.y - mrun.ysim))
    ok = np.isfinite(errors[0]) & np.isfinite(errors[1])
    return errors[0][ok], errors[1][ok]


@dataclasses.dataclass(frozen=True)
class Way:
    """One way to leave a trip out: the held-out errors (without, with) it returns, and how an explanation says it."""
    errors: Callable[..., tuple[np.ndarray, np.ndarray]]
    words: str


WAYS = {"own_dynamics": Way(_own_dynamics_errors, "its own dynamics fitted to the model's errors"),
        "re_identified": Way(_reidentified_errors, "the model re-identified with it")}


def left_out_trips(effect: str, model: PolyModel, ds, run: Run, *, defined=(), max_iter: int,
                   min_drop_percent: float, memo: FitMemo | None = None) -> dict | None:
    """Leave-one-trip-out of `effect` both ways (module docstring) around `model` (run: its Run on ds, whose
    segments are grouped into trips); defined: engineer-defined effects `effect` may name; max_iter: the PEM fits'
    iteration limit; memo: PEM fits on these data kept across calls (ident.identify.FitMemo: the model without the
    candidate is every candidate's). None with fewer than two trips. Returns, per way, {rmse_without, rmse_with}
    [output unit] pooled over the held-out trips, per_trip [[without, with] …] and lowered: with ≤
    (1 − min_drop_percent / 100) without; min_drop_percent; carries_over: lowered both ways. The ways are taken in
    WAYS's order, the cheap one first, and stop at the first not lowered: the other cannot make it carry over (its
    PEM refits per trip are most of this check's time), and is not in the record."""
    masks = _held_out_masks(ds, run)
    if len(masks) < 2:
        return None
    defined = tuple(effects_of_model(model)) + tuple(defined)
    out = {"min_drop_percent": min_drop_percent, "carries_over": True}
    for name, way in WAYS.items():
        pooled, per_trip = ([], []), []
        for held in masks:
            try:
                e = way.errors(effect, model, ds, run, held, defined, max_iter, memo)
            except (FuelidError, np.linalg.LinAlgError) as exc:
                return {"error": f"{name.replace('_', ' ')}: {exc}", "carries_over": False}
            for acc, x in zip(pooled, e):
                acc.append(x ** 2)
            per_trip.append([float(np.sqrt(np.mean(x ** 2))) for x in e])
        without, with_ = (float(np.sqrt(np.mean(np.concatenate(acc)))) for acc in pooled)
        out[name] = {"rmse_without": without, "rmse_with": with_, "per_trip": per_trip,
                     "lowered": with_ <= (1.0 - min_drop_percent / 100.0) * without}
        if not out[name]["lowered"]:
            out["carries_over"] = False
            break
    return out
