"""Ranking the candidates and naming the missing effect: the engine's own map first, the tests of every other
candidate, Holm, verification of the likeliest, and forward selection of every effect missing.

0. The engine map. A real engine's fuel map is curved (efficiency varies over speed × torque) and a linear model is
   a plane through it, and the engine burns more while the torque builds up than its map says (transient fuelling);
   that is a property of the engine, not a hidden effect, and on a real engine it outweighs any hidden one. The map
   term `engine_map` (ident.effects: ñ·T̃, ñ², T̃², the torque's rise) is tested first, as one group (one test over
   all its columns, at α: the first test of a fixed sequence, so the hidden-effect family after it keeps its own α),
   must explain min_effect_percent and is verified like any candidate (held-out drop ≥ min_drop_percent). When it is
   confirmed and no other candidate, verified on the model as it is, lowers the held-out error more (a generic bus
   signal's drop discounted by GENERIC_WEIGHT, as in 5; the map's columns would absorb part of such an effect that
   varies with the operating point: on a linear engine hiding an inertia, they do), it is named as the engine map
   term (role ENGINE_MAP) — as `power_nonlinearity` when the speed × torque product alone does as well (the other
   terms add less than min_drop_percent held out) and the model identify builds with the full map simulates the data
   no better by min_drop_percent than the one built with the product (`_map_beats_product`: the linearised refit
   steps once from the model as it is, while PEM reaches what the map's FIR taps hold, e.g. a fuel delay) — and the
   hidden-effect search (5) starts from the model with it: the one identify builds with it (`BuiltCheck`), unless
   forward selection's warm-started refit simulates the data better (`_searched_on`). Started from the linear model
   and capped at REFIT_MAX_ITER iterations, that refit can stop far short of it (README), and the hidden effects,
   tested on what it leaves, would be tested against the map's curvature too. The full map is never a hidden effect;
   the product term is one only when no map term is named.

5. Forward selection. Bus signals are dependent (a cab temperature follows the level shift a real effect leaves
   in the error), and two effects can hide at once (the weaker one's held-out drop on the model as it is falls
   short, the stronger one's error covering it, and the model's own parameters, fitted without the stronger one,
   are biased by it). The confirmed candidate with the largest held-out drop (`_priority`; a generic bus signal's
   discounted by GENERIC_WEIGHT) is accepted first and the model re-identified with it by PEM, warm-started from
   the model itself with the effect's coefficients at zero (ident.identify.refit_with_effects: the point the
   linearised refit of 4 starts from, so a few iterations suffice and V never rises); then, as long as one is
   found, every remaining candidate is tested again on that re-identified model (1–3, Holm-corrected over the
   candidates re-tested), must explain min_effect_percent and is verified on it (4: held-out drop ≥
   min_drop_percent, its physics' direction, identifiable, never worse on a held-out trip); the one with the
   largest drop is accepted next and the model re-identified with it too (`select_forward`). Those confirmed on
   the model as it is but never accepted are "explained by" the accepted ones. Explaining away can go both ways:
   two signals that move together on these data (in the simulator, an oil temperature that follows the same
   smoothed load as the intake air) each leave the other insignificant. So each rival confirmed in the same round
   as the accepted candidate, with a held-out drop at least RIVAL_SHARE of its, is re-tested alone (1–3, at α) on
   the model re-identified with the accepted one and, when it is not significant and relevant there, the other
   way round: the accepted one on the model re-identified with the rival instead. When neither is, the data cannot
   tell the two apart: the rival is listed in the accepted one's `alternatives` and its explanation says so (data
   where they differ, another day, can).
   An accepted candidate whose re-identified model simulates the data worse than the model without it (RMS simulation
   error over the tested samples: the refit cannot be verified) is not built on: the search goes on from the model
   without it, with the next candidate found; it is named, and recommended only when it brings its physics
   (catalogued or engineer-defined) and the model identify builds (below) simulates the data better with it by at
   least min_drop_percent (`_only_the_warm_refit_worse`): the relevance its refit could not show. Less is a tie
   within the fits' reproducibility, not evidence (on the map engine one such tie added an effect that raised another
   day's error: README). The warm-started refits are the search, not the model `fuelid identify --effects-from`
   builds: that one is identified by PEM from its own initialisation and from the effects added in turn
   (ident.identify.identify_model), and the two can end in minima far apart (a warm start keeps the dynamics of the
   model without the effects). So what is to be recommended is checked once more, in the order found, on the model
   identify builds (`BuiltCheck`, `refit.built`): built from the effects recommended before it plus the candidate, it
   must simulate the data no worse than built without it; otherwise the candidate is named, not recommended, and
   those found given it are not recommended either (`_given_not_added`). The fuel delay, verified on its reference
   model and on the model as it is (delay.py), is checked so too when the engine's term is added
   (`verification.built`): the model identify builds then has the term's taps, which absorb a delay, and with a delay
   estimated 0.05 s off it can simulate worse than without it (README).

A candidate is `significant` — a missing effect the diagnosis names — when the Holm-corrected test rejects
AND it explains at least min_effect_percent (default 1 %) of the simulation error AND, when verified, the
linearised refit lowers the held-out RMS error by at least min_drop_percent (default 2 %) the way its physics
says, identifiably and never worse on a held-out trip, AND (after the first) forward selection accepts it given
those before it. The conjunction can only remove rejections, so the family-wise false-alarm rate of the first
stays ≤ α. Significant candidates are listed first, in the order accepted;
then the rest by p-value. README gives the measured false alarms and the table per hidden effect.

A significant candidate is `recommended` (what `fuelid identify --effects-from` adds) when it was verified, the
model re-identified with it simulates the data no worse than the model without it (or, for an effect with its
physics, forward selection's warm-started refit alone did not: 5), and so does the model `fuelid identify` builds
with it and the effects recommended before it (5; better by min_drop_percent where the warm refit was worse) — and,
for a decoded bus signal in a generic form (level, rate, scales, torque, state of a signal fuelid has no physics
for), only when the data held several trips and it held up left out of each (leave-one-trip-out): in the linearised
refit (4; NOT_DETERMINED_BY_OTHER_TRIPS when no trip's fold determined it) and, once accepted, with its own dynamics
and the model re-identified by PEM on the other trips (diagnosis.carryover: its refit counts as not verified unless
the pooled error on the trips left out falls by min_drop_percent both ways). A signal engine speed and torque
determine (a static map of them leaves less than MIN_IDENTIFIABILITY² of its variance, `_why_inputs_determine`:
EEC3's desired speed is the engine speed but in neutral) is never added: whatever it explains is a function of speed
and torque, the engine's own fuelling, and other days cannot make it a hidden effect. On one trip any other such
signal can stand in for whatever else moves with the operating point that day (on a real engine its transient
fuelling): named, with ONE_TRIP_ONLY, but not added. A catalogued or engineer-defined effect brings its physics
(sign, form) and is recommended from one trip. Forward selection still re-identifies the model with such a signal
when it accepts one (so that it explains away its twins and what it stands in for), but what is recommended must
have been verified on the model `fuelid identify --effects-from` builds: an effect found given a signal that is not
added is named, not recommended (`_given_not_added`; one accepted that way and added without it can make the model
worse on another day: README) — unless an earlier round of forward selection found and verified it given exactly the
effects recommended before it (`_found_given_added`: it was then confirmed on the model identify builds with them,
only not accepted first, a one-trip signal's drop being larger; on the map engine a hidden inertia is so). A round
given only some of them does not count: the others, absent there, may explain it away. So once the search is built
on a signal that is never added (`_why_never_added`), every later round is given it and only a candidate that may
be added and was found in an earlier round given no such signal could still be recommended; with none left,
forward selection stops (`_nothing_left_to_recommend`). What is recommended is the same as with the search run to
its end; what would have been named after it, found given it, is not (on the map engine's DPF trip the overrun
cut-off and EEC1's demand torque after EEC3's desired speed).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fuelid.blas import in_one_blas_thread
from fuelid.errors import FuelidError, InputError
from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.builds import BuiltCheck, built_record
from fuelid.ident.diagnosis.candidate import ENGINE_MAP, MISSING_EFFECT, Candidate
from fuelid.ident.diagnosis.carryover import WAYS, left_out_trips
from fuelid.ident.diagnosis.entries import ENTRIES
from fuelid.ident.diagnosis.explanation import as_evidence, contribution_on_grid, explain
from fuelid.ident.diagnosis.failures import where_it_fails
from fuelid.ident.diagnosis.run import Run, run_gradients
from fuelid.ident.diagnosis.statistics import holm
from fuelid.ident.diagnosis.verification import MIN_IDENTIFIABILITY, Baseline, baseline, trips
from fuelid.ident.filters import lfilter
from fuelid.ident.identify import FitMemo, refit_with_effects
from fuelid.ident.modeldata import at_operating_point
from fuelid.ident.modelrun import ModelRun, run_model
from fuelid.ident.polymodel import PolyModel
from fuelid.ident.validation import metrics

GENERIC_WEIGHT = 0.8  # a generic bus signal must explain 25 % more than a named effect to be accepted first
RIVAL_SHARE = 0.5  # a rival explaining less than half of what the accepted one does cannot explain it away (5)
MAP_TERM, PRODUCT_TERM = "engine_map", "power_nonlinearity"  # the engine's curvature: its map, its product term (0)


@dataclass
class Diagnosis:
    """The whole diagnosis (`diagnose`), serialised by `to_json` as `fuelid diagnose --json` prints it; run the
    model run it read (ident.modelrun.ModelRun), for the report, never serialised."""

    model: dict
    data: dict
    compare: dict
    held_out: dict | None
    where_it_fails: dict
    test: dict
    candidates: list[Candidate]
    verdict: str
    run: ModelRun = field(repr=False)
    engine_map: Candidate | None = None  # the engine map term (0) when named, also listed first in candidates

    @property
    def missing_effects(self) -> list[Candidate]:
        """The hidden effects named (role MISSING_EFFECT), in the order accepted."""
        return [c for c in self.candidates if c.role == MISSING_EFFECT]

    def to_json(self) -> dict:
        """The diagnosis as `fuelid diagnose --json` prints it: engine_map the effect id of the engine map term
        (None when the engine's map is not measurably curved), missing_effects those of the hidden effects."""
        return {"model": self.model, "data": self.data, "compare": self.compare, "held_out": self.held_out,
                "where_it_fails": self.where_it_fails, "test": self.test,
                "engine_map": None if self.engine_map is None else self.engine_map.effect,
                "missing_effects": [c.effect for c in self.missing_effects],
                "candidates": [c.to_json() for c in self.candidates], "verdict": self.verdict}


def rank_candidates(model: PolyModel, ds, run: Run, candidates=None, alpha: float = 0.05,
                    effects=()) -> list[Candidate]:
    """Both tests of every candidate effect not already in the model (ident.diagnosis.statistics, 1–3), each as its
    entry kind tests it (ident.diagnosis.entries); Holm-corrected; sorted by p-value (log p), the untested last.
    candidates: default the built-in effects, installed plug-ins', `effects` (the engineer's, ident.effectfile)
    and every other bus signal's."""
    if candidates is None:
        candidates = list(fx.EFFECTS.values()) + list(fx.plugin_effects()) + list(effects) + fx.generic_effects(ds)
    included = {fx.parse_effect(e)[0] for e in model.effects}
    dsm = at_operating_point(ds, model)
    rows, untested = [], []
    for effect in candidates:
        if effect.id in included:
            continue
        entry = ENTRIES[effect.enters]
        found = entry.test(model, dsm, run, effect)
        if found is None:
            untested.append(Candidate(effect.id, effect.name, effect.form, list(effect.signals), list(effect.spns),
                                      effect.physics, "not testable: its bus signals are not in the data"))
            continue
        tests = found.tests
        log_p = min(0.0, math.log(len(tests)) + min(t.log_p for t in tests.values()))  # Bonferroni over its tests
        df = max(t.df for t in tests.values())
        gains = found.coef.reshape(len(effect.lags), -1).sum(axis=0)
        text, size = explain(entry, effect, found.reg, contribution_on_grid(effect.form, found.x, found.coef, run),
                             gains, [model], dsm, run)
        rows.append(Candidate(
            effect.id, effect.name, effect.form, list(effect.signals), list(effect.spns), effect.physics, text,
            spec=effect.id, statistic=max(t.statistic for t in tests.values()), df=df, p_value=math.exp(log_p),
            log10_p=log_p / math.log(10), testable=df > 0,
            tests={name: {"statistic": t.statistic, "df": t.df, "p_value": t.p_value} for name, t in tests.items()},
            estimated_drop_percent=100.0 * (1.0 - found.left), size=size, definition=effect, entry=entry,
            reg=found.reg, x=found.x, w=lfilter(model.A, [1.0], found.x, axis=0), ref=found.ref))
    family = [c for c in rows if c.effect != MAP_TERM]  # the map term is tested first, alone, at alpha (0)
    adj, sig = holm([c.p_value for c in family], alpha) if family else (np.zeros(0), np.zeros(0, bool))
    for c, a, s in zip(family, adj, sig):
        c.p_holm = float(a)
        # p-values below ~1e-300 underflow; compare log p with Holm's log(alpha/m) bound in that case
        c.test_significant = bool(c.testable and (s or c.log10_p < math.log10(alpha / len(family))))
    for c in rows:
        if c.effect == MAP_TERM:
            c.p_holm = c.p_value
            c.test_significant = bool(c.testable and c.log10_p < math.log10(alpha))
    rows.sort(key=lambda c: (c.log10_p, -c.statistic))
    return rows + untested


def _confirmed(c: Candidate, v: dict | None, min_drop_percent: float) -> bool:
    """Whether a verification v of c confirms it: the held-out RMS error falls by at least min_drop_percent (its
    entry kind's relevance), and the fuel moves the way the effect's physics says (Effect.sign: fuel cut on
    overrun falls, a regeneration adds fuel, the fuel signal lags), and its entry kind admits it (a fuel delay:
    entries.Shift.why_not_admitted). A candidate the refit did not or could not score stays as the tests found it."""
    if v is None or "error" in v:
        return True
    return c.entry.relevance(v) >= min_drop_percent and c.definition.sign * v["direction"] >= 0 \
        and v.get("identifiable", True) and not _worse_on_held_out_trips(v) \
        and c.entry.why_not_admitted(v, min_drop_percent) is None


def _worse_on_held_out_trips(v: dict) -> bool:
    """Whether adding the effect raises the RMS error over the trips, each left out of its refit (verification, 4;
    pooled over the trips: one trip's error can rise by a fraction of a % with noise while the others' fall)."""
    return "trips" in v and v["trips"]["pooled_rmse_drop_percent"] < 0


def _refit_verified(c: Candidate) -> bool:
    """Whether the model re-identified with c simulates the data no worse than the model without it (forward
    selection's refit, 5; True for one not refitted: the fuel delay, verified on its reference model)."""
    return c.refit is None or c.refit["verified"]


def _only_the_warm_refit_worse(c: Candidate) -> bool:
    """Whether a catalogued or engineer-defined c, verified on held-out data, was held back only because forward
    selection's warm-started refit simulated the data worse (module docstring, 5): that refit keeps the dynamics
    of the model without c and can end far from the minimum `fuelid identify` reaches from its own
    initialisation, so the model identify builds with c decides instead (`BuiltCheck`). A generic bus signal keeps
    its trip checks, which only a verified refit runs."""
    r = c.refit
    return r is not None and not r["verified"] and "error" not in r and not _generic(c) \
        and c.verification is not None and "error" not in c.verification


def _why_built_worse(b: dict) -> str:
    """What the explanation of a candidate the model identify builds does not take adds (b: its `BuiltCheck` record)."""
    after = f", after {', '.join(b['effects'])}" if b["effects"] else ""
    if "error" in b:
        return f" — but `fuelid identify` cannot build the model with it{after} ({b['error']}): not recommended"
    if b["min_gain_percent"] and b["rmse_with"] <= b["rmse_without"]:
        return f" — but forward selection's warm-started refit with it simulated these data worse, and the model " \
               f"`fuelid identify --effects-from` builds with it{after} (PEM from its own initialisation) lowers " \
               f"their RMS error by less than {b['min_gain_percent']:g} % ({b['rmse_without']:.3f} → " \
               f"{b['rmse_with']:.3f}): not recommended"
    return f" — but the model `fuelid identify --effects-from` builds with it{after} (PEM from its own " \
           f"initialisation) simulates these data worse (RMS error {b['rmse_without']:.3f} → " \
           f"{b['rmse_with']:.3f}): not recommended"


def _why_refit_not_verified(c: Candidate) -> str:
    """What the explanation of a named candidate whose refit was not verified adds."""
    if "built" in c.refit:
        return _why_built_worse(c.refit["built"])
    if "error" in c.refit:
        return f" — but the model cannot be re-identified with it ({c.refit['error']}): not recommended"
    if "trips" in c.refit:
        t = c.refit["trips"]
        if "error" in t:
            return f" — but the model cannot be re-identified with it leaving a trip out ({t['error']}): " \
                   "not recommended"
        short = [f"{way.words}, RMS error {t[name]['rmse_without']:.3f} → {t[name]['rmse_with']:.3f}"
                 for name, way in WAYS.items() if name in t and not t[name]["lowered"]]
        return f" — but fitted on the other trips it does not lower the error on the trips left out by " \
               f"{t['min_drop_percent']:g} % ({'; '.join(short)}, pooled, leave-one-trip-out by PEM): not recommended"
    return f" — but the model re-identified with it (PEM, from the model without it) simulates these data worse " \
           f"(RMS error {c.refit['rmse_without']:.3f} → {c.refit['rmse_with']:.3f}): not recommended"


def _why_not_confirmed(c: Candidate, min_drop_percent: float) -> str:
    """What the explanation of a verified but unconfirmed candidate adds."""
    v, drop = c.verification, c.entry.relevance(c.verification)
    if drop < min_drop_percent:
        return f" — but adding it changes the held-out RMS error by {-drop:+.1f} % (a fall of " \
               f"{min_drop_percent:g} % is needed): not confirmed"
    if c.definition.sign * v["direction"] < 0:
        return " — but the refit moves the fuel the other way than this effect would: not confirmed"
    if (why := c.entry.why_not_admitted(v, min_drop_percent)) is not None:
        return why
    if not v.get("identifiable", True):
        return f" — but it is not identifiable from these data: its signal's variation makes only " \
               f"{100 * v['identifiability']:.0f} % of its column beyond an offset and the initial states " \
               "(the signal hardly varies, or only with the trip's start or, a bus signal whose physics is not known, " \
               "as a slow drift over the trip); data that differ in it (other days, places) are " \
               "needed: not recommended"
    return f" — but fitted on the other trips it makes the held-out trips worse (RMS error " \
           f"{-v['trips']['pooled_rmse_drop_percent']:+.1f} %, leave-one-trip-out): not recommended"


NOT_RECOMMENDED = "; not recommended: "  # how the clauses below begin: the verdict says the drop before them
ONE_TRIP_ONLY = (NOT_RECOMMENDED + "a bus signal fuelid knows no physics for, found on one trip (diagnose it "
                 "with other days' files to see whether it carries over)")
"""Why a generic bus-signal candidate found on one trip is named but not recommended (module docstring)."""
NOT_DETERMINED_BY_OTHER_TRIPS = (NOT_RECOMMENDED + "a bus signal fuelid knows no physics for, whose effect no "
                                 "trip left out had determined by the others (its carry-over is untested: diagnose "
                                 "it with more days' files)")
"""Why a generic bus-signal candidate is named but not recommended when no leave-one-trip-out fit determined it."""


def _why_inputs_determine(c: Candidate, ds) -> str | None:
    """Why generic bus-signal candidate c is named but not recommended when the model's inputs determine its signal
    (less than MIN_IDENTIFIABILITY² of its variance beyond the static map of speed and torque, a variance inflation
    factor of 10, as for identifiability: `fx.share_beyond_inputs`); None when they do not."""
    signal = c.definition.signals[0]
    share = fx.share_beyond_inputs(ds, signal)
    if share >= MIN_IDENTIFIABILITY ** 2:
        return None
    return NOT_RECOMMENDED + f"engine speed and torque determine {signal} (a static map of them leaves " \
           f"{100 * share:.1f} % of its variance), so what it explains is the engine's own fuelling at its " \
           "operating point — the engine's term and the model's gains hold that — not a hidden effect"


def _why_never_added(c: Candidate, ds, v: dict | None = None) -> str | None:
    """Why c, a generic bus-signal candidate, is never recommended whatever else is (module docstring): speed and
    torque determine its signal (`_why_inputs_determine`), it was verified on one trip (ONE_TRIP_ONLY), or no trip
    left out determined it (NOT_DETERMINED_BY_OTHER_TRIPS); None when none holds, when c has known physics, or when
    its verification v (default c's own) is missing (which then decides: not verified)."""
    if not _generic(c):
        return None
    if (why := _why_inputs_determine(c, ds)) is not None:
        return why
    v = c.verification if v is None else v
    if v is None or "error" in v:
        return None
    if "trips" not in v:
        return ONE_TRIP_ONLY
    return None if any(v["trips"]["determined"]) else NOT_DETERMINED_BY_OTHER_TRIPS


def _said_with_drop(c: Candidate) -> str:
    """c's explanation as the verdict says it: with the held-out RMS error drop adding it makes (`_added_drop`,
    where its entry kind says it), before the clause saying why it is not recommended, if one begins
    NOT_RECOMMENDED."""
    drop = _added_drop(c)
    if drop is None or not c.entry.drop_in_verdict:
        return c.explanation
    said, clause, why = c.explanation.partition(NOT_RECOMMENDED)
    return f"{said} (held-out RMS error {-drop:+.0f} % when added){clause}{why}"


def _generic(c: Candidate) -> bool:
    """Whether c is a decoded bus signal in one of the generic forms (ids FORM:SIGNAL), not a catalogued or an
    engineer-defined effect with known physics."""
    return ":" in c.effect


def _priority(c: Candidate, v: dict | None = None, estimated: float | None = None) -> float:
    """Order of acceptance: the held-out RMS error drop of its verification v (default c's own) when verified,
    else the estimated drop (default c's own); a generic bus signal's discounted by GENERIC_WEIGHT (a named
    physical effect is preferred to a bus signal that explains no more than it)."""
    v = c.verification if v is None else v
    drop = (c.estimated_drop_percent if estimated is None else estimated) if v is None or "error" in v \
        else c.entry.relevance(v)
    return drop * (GENERIC_WEIGHT if _generic(c) else 1.0)


def _added_drop(c: Candidate) -> float | None:
    """The held-out RMS error drop [%] adding c makes: on top of the effects accepted before it when it was
    selected given them, else on the model as it is."""
    cond = c.conditional or {}
    return cond["rmse_drop_percent"] if cond.get("rmse_drop_percent") is not None else c.rmse_drop_percent


REFIT_MAX_ITER = 30  # Levenberg–Marquardt iterations of forward selection's warm-started PEM refit (5)


def _simulation_rmse(run: Run | ModelRun, index: np.ndarray) -> float:
    """RMS simulation error [output unit] of a run on the dataset samples `index` (tested ones)."""
    return float(np.sqrt(np.mean((run.y[index] - run.ysim[index]) ** 2)))


def _refit(c: Candidate, model: PolyModel, run: Run, ds, effects, min_drop_percent: float,
           built: BuiltCheck | None = None, memo: FitMemo | None = None) -> tuple[PolyModel, Run] | None:
    """The model re-identified with c added (module docstring, 5) and its run, with c.refit its record (RMS
    simulation error and loss V without and with, over the samples both runs test; verified: not worse, and for a
    generic bus signal on several trips, carried over: the trips left out min_drop_percent better both ways,
    diagnosis.carryover); None when the refit fails or is not verified. built (given for the engine's term): the
    model it builds with c replaces the warm-started refit when it simulates the data better (`_searched_on`).
    The gradients (run_gradients) are taken of the model kept only: the others are judged by their simulation.
    memo: the fits `BuiltCheck` makes (its FitMemo), where this refit is the start of the one it makes from the same
    model with c added in turn, and where the leave-one-trip-out refits without c are every candidate's."""
    try:
        refit = refit_with_effects(model, ds, [c.effect], defined=effects, max_iter=REFIT_MAX_ITER, memo=memo)
        refit_run = run_model(refit, ds)
        refit_run.require_tested()
    except (FuelidError, np.linalg.LinAlgError) as exc:
        c.refit = {"error": str(exc), "verified": False}
        return None
    index = np.intersect1d(run.index, refit_run.tested_index)
    without, with_ = _simulation_rmse(run, index), _simulation_rmse(refit_run, index)
    c.refit = {"rmse_without": without, "rmse_with": with_, "loss_V_without": model.info.get("loss_V"),
               "loss_V_with": refit.info["loss_V"], "iterations": refit.info["iterations"],
               "verified": bool(with_ <= without)}
    if c.refit["verified"] and _generic(c):
        carry = left_out_trips(c.effect, model, ds, run, defined=effects, max_iter=REFIT_MAX_ITER,
                               min_drop_percent=min_drop_percent, memo=memo)
        if carry is not None:
            c.refit["trips"] = carry
            c.refit["verified"] = carry["carries_over"]
    if not c.refit["verified"]:
        return None
    if built is not None:
        refit, refit_run = _searched_on(c, built, ds, (refit, refit_run))
    try:
        return refit, run_gradients(refit_run)
    except (FuelidError, np.linalg.LinAlgError) as exc:
        c.refit.update(error=str(exc), verified=False)
        return None


def _searched_on(c: Candidate, built: BuiltCheck, ds,
                 refitted: tuple[PolyModel, ModelRun]) -> tuple[PolyModel, ModelRun]:
    """The model (and its run) forward selection searches on after accepting c: the one `fuelid identify` builds
    with c (`BuiltCheck`) when it simulates the data better than the warm-started refit `refitted`, else that refit;
    recorded in c.refit["searched_on"]. The refit's iterations are capped (REFIT_MAX_ITER), and from the model
    without the engine's term they can stop far from the model the engineer gets with it (README)."""
    try:
        model = built.model_with(c)
        run = run_model(model, ds)
        run.require_tested()
    except (FuelidError, np.linalg.LinAlgError) as exc:
        c.refit["searched_on"] = {"model": "warm-started refit", "built_error": str(exc)}
        return refitted
    index = np.intersect1d(run.tested_index, refitted[1].tested_index)
    rmse_built, rmse_warm = _simulation_rmse(run, index), _simulation_rmse(refitted[1], index)
    better = rmse_built < rmse_warm
    c.refit["searched_on"] = {"model": "built" if better else "warm-started refit", "rmse_built": rmse_built,
                              "rmse_warm": rmse_warm}
    return (model, run) if better else refitted


def _retest(pool: list[Candidate], model: PolyModel, run: Run, ds, given: list[str], alpha: float,
            min_effect_percent: float, min_drop_percent: float, n_verify: int) -> list[Candidate]:
    """Those of `pool` significant, relevant and (n_verify > 0) confirmed on `model` (re-identified with the
    effects `given`), tested and verified on it afresh (module docstring, 5), best first; each one's
    `conditional` record is this test's, with the explanation its verification makes."""
    rows = {r.effect: r for r in rank_candidates(model, ds, run, [c.definition for c in pool], alpha)}
    eligible = sorted((r for r in rows.values() if r.test_significant and r.estimated_drop_percent >= min_effect_percent),
                      key=lambda r: -_priority(r))
    if n_verify and eligible:
        base = baseline(model, run, ds)
        for r in eligible[:n_verify]:
            _verify(r, model, ds, run, base)
    found = []
    for c in pool:
        r = rows[c.effect]
        rounds = _rounds_found(c)
        c.conditional = {"given": given, "p_value": r.p_value, "p_holm": r.p_holm,
                         "estimated_drop_percent": r.estimated_drop_percent, "rmse_drop_percent": r.rmse_drop_percent,
                         "found_given": rounds}
        if r.verification is not None:
            c.conditional["verification"] = r.verification
        if r in eligible and (not n_verify or r.verification is not None and "error" not in r.verification
                              and _confirmed(r, r.verification, min_drop_percent)):
            c.conditional["explanation"] = r.explanation
            c.conditional["found_given"] = rounds + [given]
            found.append(c)
    return sorted(found, key=lambda c: -_priority(rows[c.effect], rows[c.effect].verification))


def select_forward(first: list[Candidate], pool: list[Candidate], run: Run, model: PolyModel, ds, alpha: float,
                   min_effect_percent: float, min_drop_percent: float, n_verify: int,
                   effects=(), built: BuiltCheck | None = None) -> list[Candidate]:
    """Forward selection (module docstring, 5): of `first` (the engine map term, or the missing effects confirmed
    on the model as it is, best first) the first whose refit is verified, then, as long as one is found, the next
    of `pool` (the other re-testable candidates) significant, relevant and verified on the model re-identified with
    those accepted so far. Returns the candidates named in order, `first`'s first; each has its `refit` record (those
    not verified are named, not recommended) and its `alternatives` (`_indistinguishable`); each one tested after
    them has its `conditional` record (the last round's for those never accepted). Stops early once nothing a later
    round could accept can be recommended (`_nothing_left_to_recommend`); the others that round found then hold the
    one it accepted in conditional["stopped_after"]. effects: the engineer-defined effects the candidates may name;
    built: the models `fuelid identify` builds, which the search continues from once the engine's term is accepted
    (`_searched_on`)."""
    named, pool, found = [], list(pool), list(first)  # the confirmed ones not accepted first are re-tested too
    while found:
        for k, c in enumerate(found):
            named.append(c)
            if c in pool:
                pool.remove(c)
            if "explanation" in (c.conditional or {}):  # said as the test on the model re-identified measures it
                c.explanation = c.conditional.pop("explanation")
                if _verification_when_named(c) is not c.verification:
                    c.verification = c.conditional["verification"]
                    c.rmse_drop_percent = c.verification["rmse_drop_percent"]
            refitted = _refit(c, model, run, ds, effects, min_drop_percent,
                              built if c.effect in (MAP_TERM, PRODUCT_TERM) else None,
                              built.memo if built is not None else None)
            if built is not None and c.effect not in (MAP_TERM, PRODUCT_TERM) and _may_be_built(c, refitted):
                built.expect(c)
            if refitted is not None:
                rivals = [r for r in found[k + 1:] if (_round_drop(r) or 0.0) >= RIVAL_SHARE * (_round_drop(c) or 0.0)]
                c.alternatives = _indistinguishable(c, rivals, model, refitted, ds, alpha, min_effect_percent, effects)
                model, run = refitted
                break
        else:  # no refit verified: nothing to re-test the rest on
            break
        if _nothing_left_to_recommend(named, pool, ds, run):
            for rest in found[k + 1:]:  # found beside c, never tested given it
                rest.conditional = {**(rest.conditional or {}), "stopped_after": c.effect}
            break
        found = _retest(pool, model, run, ds, [a.effect for a in named if a.refit["verified"]], alpha,
                        min_effect_percent, min_drop_percent, n_verify) if pool else []
        if built is not None and (likely := next((c for c in found if _may_be_added(c, ds, run)), None)):
            built.guess(likely)  # the one accepted next that may be added, if its refit holds
    for c in pool:
        (c.conditional or {}).pop("explanation", None)
    return named


def _verification_when_named(c: Candidate) -> dict | None:
    """The verification c has once forward selection names it: its own, or when it has none (or its own failed)
    its re-test's (none without verification: n_verify = 0)."""
    if (c.verification is None or "error" in c.verification) and "verification" in (c.conditional or {}):
        return c.conditional["verification"]
    return c.verification


def _nothing_left_to_recommend(named: list[Candidate], pool: list[Candidate], ds, run: Run) -> bool:
    """Whether no later round of forward selection can find an effect that will be recommended (module docstring,
    5): the search is built on a signal that is never added (`_why_never_added`), so whatever a later round finds
    is found given it (`_given_not_added`), and no candidate left that may be added itself (on one trip, no generic
    bus signal) was found in an earlier round given none such (`_found_given_added`). run: the model's, on ds."""
    never = {c.effect for c in named if c.refit is not None and c.refit["verified"] and _why_never_added(c, ds)}
    if not never:
        return False
    # the rounds first: whether speed and torque determine a signal is a regression over the data
    return not any(any(not never.intersection(g) for g in _rounds_found(c)) and _may_be_added(c, ds, run) for c in pool)


def _may_be_added(c: Candidate, ds, run: Run) -> bool:
    """Whether c, once forward selection names it, may be added (recommended) on ds (run: the model's): not a generic
    bus signal on one trip (its verification then holds no trips: ONE_TRIP_ONLY) nor one `_why_never_added` rules
    out."""
    if _generic(c) and len(trips(ds, run)) < 2:
        return False
    return _why_never_added(c, ds, _verification_when_named(c)) is None


def _why_left_at_the_stop(accepted: str) -> str:
    """What the explanation of a candidate found in the round of forward selection that stopped the search
    (`_nothing_left_to_recommend`), beside the one it accepted there, adds."""
    return f" — found beside {accepted}, but forward selection accepted that one and stopped: it had re-identified " \
           "the model with a signal that is never added, after which nothing it finds can be recommended"


def _rounds_found(c: Candidate) -> list[list[str]]:
    """The effects given which each round of forward selection that found c had re-identified the model."""
    return (c.conditional or {}).get("found_given", [])


def _may_be_built(c: Candidate, refitted) -> bool:
    """Whether the final check may build the model with c, accepted by forward selection (`refitted` its verified
    refit, or None): when its refit is verified, unless a generic bus signal found on one trip (never
    recommended), or when only the warm-started refit was worse (`_only_the_warm_refit_worse`)."""
    if refitted is None:
        return _only_the_warm_refit_worse(c)
    return not (_generic(c) and "trips" not in (c.verification or {}))


def _not_recommended(c: Candidate, why: str) -> None:
    """c named but not recommended: its explanation's advice to add it replaced by `why` (a clause saying why)."""
    c.recommended = False
    c.explanation = c.explanation.replace(f"; add effect {c.spec}", "") + why


def _accepted_given_not_added(c: Candidate, recommended: set[str]) -> list[str]:
    """The effects c was accepted given (its conditional record's) that are not among `recommended`."""
    return [e for e in (c.conditional or {}).get("given", []) if e not in recommended]


def _given_not_added(c: Candidate, recommended: set[str]) -> list[str]:
    """The effects c was found and verified given that are not among `recommended`: those it was accepted given,
    none when a round of forward selection found it given recommended effects only (`_found_given_added`)."""
    return [] if _found_given_added(c, recommended) is not None else _accepted_given_not_added(c, recommended)


def _found_given_added(c: Candidate, recommended: set[str]) -> list[str] | None:
    """The effects given which a round of forward selection found c (significant, relevant, confirmed: `_retest`),
    the first such round whose effects are those recommended before c (`recommended`), no more and no fewer — so c
    was verified on the model `fuelid identify --effects-from` builds with them, though accepted in a later round
    given a bus signal that is not added (a one-trip signal with a larger drop accepted before it); None when no round
    was. (A round given only some of them verified c on a model without the others, which may explain it away.)"""
    return next((g for g in _rounds_found(c) if set(g) == recommended), None)


def _round_drop(c: Candidate) -> float | None:
    """c's held-out drop [%] on the model of the round it was found in: its re-test's, else the model as it is."""
    return (c.conditional or {}).get("rmse_drop_percent", c.rmse_drop_percent)


def _relevant_given(c: Candidate, model: PolyModel, run: Run, ds, alpha: float, min_effect_percent: float) -> bool:
    """c re-tested alone on `model` (1–3, at alpha): significant and explaining min_effect_percent."""
    given = rank_candidates(model, ds, run, [c.definition], alpha)[0]
    return given.test_significant and given.estimated_drop_percent >= min_effect_percent


def _indistinguishable(c: Candidate, rivals: list[Candidate], model: PolyModel, with_c: tuple[PolyModel, Run], ds,
                       alpha: float, min_effect_percent: float, effects=()) -> list[str]:
    """Those of `rivals` (found on `model` beside c) that explain c away and c them (module docstring, 5): not
    significant and relevant on `with_c`, the model re-identified with c and its run, and c not on `model`
    re-identified with the rival instead. A rival whose refit fails cannot be compared and is left out."""
    alike = []
    for r in rivals:
        if _relevant_given(r, *with_c, ds, alpha, min_effect_percent):
            continue
        try:
            refit = refit_with_effects(model, ds, [r.effect], defined=effects, max_iter=REFIT_MAX_ITER)
            if not _relevant_given(c, refit, run_gradients(run_model(refit, ds)), ds, alpha, min_effect_percent):
                alike.append(r.effect)
        except (FuelidError, np.linalg.LinAlgError):
            continue
    return alike


def _verify(c: Candidate, model: PolyModel, ds, run: Run, base: Baseline) -> None:
    """c's verification against the model as it is (base: its Baseline; the entry kind's), kept on c; an error
    recorded, not raised."""
    try:
        c.verification = v = c.entry.verify(c, model, ds, run, base)
        c.rmse_drop_percent = v["rmse_drop_percent"]
    except (ValueError, np.linalg.LinAlgError) as exc:
        c.verification = {"error": str(exc)}


def engine_map_term(testable: list[Candidate], model: PolyModel, ds, run: Run, base: Baseline | None,
                    min_effect_percent: float, min_drop_percent: float, n_verify: int,
                    built: BuiltCheck) -> Candidate | None:
    """The engine map term (module docstring, 0): the `engine_map` candidate when its test (alone, at α) rejects,
    it explains min_effect_percent and (n_verify > 0) its verification confirms it; the `power_nonlinearity`
    candidate instead when that product term alone, verified too, comes within min_drop_percent of its held-out
    drop and the model identify builds with it (`built`) simulates the data within min_drop_percent of the one
    built with the full map (`_map_beats_product`). None when the map is not measurably curved (or not
    testable: the model has it already)."""
    full = next((c for c in testable if c.effect == MAP_TERM), None)
    if full is None or not full.test_significant or full.estimated_drop_percent < min_effect_percent:
        return None
    if not n_verify:
        return full
    product = next((c for c in testable if c.effect == PRODUCT_TERM), None)
    for c in (full, product):
        if c is not None:
            _verify(c, model, ds, run, base)
    if "error" in full.verification or not _confirmed(full, full.verification, min_drop_percent):
        return None
    if product is not None and "error" not in product.verification \
            and _confirmed(product, product.verification, min_drop_percent) \
            and product.rmse_drop_percent > full.rmse_drop_percent - min_drop_percent \
            and not _map_beats_product(built, full, product, min_drop_percent):
        return product
    return full


def _map_beats_product(built: BuiltCheck, full: Candidate, product: Candidate, min_drop_percent: float) -> bool:
    """Whether the model identify builds with the full map term simulates the data better by min_drop_percent than
    the one built with the product term alone (recorded in full.verification["built"]). The linearised refit
    steps once from the model as it is; the map's FIR taps reach further by PEM (a fuel delay they absorb: README),
    and the model identify builds is what the engineer gets."""
    try:
        with_product, with_map = (built.rmse_with(c) for c in (product, full))
    except (FuelidError, np.linalg.LinAlgError):
        return False
    full.verification["built"] = {"effects": list(built.specs), "rmse_with_product": with_product,
                                  "rmse_with_map": with_map}
    return with_map < (1.0 - min_drop_percent / 100.0) * with_product


def _map_sentence(term: Candidate, full: Candidate | None, product: Candidate | None) -> str:
    """What the diagnosis says of the engine map term: the curvature, what the linear model misses of it held
    out, how much of it the speed × torque product alone explains (its own held-out drop beside the full map's)
    and what to add."""
    drop = (term.verification or {}).get("rmse_drop_percent")
    misses = "" if drop is None else f"; the linear model misses it: the held-out RMS error falls {drop:.0f} % " \
                                     f"with the map term"
    if term is product:
        alone = "" if full is None or full.rmse_drop_percent is None else \
            f" (the full map term, with its other terms, {full.rmse_drop_percent:.0f} %)"
        dominant = f"; the speed × torque product alone explains it{alone}"
    elif product is not None and product.rmse_drop_percent is not None:
        dominant = f"; the speed × torque product alone {product.rmse_drop_percent:.0f} %, the other terms " \
                   f"({', '.join(term.reg.names[1:])}) the rest"
    else:
        dominant = ""
    b = None if full is None else (full.verification or {}).get("built")
    if b is not None:  # the linearised refit preferred the product term: the models identify builds decided
        dominant += f"; as `fuelid identify` builds them, the model with the full map term simulates these data " \
                    f"with RMS error {b['rmse_with_map']:.3f}, with the product alone {b['rmse_with_product']:.3f}"
    return f"the engine's fuel map is curved: efficiency varies over speed × torque, so fuel is not a plane in " \
           f"them, and it burns more while the torque builds up (transient fuelling){misses}{dominant}; a property " \
           f"of the engine, not a hidden effect; add effect {term.effect}"


@in_one_blas_thread
def diagnose(model: PolyModel, ds, alpha: float = 0.05, n_verify: int = 10, min_effect_percent: float = 1.0,
             candidates=None, min_drop_percent: float = 2.0, effects=(), workers: int = 0) -> Diagnosis:
    """The whole diagnosis of `model` on dataset ds (ident.diagnosis and its modules).

    Returns a Diagnosis: model, data, compare (ident.validation.metrics of its run), held_out (held_out_scores of
    the model as it is, linearised refit without each block: rmse [output unit], cycle_fuel_error_percent; None
    when it cannot be scored), where_it_fails, test, candidates, verdict, run.
    Each candidate (best first) has: effect (id for `fuelid identify --effect`), name, form, signals (DBC
    names), spns, statistic (the larger LM of its two tests), df, p_value (Bonferroni over the two tests),
    p_holm, test_significant (Holm at alpha), estimated_drop_percent (share of the simulation error its
    least-squares fit explains), conditional (its re-test given the effects accepted before it), explained_by,
    alternatives (for a missing effect named, the rivals these data cannot tell it from: module docstring, 5),
    rmse_drop_percent (held-out RMS simulation error drop with it, linearised refit, None unless verified),
    verification (held-out RMSE and cycle fuel errors without/with, direction), significant (a missing effect:
    when verified, a held-out drop ≥ min_drop_percent in the direction of its physics, then accepted by
    `select_forward`; or the engine map term, module docstring 0), role (ENGINE_MAP for the engine map term,
    MISSING_EFFECT for a hidden effect named, None otherwise), recommended (significant and verified: what
    `fuelid identify --effects-from` adds, the engine map term first), size,
    explanation, physics, tests. At most n_verify of the candidates that pass the tests and explain
    min_effect_percent are verified, by estimated drop (and the fuel delay, the signal path's own family,
    whenever its tests find it). effects: effects the engineer defined (ident.effectfile),
    tested beside the built-in ones. BLAS runs on one thread throughout: every product here is N × d with d up to
    about a hundred, where its threads cost more time than they save, and the diagnosis is then the same to the bit
    on any number of cores (a fleet worker runs one thread: fleet.jobs). workers: 1 to build the models `fuelid
    identify` would build, on which what is recommended is checked (5), ahead in a worker process beside the
    diagnosis (ident.diagnosis.builds: the same diagnosis, sooner on two cores), 0 to build each here when needed
    (the fleet's jobs: one per core already)."""
    mrun = run_model(model, ds)
    run = run_gradients(mrun)
    built = BuiltCheck(model, ds, effects, workers)  # what is recommended is verified on the model identify builds (5)
    try:
        return _diagnosed(model, ds, mrun, run, built, candidates, alpha, n_verify, min_effect_percent,
                          min_drop_percent, effects)
    finally:
        built.close()


def _diagnosed(model: PolyModel, ds, mrun: ModelRun, run: Run, built: BuiltCheck, candidates, alpha: float,
               n_verify: int, min_effect_percent: float, min_drop_percent: float, effects) -> Diagnosis:
    """`diagnose` with its model run, gradients and the builds it checks on."""
    relevant = lambda c: c.test_significant and c.estimated_drop_percent >= min_effect_percent  # noqa: E731
    if built.ahead and n_verify and candidates is None and MAP_TERM not in model.effects:
        # the engine's term tested first, alone (at α, as in rank_candidates): its build starts in the worker
        # while the other candidates are tested
        early = rank_candidates(model, ds, run, [fx.EFFECTS[MAP_TERM]], alpha)[0]
        if relevant(early):
            built.guess(early)
    rows = rank_candidates(model, ds, run, candidates, alpha, effects)
    testable = [c for c in rows if c.testable]
    try:  # the model as it is, scored on each block left out: the reference every verification is measured against
        base = baseline(model, run, ds)
    except (ValueError, np.linalg.LinAlgError):
        base = None
    if n_verify and base is None and any(c.test_significant for c in testable):
        raise InputError("the model cannot be scored on held-out blocks of these data")
    full = next((c for c in testable if c.effect == MAP_TERM), None)
    if n_verify and full is not None and relevant(full):  # the build the engine's term needs, ahead (builds.py)
        built.guess(full)
    others = sorted((c for c in testable if c.effect not in (MAP_TERM, PRODUCT_TERM) and relevant(c)),
                    key=lambda c: -_priority(c))
    # verified before the engine's term, whose check waits for that build: they do not depend on it
    for c in others[:n_verify] + [c for c in others[n_verify:] if n_verify and not c.entry.retested]:
        # the signal path's candidate (the fuel delay) is a family of its own, verified on its own reference: it
        # does not compete with the fuelling effects for the verification budget
        _verify(c, model, ds, run, base)
    term = engine_map_term(testable, model, ds, run, base, min_effect_percent, min_drop_percent, n_verify, built)
    outranking = [c for c in others if term is not None and c.entry.retested and c.rmse_drop_percent is not None
                  and _confirmed(c, c.verification, min_drop_percent) and _priority(c) > term.rmse_drop_percent]
    if outranking:  # a hidden effect the map's columns would partly absorb: no map term first (module docstring, 0)
        full = next(c for c in testable if c.effect == MAP_TERM)
        full.explanation += f" — but {outranking[0].effect} explains more of what the model misses " \
                            f"({outranking[0].rmse_drop_percent:.0f} % held out against {term.rmse_drop_percent:.0f} %)" \
                            ": not named as the engine's map"
        term = None
    # the hidden-effect family: never the full map; the product term too once the map term is named (0)
    hidden = [c for c in testable if c.effect != MAP_TERM and (term is None or c.effect != PRODUCT_TERM)]
    eligible = sorted((c for c in hidden if relevant(c)), key=lambda c: -_priority(c))
    for c in [c for c in eligible if c.verification is None][:max(n_verify - len(others[:n_verify]), 0)]:
        _verify(c, model, ds, run, base)
    confirmed, unconfirmed = [], []
    for c in eligible:
        (confirmed if _confirmed(c, c.verification, min_drop_percent) else unconfirmed).append(c)
    confirmed.sort(key=lambda c: (c.verification is None, -_priority(c)))  # verified ones first
    accepted = [c for c in confirmed if not c.entry.retested]  # the fuel delay: the signal path (delay.py)
    first = [term] if term is not None else [c for c in confirmed if c.entry.retested]
    if term is not None:  # the builds `add` takes if the term and the fuel delay are added (the others: select_forward)
        for c in [term] + accepted:
            built.expect(c)
    if first:
        pool = [c for c in hidden if c.entry.retested]
        found = select_forward(first, pool, run, model, ds, alpha, min_effect_percent, min_drop_percent, n_verify,
                               effects, built)
        accepted += [c for c in found if c is not term]
        for c in confirmed + [c for c in testable if term is not None and c not in hidden and c is not term]:
            if c not in accepted and (c.test_significant or c.effect in (MAP_TERM, PRODUCT_TERM)):
                cond = c.conditional or {}
                if "stopped_after" in cond:  # found in the round that stopped the search, not explained away
                    c.explanation += _why_left_at_the_stop(cond["stopped_after"])
                else:  # what its last re-test was given (forward selection may stop before a round given them all)
                    c.explained_by = ", ".join(cond.get("given") or [a.effect for a in found])
    if term is not None:
        term.significant, term.role = True, ENGINE_MAP
        term.recommended = term.verification is not None and "error" not in term.verification \
            and _refit_verified(term)
        term.explanation = _map_sentence(term, *(next((c for c in testable if c.effect == e), None)
                                                 for e in (MAP_TERM, PRODUCT_TERM)))
        if term.recommended and term.refit is not None and not built.add(term):
            term.refit["verified"] = False
            _not_recommended(term, _why_refit_not_verified(term))
    term_added = term is not None and term.recommended
    recommended = {term.effect} if term_added else set()
    for c in accepted:  # in the order accepted, so that what each was found given is decided before it
        c.significant, c.role = True, MISSING_EFFECT
        if c.alternatives:
            c.explanation += f" — or {' or '.join(c.alternatives)}: these data cannot tell them apart (neither is " \
                             "significant given the other; data where they differ, another day, can)"
        # verified on held-out data (and trips, when there are several): what `fuelid identify --effects-from` adds
        warm_only = _only_the_warm_refit_worse(c)  # the model identify builds decides instead (5)
        c.recommended = c.verification is not None and "error" not in c.verification \
            and (_refit_verified(c) or warm_only)
        if c.verification is None:  # significant by its tests alone: what they found is no advice to add it
            _not_recommended(c, f" — not verified (`fuelid diagnose --verify {n_verify}`): not recommended")
        elif not _refit_verified(c) and not warm_only:
            _not_recommended(c, _why_refit_not_verified(c))
        elif c.recommended and (why := _why_never_added(c, ds)) is not None:
            _not_recommended(c, why)
        elif c.recommended and (missing := _given_not_added(c, recommended)):
            _not_recommended(c, f" — but it was found given {', '.join(missing)}, which is not added: not recommended")
        if c.recommended and c.refit is None and not term_added:  # the fuel delay, on the model as it is
            built.given(c)
        elif c.recommended and not built.add(c, min_drop_percent if warm_only else 0.0):
            # (the fuel delay: given the engine's term.) Where only the warm refit was worse, the built model must
            # show the relevance the refit could not: a smaller gain is a tie within the fits' reproducibility
            if c.refit is not None:
                c.refit["verified"] = False
            _not_recommended(c, _why_built_worse(built_record(c)["built"]))
        elif c.recommended and warm_only:
            c.refit["verified"] = True
            b = c.refit["built"]
            c.explanation += f" (forward selection's warm-started refit with it simulated these data worse, RMS " \
                             f"error {c.refit['rmse_without']:.3f} → {c.refit['rmse_with']:.3f}; the model " \
                             f"`fuelid identify --effects-from` builds with it simulates them at least " \
                             f"{b['min_gain_percent']:g} % better, {b['rmse_without']:.3f} → {b['rmse_with']:.3f})"
        if c.recommended and (missing := _accepted_given_not_added(c, recommended)):
            c.explanation += f" (accepted given {', '.join(missing)}, not added; found and verified before that " \
                             f"given {', '.join(_found_given_added(c, recommended))} alone)"
        if c.recommended:
            recommended.add(c.effect)
    for c in unconfirmed:
        if not c.significant:
            c.explanation += _why_not_confirmed(c, min_drop_percent)
    for c in rows:
        if c.explained_by:
            given = "them" if "," in c.explained_by else "it"
            c.explanation += f" — explained by {c.explained_by} (not significant given {given})"
        elif c.test_significant and not c.significant and c.estimated_drop_percent < min_effect_percent:
            c.explanation += f" — statistically detectable, but it explains only " \
                             f"{c.estimated_drop_percent:.1f} % of the simulation error (< {min_effect_percent:g} %)"
    for c in rows:
        if c.testable and not c.significant:
            c.explanation = as_evidence(c)
    order = {id(c): k for k, c in enumerate(([term] if term is not None else []) + accepted)}
    rows.sort(key=lambda c: (not c.significant, order.get(id(c), 0), c.log10_p))
    n_hidden = len([c for c in hidden if c.testable])
    said = [_said_with_drop(c) for c in accepted]
    engine = "" if term is None else f"Engine map: {term.explanation}. "
    if said:
        verdict = engine + (f"Missing effect: {said[0]}." if len(said) == 1 else
                            f"Missing effects ({len(said)}): " + "; ".join(f"({k}) {t}" for k, t in enumerate(said, 1))
                            + ".")
    elif term is None:
        verdict = f"No significant candidate: none of the {n_hidden} candidate effects explains the residual " \
                  f"(Holm-corrected, family-wise α = {alpha:g}, at least {min_effect_percent:g} % of the " \
                  f"simulation error, and a held-out RMS error drop of at least {min_drop_percent:g} %); the model " \
                  "is not missing any effect the bus reveals."
    else:
        verdict = engine + f"No missing effect: given the engine map term, none of the {n_hidden} other candidate " \
                  f"effects explains the residual (Holm-corrected, family-wise α = {alpha:g}, at least " \
                  f"{min_effect_percent:g} % of the simulation error, and a held-out RMS error drop of at least " \
                  f"{min_drop_percent:g} %); beyond its map, the model is not missing any effect the bus reveals."
    return Diagnosis(
        model={"effects": list(model.effects), "inputs": list(model.input_names), "Ts": model.Ts},
        data=ds.summary() if hasattr(ds, "summary") else {},
        compare={**metrics(mrun, ds), "unit": ds.output_unit},
        held_out=None if base is None else base.scores,
        where_it_fails=where_it_fails(model, ds, run),
        test={"method": "score (LM) tests on the prediction errors and, GLS-whitened under the alternative, on "
                        "the simulation errors; Newey-West robust, chi2(k); Bonferroni over the two, Holm "
                        "step-down over all candidates; relevance; a linearised refit scored leaving out one 60-s "
                        "block (and, with several trips, one trip) at a time; forward selection re-testing the rest "
                        "on the model refitted with the effects accepted",
              "alpha": alpha, "min_effect_percent": min_effect_percent, "min_drop_percent": min_drop_percent,
              "candidates_tested": len(testable),
              "samples": int(run.e.size)},
        candidates=rows,
        verdict=verdict,
        run=mrun,
        engine_map=term,
    )
