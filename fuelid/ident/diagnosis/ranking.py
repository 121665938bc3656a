"""Ranking the candidates and naming the missing effect: the tests of every candidate, Holm, verification of
the likeliest, and the sequential conditional check.

5. Sequential conditional check. Bus signals are dependent (a cab temperature follows the level shift a real
   effect leaves in the error). The confirmed candidates are taken in the order of their held-out drop
   (`_priority`; a generic bus signal's discounted by GENERIC_WEIGHT); each after the first is re-tested by the
   simulation-error test with the accepted candidates' columns among the nuisance columns and must still reject
   (Bonferroni over the candidates) and explain min_effect_percent, and, added on top of them, still lower the
   held-out RMS error by min_drop_percent, else it is "explained by" the first (`accept_sequentially`).

A candidate is `significant` — a missing effect the diagnosis names — when the Holm-corrected test rejects
AND it explains at least min_effect_percent (default 1 %) of the simulation error AND, when verified, the
linearised refit lowers the held-out RMS error by at least min_drop_percent (default 2 %) the way its physics
says AND (after the first) it survives the conditional check. The conjunction can only remove rejections, so
the family-wise false-alarm rate stays ≤ α. Significant candidates are listed first, in the order accepted;
then the rest by p-value. Measured on 20-minute simulated trips (benchmarks/bench_diagnose.py --acceptance):
1 of 70 data sets with nothing hidden (50 trips, 20 pairs of trips) names an effect; README gives the table per
hidden effect.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter

from fuelid.errors import InputError
from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.candidate import Candidate
from fuelid.ident.diagnosis.entries import ENTRIES
from fuelid.ident.diagnosis.explanation import as_evidence, contribution_on_grid, explain
from fuelid.ident.diagnosis.failures import where_it_fails
from fuelid.ident.diagnosis.run import Run, run_gradients
from fuelid.ident.diagnosis.statistics import holm, level_test, nuisance_basis, one_blas_thread
from fuelid.ident.diagnosis.verification import held_out, held_out_scores
from fuelid.ident.modeldata import at_operating_point
from fuelid.ident.modelrun import ModelRun, run_model
from fuelid.ident.polymodel import PolyModel
from fuelid.ident.validation import metrics

GENERIC_WEIGHT = 0.8  # a generic bus signal must explain 25 % more than a named effect to be accepted first


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

    def to_json(self) -> dict:
        """The diagnosis as `fuelid diagnose --json` prints it."""
        return {"model": self.model, "data": self.data, "compare": self.compare, "held_out": self.held_out,
                "where_it_fails": self.where_it_fails, "test": self.test,
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
    adj, sig = holm([c.p_value for c in rows], alpha) if rows else (np.zeros(0), np.zeros(0, bool))
    for c, a, s in zip(rows, adj, sig):
        c.p_holm = float(a)
        # p-values below ~1e-300 underflow; compare log p with Holm's log(alpha/m) bound in that case
        c.test_significant = bool(c.testable and (s or c.log10_p < math.log10(alpha / len(rows))))
    rows.sort(key=lambda c: (c.log10_p, -c.statistic))
    return rows + untested


def _confirmed(c: Candidate, min_drop_percent: float) -> bool:
    """Whether c's verification confirms it: the held-out RMS error falls by at least min_drop_percent (its entry
    kind's relevance), and the fuel moves the way the effect's physics says (Effect.sign: fuel cut on overrun
    falls, a regeneration adds fuel, the fuel signal lags). A candidate the refit cannot score stays as the tests
    found it."""
    v = c.verification
    if "error" in v:
        return True
    return c.entry.relevance(v) >= min_drop_percent and c.definition.sign * v["direction"] >= 0


def _priority(c: Candidate) -> float:
    """Order of acceptance: the held-out RMS error drop when verified, else the estimated drop; a generic bus
    signal's discounted by GENERIC_WEIGHT (a named physical effect is preferred to a bus signal that explains no
    more than it)."""
    v = c.verification
    drop = c.estimated_drop_percent if v is None or "error" in v else c.entry.relevance(v)
    return drop * (GENERIC_WEIGHT if ":" in c.effect else 1.0)  # generic ids are FORM:SIGNAL


def accept_sequentially(rows: list[Candidate], run: Run, model: PolyModel, ds, alpha: float,
                        min_effect_percent: float, min_drop_percent: float, m: int) -> list[Candidate]:
    """The candidates named as missing, in order (module docstring, 5): rows (in order of preference), each after
    the first re-tested conditional on those accepted before it and accepted when (a) the simulation-error test
    with their columns among the nuisance columns still rejects at alpha/m (Bonferroni over the m candidates
    tested) and still explains min_effect_percent, and (b) when verified, adding it on top of them still lowers
    the held-out RMS error by min_drop_percent. The others get `explained_by`. An entry kind that is not
    `retested` (the fuel-signal delay: the signal path, tested on its own reference model) is accepted as it is."""
    accepted, QG, resid = [], run.QG, run.r
    X_accepted, rmse_accepted = np.zeros((run.r.size, 0)), None  # verified columns accepted so far, their score
    for c in rows:
        if not c.entry.retested:
            accepted.append(c)
            continue
        if accepted:
            with one_blas_thread():
                test, left = level_test(resid, c.w, run.lens, QG)
            c.conditional = {"given": [a.effect for a in accepted], "p_value": test.p_value,
                             "estimated_drop_percent": 100.0 * (1.0 - left), "rmse_drop_percent": None}
            explained = test.log_p >= math.log(alpha / m) or 100.0 * (1.0 - left) < min_effect_percent
            if not explained and c.X is not None:
                if rmse_accepted is None:
                    rmse_accepted = held_out_scores(held_out(model, run, X_accepted), ds)["rmse"]
                rmse = held_out_scores(held_out(model, run, np.column_stack([X_accepted, c.X])), ds)["rmse"]
                drop = 100.0 * (1.0 - rmse / rmse_accepted)
                c.conditional["rmse_drop_percent"] = drop
                explained = drop < min_drop_percent
            if explained:
                c.explained_by = accepted[0].effect
                continue
        accepted.append(c)
        if c.X is not None:
            X_accepted, rmse_accepted = np.column_stack([X_accepted, c.X]), None
        with one_blas_thread():
            QG = nuisance_basis(np.column_stack([QG, c.w]))
        resid = run.r - QG @ (QG.T @ run.r)
    return accepted


def diagnose(model: PolyModel, ds, alpha: float = 0.05, n_verify: int = 10, min_effect_percent: float = 1.0,
             candidates=None, min_drop_percent: float = 2.0, effects=()) -> Diagnosis:
    """The whole diagnosis of `model` on dataset ds (ident.diagnosis and its modules).

    Returns a Diagnosis: model, data, compare (ident.validation.metrics of its run), held_out (held_out_scores of
    the model as it is, linearised refit without each block: rmse [output unit], cycle_fuel_error_percent; None
    when it cannot be scored), where_it_fails, test, candidates, verdict, run.
    Each candidate (best first) has: effect (id for `fuelid identify --effect`), name, form, signals (DBC
    names), spns, statistic (the larger LM of its two tests), df, p_value (Bonferroni over the two tests),
    p_holm, test_significant (Holm at alpha), estimated_drop_percent (share of the simulation error its
    least-squares fit explains), conditional (its re-test given the effects accepted before it), explained_by,
    rmse_drop_percent (held-out RMS simulation error drop with it, linearised refit, None unless verified),
    verification (held-out RMSE and cycle fuel errors without/with, direction), significant (a missing effect:
    when verified, a held-out drop ≥ min_drop_percent in the direction of its physics, then accepted by
    `accept_sequentially`), size, explanation, physics, tests. At most n_verify of the candidates that pass the
    tests and explain min_effect_percent are verified, by estimated drop. effects: effects the engineer defined
    (ident.effectfile), tested beside the built-in ones."""
    mrun = run_model(model, ds)
    run = run_gradients(mrun)
    rows = rank_candidates(model, ds, run, candidates, alpha, effects)
    testable = [c for c in rows if c.testable]
    try:  # the model as it is, scored on each block left out: the reference every verification is measured against
        base_ysim = held_out(model, run, np.zeros((run.r.size, 0)))["ysim"]
        base = held_out_scores({"y": run.y, "ysim": base_ysim}, ds)
    except (ValueError, np.linalg.LinAlgError):
        base = base_ysim = None
    eligible = sorted((c for c in testable if c.test_significant and c.estimated_drop_percent >= min_effect_percent),
                      key=lambda c: -_priority(c))
    if eligible and n_verify and base is None:
        raise InputError("the model cannot be scored on held-out blocks of these data")
    for c in eligible[:n_verify]:
        try:
            c.verification = v = c.entry.verify(c, model, ds, run, base, base_ysim)
            c.rmse_drop_percent = v["rmse_drop_percent"]
        except (ValueError, np.linalg.LinAlgError) as exc:
            c.verification = {"error": str(exc)}
    confirmed, unconfirmed = [], []
    for c in eligible:
        (confirmed if c.verification is None or _confirmed(c, min_drop_percent) else unconfirmed).append(c)
    confirmed.sort(key=lambda c: (c.verification is None, -_priority(c)))  # verified ones first
    accepted = accept_sequentially(confirmed, run, model, ds, alpha, min_effect_percent, min_drop_percent,
                                   max(len(testable), 1))
    for c in accepted:
        c.significant = True
    for c in unconfirmed:
        drop = c.entry.relevance(c.verification)
        if drop < min_drop_percent:
            c.explanation += f" — but adding it changes the held-out RMS error by {-drop:+.1f} " \
                             f"% (a fall of {min_drop_percent:g} % is needed): not confirmed"
        else:
            c.explanation += " — but the refit moves the fuel the other way than this effect would: not " \
                             "confirmed"
    for c in rows:
        if c.explained_by:
            c.explanation += f" — explained by {c.explained_by} (not significant given it)"
        elif c.test_significant and not c.significant and c.estimated_drop_percent < min_effect_percent:
            c.explanation += f" — statistically detectable, but it explains only " \
                             f"{c.estimated_drop_percent:.1f} % of the simulation error (< {min_effect_percent:g} %)"
    for c in rows:
        if c.testable and not c.significant:
            c.explanation = as_evidence(c)
    order = {id(c): k for k, c in enumerate(accepted)}
    rows.sort(key=lambda c: (not c.significant, order.get(id(c), 0), c.log10_p))
    testable = [c for c in rows if c.testable]
    best = rows[0] if rows and rows[0].significant else None
    if best:
        drop = "" if best.rmse_drop_percent is None or not best.entry.drop_in_verdict else \
            f" (held-out RMS error {-best.rmse_drop_percent:+.0f} % when added)"
        verdict = f"Missing effect: {best.explanation}{drop}."
    else:
        verdict = f"No significant candidate: none of the {len(testable)} candidate effects explains the residual " \
                  f"(Holm-corrected, family-wise α = {alpha:g}, at least {min_effect_percent:g} % of the " \
                  f"simulation error, and a held-out RMS error drop of at least {min_drop_percent:g} %); the model " \
                  "is not missing any effect the bus reveals."
    return Diagnosis(
        model={"effects": list(model.effects), "inputs": list(model.input_names), "Ts": model.Ts},
        data=ds.summary() if hasattr(ds, "summary") else {},
        compare={**metrics(mrun, ds), "unit": ds.output_unit},
        held_out=base,
        where_it_fails=where_it_fails(model, ds, run),
        test={"method": "score (LM) tests on the prediction errors and, GLS-whitened under the alternative, on "
                        "the simulation errors; Newey-West robust, chi2(k); Bonferroni over the two, Holm "
                        "step-down over all candidates; relevance, sequential conditional re-tests, and "
                        "a linearised refit scored leaving out one 60-s block at a time",
              "alpha": alpha, "min_effect_percent": min_effect_percent, "min_drop_percent": min_drop_percent,
              "candidates_tested": len(testable),
              "samples": int(run.e.size)},
        candidates=rows,
        verdict=verdict,
        run=mrun,
    )
