"""Forward selection of every effect missing, after the engine map term (ident.diagnosis.verdict, 0) or the first effect
confirmed on the model as it is.

5. Forward selection. Bus signals are dependent (a cab temperature follows the level shift a real effect leaves in the
   error), and two effects can hide at once (the weaker one's held-out drop on the model as it is falls short, the
   stronger one's error covering it, and the model's own parameters, fitted without the stronger one, are biased by it).
   The confirmed candidate with the largest held-out drop (`priority`; a generic bus signal's discounted by
   GENERIC_WEIGHT) is accepted first and the model re-identified with it by PEM, warm-started from the model itself with
   the effect's coefficients at zero (ident.identify.refit_with_effects: the point the linearised refit of 4 starts
   from, so a few iterations suffice and V never rises); then, as long as one is found, every remaining candidate is
   tested again on that re-identified model (1–3, Holm-corrected over the candidates re-tested), must explain
   min_effect_percent and is verified on it (4: held-out drop ≥ min_drop_percent, its physics' direction, identifiable,
   never worse on a held-out trip); the one with the largest drop is accepted next and the model re-identified with it
   too (`select_forward`). Those confirmed on the model as it is but never accepted are "explained by" the accepted
   ones. Explaining away can go both ways: two signals that move together on these data (in the simulator, an oil
   temperature that follows the same smoothed load as the intake air) each leave the other insignificant. So each rival
   confirmed in the same round as the accepted candidate, with a held-out drop at least RIVAL_SHARE of its, is re-tested
   alone (1–3, at α) on the model re-identified with the accepted one and, when it is not significant and relevant
   there, the other way round: the accepted one on the model re-identified with the rival instead. When neither is, the
   data cannot tell the two apart: the rival is listed in the accepted one's `alternatives` and its explanation says so
   (data where they differ, another day, can). Not when engine speed and torque determine both signals (two forms of
   EEC1's demand torque): neither is ever added, on any data, and both stand for the engine's own fuelling, so which one
   it is does not matter (`inputs_determine`). An accepted candidate whose re-identified model simulates the data worse
   than the model without it (RMS simulation error over the tested samples: the refit cannot be verified) is not built
   on: the search goes on from the model without it, with the next candidate found; it is named, and recommended only
   when it brings its physics (catalogued or engineer-defined) and the model identify builds (below) simulates the data
   better with it by at least min_drop_percent (`only_the_warm_refit_worse`): the relevance its refit could not show.
   Less is a tie within the fits' reproducibility, not evidence (on the map engine one such tie added an effect that
   raised another day's error: README). The warm-started refits are the search, not the model `fuelid identify
   --effects-from` builds: that one is identified by PEM from its own initialisation and from the effects added in turn
   (ident.identify.identify_model), and the two can end in minima far apart (a warm start keeps the dynamics of the
   model without the effects). So what is to be recommended is checked once more, in the order found, on the model
   identify builds (`BuiltCheck`, `refit.built`): built from the effects recommended before it plus the candidate, it
   must simulate the data no worse than built without it; otherwise the candidate is named, not recommended, and those
   found given it are not recommended either (`given_not_added`). The fuel delay, verified on its reference model and on
   the model as it is (delay.py), is checked so too when the engine's term is added (`verification.built`): the model
   identify builds then has the term's taps, which absorb a delay, and with a delay estimated 0.05 s off it can simulate
   worse than without it (README).
"""
from __future__ import annotations

import numpy as np

from fuelid.errors import FuelidError
from fuelid.ident.diagnosis.builds import BuiltCheck
from fuelid.ident.diagnosis.candidate import Candidate
from fuelid.ident.diagnosis.carryover import left_out_trips
from fuelid.ident.diagnosis.ranking import MAP_TERM, PRODUCT_TERM, rank_candidates, verify
from fuelid.ident.diagnosis.recommendation import inputs_determine, is_confirmed, is_generic, \
    only_the_warm_refit_worse, priority, rounds_found, why_never_added
from fuelid.ident.diagnosis.run import Run, run_gradients
from fuelid.ident.diagnosis.verification import baseline, trips
from fuelid.ident.identify import FitMemo, refit_with_effects
from fuelid.ident.modelrun import ModelRun, run_model
from fuelid.ident.polymodel import PolyModel

RIVAL_SHARE = 0.5  # a rival explaining less than half of what the accepted one does cannot explain it away
REFIT_MAX_ITER = 30  # Levenberg–Marquardt iterations of forward selection's warm-started PEM refit


def _simulation_rmse(run: Run | ModelRun, index: np.ndarray) -> float:
    """RMS simulation error [output unit] of a run on the dataset samples `index` (tested ones)."""
    return float(np.sqrt(np.mean((run.y[index] - run.ysim[index]) ** 2)))


def _refit(c: Candidate, model: PolyModel, run: Run, ds, effects, min_drop_percent: float,
           built: BuiltCheck | None = None, memo: FitMemo | None = None) -> tuple[PolyModel, Run] | None:
    """The model re-identified with c added (module docstring) and its run, with c.refit its record (RMS
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
    if c.refit["verified"] and is_generic(c):
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
    effects `given`), tested and verified on it afresh (module docstring), best first; each one's
    `conditional` record is this test's, with the explanation its verification makes."""
    rows = {r.effect: r for r in rank_candidates(model, ds, run, [c.definition for c in pool], alpha)}
    eligible = sorted((r for r in rows.values() if r.test_significant and r.estimated_drop_percent >= min_effect_percent),
                      key=lambda r: -priority(r))
    if n_verify and eligible:
        base = baseline(model, run, ds)
        for r in eligible[:n_verify]:
            verify(r, model, ds, run, base)
    found = []
    for c in pool:
        r = rows[c.effect]
        rounds = rounds_found(c)
        c.conditional = {"given": given, "p_value": r.p_value, "p_holm": r.p_holm,
                         "estimated_drop_percent": r.estimated_drop_percent, "rmse_drop_percent": r.rmse_drop_percent,
                         "found_given": rounds}
        if r.verification is not None:
            c.conditional["verification"] = r.verification
        if r in eligible and (not n_verify or r.verification is not None and "error" not in r.verification
                              and is_confirmed(r, r.verification, min_drop_percent)):
            c.conditional["explanation"] = r.explanation
            c.conditional["found_given"] = rounds + [given]
            found.append(c)
    return sorted(found, key=lambda c: -priority(rows[c.effect], rows[c.effect].verification))


def select_forward(first: list[Candidate], pool: list[Candidate], run: Run, model: PolyModel, ds, alpha: float,
                   min_effect_percent: float, min_drop_percent: float, n_verify: int,
                   effects=(), built: BuiltCheck | None = None) -> list[Candidate]:
    """Forward selection (module docstring): of `first` (the engine map term, or the missing effects confirmed
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
                c.alternatives = _indistinguishable(c, _rivals(c, found[k + 1:], ds), model, refitted, ds, alpha,
                                                    min_effect_percent, effects)
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
    """Whether no later round of forward selection can find an effect that will be recommended
    (ident.diagnosis.recommendation): the search is built on a signal that is never added (`why_never_added`), so
    whatever a later round finds is found given it (`given_not_added`), and no candidate left that may be added itself
    (on one trip, no generic bus signal) was found in an earlier round given none such (`found_given_added`). run: the
    model's, on ds."""
    never = {c.effect for c in named if c.refit is not None and c.refit["verified"] and why_never_added(c, ds)}
    if not never:
        return False
    # the rounds first: whether speed and torque determine a signal is a regression over the data
    return not any(any(not never.intersection(g) for g in rounds_found(c)) and _may_be_added(c, ds, run) for c in pool)


def _may_be_added(c: Candidate, ds, run: Run) -> bool:
    """Whether c, once forward selection names it, may be added (recommended) on ds (run: the model's): not a generic
    bus signal on one trip (its verification then holds no trips: ONE_TRIP_ONLY) nor one `why_never_added` rules
    out."""
    if is_generic(c) and len(trips(ds, run)) < 2:
        return False
    return why_never_added(c, ds, _verification_when_named(c)) is None


def why_left_at_the_stop(accepted: str) -> str:
    """What the explanation of a candidate found in the round of forward selection that stopped the search
    (`_nothing_left_to_recommend`), beside the one it accepted there, adds."""
    return f" — found beside {accepted}, but forward selection accepted that one and stopped: it had re-identified " \
           "the model with a signal that is never added, after which nothing it finds can be recommended"


def _may_be_built(c: Candidate, refitted) -> bool:
    """Whether the final check may build the model with c, accepted by forward selection (`refitted` its verified
    refit, or None): when its refit is verified, unless a generic bus signal found on one trip (never
    recommended), or when only the warm-started refit was worse (`only_the_warm_refit_worse`)."""
    if refitted is None:
        return only_the_warm_refit_worse(c)
    return not (is_generic(c) and "trips" not in (c.verification or {}))


def _round_drop(c: Candidate) -> float | None:
    """c's held-out drop [%] on the model of the round it was found in: its re-test's, else the model as it is."""
    return (c.conditional or {}).get("rmse_drop_percent", c.rmse_drop_percent)


def _rivals(c: Candidate, beside: list[Candidate], ds) -> list[Candidate]:
    """Of the candidates found beside c, the one accepted, those that might explain it away (module docstring): a
    held-out drop in their round at least RIVAL_SHARE of c's, and not both signals that engine speed and torque
    determine (`inputs_determine`)."""
    rivals = [r for r in beside if (_round_drop(r) or 0.0) >= RIVAL_SHARE * (_round_drop(c) or 0.0)]
    return [r for r in rivals if not inputs_determine(r, ds)] if inputs_determine(c, ds) else rivals


def _relevant_given(c: Candidate, model: PolyModel, run: Run, ds, alpha: float, min_effect_percent: float) -> bool:
    """c re-tested alone on `model` (1–3, at alpha): significant and explaining min_effect_percent."""
    given = rank_candidates(model, ds, run, [c.definition], alpha)[0]
    return given.test_significant and given.estimated_drop_percent >= min_effect_percent


def _indistinguishable(c: Candidate, rivals: list[Candidate], model: PolyModel, with_c: tuple[PolyModel, Run], ds,
                       alpha: float, min_effect_percent: float, effects=()) -> list[str]:
    """Those of `rivals` (found on `model` beside c) that explain c away and c them (module docstring): not
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
