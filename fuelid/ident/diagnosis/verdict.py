"""The diagnosis's verdict: the engine's own map first, the hidden effects forward selection names after it
(ident.diagnosis.selection, 5), what is recommended (ident.diagnosis.recommendation), checked on the models `fuelid
identify` builds (ident.diagnosis.builds), and the sentence that says it all: `diagnose` → Diagnosis.

0. The engine map. A real engine's fuel map is curved (efficiency varies over speed × torque) and a linear model is a
   plane through it, and the engine burns more while the torque builds up than its map says (transient fuelling); that
   is a property of the engine, not a hidden effect, and on a real engine it outweighs any hidden one. The map term
   `engine_map` (ident.effects: ñ·T̃, ñ², T̃², the torque's rise) is tested first, as one group (one test over all its
   columns, at α: the first test of a fixed sequence, so the hidden-effect family after it keeps its own α), must
   explain min_effect_percent and is verified like any candidate (held-out drop ≥ min_drop_percent). When it is
   confirmed and no other candidate, verified on the model as it is, lowers the held-out error more (a generic bus
   signal's drop discounted by GENERIC_WEIGHT, as in selection, 5; the map's columns would absorb part of such an effect
   that varies with the operating point: on a linear engine hiding an inertia, they do), it is named as the engine map
   term (role ENGINE_MAP) — as `power_nonlinearity` when the speed × torque product alone does as well (the other terms
   add less than min_drop_percent held out) and the model identify builds with the full map simulates the data no better
   by min_drop_percent than the one built with the product (`_map_beats_product`: the linearised refit steps once from
   the model as it is, while PEM reaches what the map's FIR taps hold, e.g. a fuel delay) — and the hidden-effect search
   (selection, 5) starts from the model with it: the one identify builds with it (`BuiltCheck`), unless forward
   selection's warm-started refit simulates the data better (`selection._searched_on`). Started from the linear model
   and capped at REFIT_MAX_ITER iterations, that refit can stop far short of it (README), and the hidden effects, tested
   on what it leaves, would be tested against the map's curvature too. The full map is never a hidden effect; the
   product term is one only when no map term is named.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fuelid.blas import in_one_blas_thread
from fuelid.errors import FuelidError, InputError
from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.builds import BuiltCheck, built_record
from fuelid.ident.diagnosis.candidate import ENGINE_MAP, MISSING_EFFECT, Candidate
from fuelid.ident.diagnosis.explanation import as_evidence
from fuelid.ident.diagnosis.failures import where_it_fails
from fuelid.ident.diagnosis.ranking import MAP_TERM, PRODUCT_TERM, rank_candidates, verify
from fuelid.ident.diagnosis.recommendation import NOT_RECOMMENDED, accepted_given_not_added, is_confirmed, \
    found_given_added, given_not_added, not_recommended, only_the_warm_refit_worse, priority, refit_verified, \
    why_built_worse, why_never_added, why_not_confirmed, why_refit_not_verified
from fuelid.ident.diagnosis.run import Run, run_gradients
from fuelid.ident.diagnosis.selection import REFIT_MAX_ITER, select_forward, why_left_at_the_stop
from fuelid.ident.diagnosis.verification import Baseline, baseline
from fuelid.ident.modelrun import ModelRun, run_model
from fuelid.ident.polymodel import PolyModel
from fuelid.ident.validation import metrics


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
            verify(c, model, ds, run, base)
    if "error" in full.verification or not is_confirmed(full, full.verification, min_drop_percent):
        return None
    if product is not None and "error" not in product.verification \
            and is_confirmed(product, product.verification, min_drop_percent) \
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
    alternatives (for a missing effect named, the rivals these data cannot tell it from: ident.diagnosis.selection, 5),
    rmse_drop_percent (held-out RMS simulation error drop with it, linearised refit, None unless verified),
    verification (held-out RMSE and cycle fuel errors without/with, direction), significant (a missing effect:
    when verified, a held-out drop ≥ min_drop_percent in the direction of its physics, then accepted by
    `select_forward`; or the engine map term, module docstring, 0), role (ENGINE_MAP for the engine map term,
    MISSING_EFFECT for a hidden effect named, None otherwise), recommended (significant and verified: what
    `fuelid identify --effects-from` adds, the engine map term first), size,
    explanation, physics, tests. At most n_verify of the candidates that pass the tests and explain
    min_effect_percent are verified, by estimated drop (and the fuel delay, the signal path's own family,
    whenever its tests find it). effects: effects the engineer defined (ident.effectfile),
    tested beside the built-in ones. BLAS runs on one thread throughout: every product here is N × d with d up to
    about a hundred, where its threads cost more time than they save, and the diagnosis is then the same to the bit
    on any number of cores (a fleet worker runs one thread: fleet.jobs). workers: 1 to build the models `fuelid
    identify` would build, on which what is recommended is checked (selection, 5), ahead in a worker process beside the
    diagnosis (ident.diagnosis.builds: the same diagnosis, sooner on two cores), 0 to build each here when needed
    (the fleet's jobs: one per core already)."""
    mrun = run_model(model, ds)
    run = run_gradients(mrun)
    # what is recommended is verified on the model identify builds (selection, 5)
    # its fits are kept at the warm-started refits' limit on their way: that refit, where forward selection needs it
    built = BuiltCheck(model, ds, effects, workers, checkpoints=(REFIT_MAX_ITER,))
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
                    key=lambda c: -priority(c))
    # verified before the engine's term, whose check waits for that build: they do not depend on it
    for c in others[:n_verify] + [c for c in others[n_verify:] if n_verify and not c.entry.retested]:
        # the signal path's candidate (the fuel delay) is a family of its own, verified on its own reference: it
        # does not compete with the fuelling effects for the verification budget
        verify(c, model, ds, run, base)
    term = engine_map_term(testable, model, ds, run, base, min_effect_percent, min_drop_percent, n_verify, built)
    outranking = [c for c in others if term is not None and c.entry.retested and c.rmse_drop_percent is not None
                  and is_confirmed(c, c.verification, min_drop_percent) and priority(c) > term.rmse_drop_percent]
    if outranking:  # a hidden effect the map's columns would partly absorb: no map term first (module docstring, 0)
        full = next(c for c in testable if c.effect == MAP_TERM)
        full.explanation += f" — but {outranking[0].effect} explains more of what the model misses " \
                            f"({outranking[0].rmse_drop_percent:.0f} % held out against {term.rmse_drop_percent:.0f} %)" \
                            ": not named as the engine's map"
        term = None
    # the hidden-effect family: never the full map; the product term too once the map term is named (0)
    hidden = [c for c in testable if c.effect != MAP_TERM and (term is None or c.effect != PRODUCT_TERM)]
    eligible = sorted((c for c in hidden if relevant(c)), key=lambda c: -priority(c))
    for c in [c for c in eligible if c.verification is None][:max(n_verify - len(others[:n_verify]), 0)]:
        verify(c, model, ds, run, base)
    confirmed, unconfirmed = [], []
    for c in eligible:
        (confirmed if is_confirmed(c, c.verification, min_drop_percent) else unconfirmed).append(c)
    confirmed.sort(key=lambda c: (c.verification is None, -priority(c)))  # verified ones first
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
                    c.explanation += why_left_at_the_stop(cond["stopped_after"])
                else:  # what its last re-test was given (forward selection may stop before a round given them all)
                    c.explained_by = ", ".join(cond.get("given") or [a.effect for a in found])
    if term is not None:
        _name_the_term(term, testable, built)
    _recommend(accepted, term, built, ds, n_verify, min_drop_percent)
    _say_why_not(rows, unconfirmed, min_effect_percent, min_drop_percent)
    order = {id(c): k for k, c in enumerate(([term] if term is not None else []) + accepted)}
    rows.sort(key=lambda c: (not c.significant, order.get(id(c), 0), c.log10_p))
    verdict = _verdict(term, accepted, len([c for c in hidden if c.testable]), alpha, min_effect_percent,
                       min_drop_percent)
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


def _name_the_term(term: Candidate, testable: list[Candidate], built: BuiltCheck) -> None:
    """The engine map term named (module docstring, 0): its sentence, and recommended when its verification stands, its
    refit is verified and the model identify builds with it simulates the data no worse (`built.add`)."""
    term.significant, term.role = True, ENGINE_MAP
    term.recommended = term.verification is not None and "error" not in term.verification \
        and refit_verified(term)
    term.explanation = _map_sentence(term, *(next((c for c in testable if c.effect == e), None)
                                             for e in (MAP_TERM, PRODUCT_TERM)))
    if term.recommended and term.refit is not None and not built.add(term):
        term.refit["verified"] = False
        not_recommended(term, why_refit_not_verified(term))


def _recommend(accepted: list[Candidate], term: Candidate | None, built: BuiltCheck, ds, n_verify: int,
               min_drop_percent: float) -> None:
    """Each missing effect accepted named, and recommended (what `fuelid identify --effects-from` adds) when the rules
    of ident.diagnosis.recommendation hold and the model identify builds with it, after those recommended before it
    (the engine map term `term` first, when it is), simulates the data no worse (`built.add`); otherwise its
    explanation says why not."""
    term_added = term is not None and term.recommended
    recommended = {term.effect} if term_added else set()
    for c in accepted:  # in the order accepted, so that what each was found given is decided before it
        c.significant, c.role = True, MISSING_EFFECT
        if c.alternatives:
            c.explanation += f" — or {' or '.join(c.alternatives)}: these data cannot tell them apart (neither is " \
                             "significant given the other; data where they differ, another day, can)"
        # verified on held-out data (and trips, when there are several): what `fuelid identify --effects-from` adds
        warm_only = only_the_warm_refit_worse(c)  # the model identify builds decides instead (selection, 5)
        c.recommended = c.verification is not None and "error" not in c.verification \
            and (refit_verified(c) or warm_only)
        if c.verification is None:  # significant by its tests alone: what they found is no advice to add it
            not_recommended(c, f" — not verified (`fuelid diagnose --verify {n_verify}`): not recommended")
        elif not refit_verified(c) and not warm_only:
            not_recommended(c, why_refit_not_verified(c))
        elif c.recommended and (why := why_never_added(c, ds)) is not None:
            not_recommended(c, why)
        elif c.recommended and (missing := given_not_added(c, recommended)):
            not_recommended(c, f" — but it was found given {', '.join(missing)}, which is not added: not recommended")
        if c.recommended and c.refit is None and not term_added:  # the fuel delay, on the model as it is
            built.given(c)
        elif c.recommended and not built.add(c, min_drop_percent if warm_only else 0.0):
            # (the fuel delay: given the engine's term.) Where only the warm refit was worse, the built model must
            # show the relevance the refit could not: a smaller gain is a tie within the fits' reproducibility
            if c.refit is not None:
                c.refit["verified"] = False
            not_recommended(c, why_built_worse(built_record(c)["built"]))
        elif c.recommended and warm_only:
            c.refit["verified"] = True
            b = c.refit["built"]
            c.explanation += f" (forward selection's warm-started refit with it simulated these data worse, RMS " \
                             f"error {c.refit['rmse_without']:.3f} → {c.refit['rmse_with']:.3f}; the model " \
                             f"`fuelid identify --effects-from` builds with it simulates them at least " \
                             f"{b['min_gain_percent']:g} % better, {b['rmse_without']:.3f} → {b['rmse_with']:.3f})"
        if c.recommended and (missing := accepted_given_not_added(c, recommended)):
            c.explanation += f" (accepted given {', '.join(missing)}, not added; found and verified before that " \
                             f"given {', '.join(found_given_added(c, recommended))} alone)"
        if c.recommended:
            recommended.add(c.effect)


def _say_why_not(rows: list[Candidate], unconfirmed: list[Candidate], min_effect_percent: float,
                 min_drop_percent: float) -> None:
    """What the explanation of each candidate not named adds: why its verification did not confirm it, what explained
    it away, or that it explains too little; then it is read as evidence, not advice (`as_evidence`)."""
    for c in unconfirmed:
        if not c.significant:
            c.explanation += why_not_confirmed(c, min_drop_percent)
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


def _verdict(term: Candidate | None, accepted: list[Candidate], n_hidden: int, alpha: float, min_effect_percent: float,
             min_drop_percent: float) -> str:
    """The diagnosis's verdict: the engine map term (None: not named) and the missing effects accepted, or that none
    of the n_hidden hidden-effect candidates tested explains the residual."""
    said = [_said_with_drop(c) for c in accepted]
    engine = "" if term is None else f"Engine map: {term.explanation}. "
    if said:
        return engine + (f"Missing effect: {said[0]}." if len(said) == 1 else
                         f"Missing effects ({len(said)}): " + "; ".join(f"({k}) {t}" for k, t in enumerate(said, 1))
                         + ".")
    if term is None:
        return f"No significant candidate: none of the {n_hidden} candidate effects explains the residual " \
               f"(Holm-corrected, family-wise α = {alpha:g}, at least {min_effect_percent:g} % of the " \
               f"simulation error, and a held-out RMS error drop of at least {min_drop_percent:g} %); the model " \
               "is not missing any effect the bus reveals."
    return engine + f"No missing effect: given the engine map term, none of the {n_hidden} other candidate " \
                    f"effects explains the residual (Holm-corrected, family-wise α = {alpha:g}, at least " \
                    f"{min_effect_percent:g} % of the simulation error, and a held-out RMS error drop of at least " \
                    f"{min_drop_percent:g} %); beyond its map, the model is not missing any effect the bus reveals."


def _said_with_drop(c: Candidate) -> str:
    """c's explanation as the verdict says it: with the held-out RMS error drop adding it makes (`_added_drop`,
    where its entry kind says it), before the clause saying why it is not recommended, if one begins
    NOT_RECOMMENDED."""
    drop = _added_drop(c)
    if drop is None or not c.entry.drop_in_verdict:
        return c.explanation
    said, clause, why = c.explanation.partition(NOT_RECOMMENDED)
    return f"{said} (held-out RMS error {-drop:+.0f} % when added){clause}{why}"


def _added_drop(c: Candidate) -> float | None:
    """The held-out RMS error drop [%] adding c makes: on top of the effects accepted before it when it was
    selected given them, else on the model as it is."""
    cond = c.conditional or {}
    return cond["rmse_drop_percent"] if cond.get("rmse_drop_percent") is not None else c.rmse_drop_percent
