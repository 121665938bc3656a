"""Ranking the candidates: both tests of every candidate effect (ident.diagnosis.statistics, 1–3), each as its entry
kind tests it (ident.diagnosis.entries), Holm over the hidden-effect family — the engine map term is tested first,
alone, at α (ident.diagnosis.verdict, 0) — and a candidate's verification (ident.diagnosis.verification, 4), kept on it.
What is then named and recommended: ident.diagnosis.recommendation, .selection and .verdict.
"""
from __future__ import annotations

import math

import numpy as np

from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.candidate import Candidate, Evidence
from fuelid.ident.diagnosis.entries import ENTRIES, projected_columns
from fuelid.ident.diagnosis.explanation import contribution_on_grid, explain
from fuelid.ident.diagnosis.run import Run
from fuelid.ident.diagnosis.statistics import holm
from fuelid.ident.diagnosis.verification import Baseline
from fuelid.ident.modeldata import at_operating_point
from fuelid.ident.polymodel import PolyModel

MAP_TERM, PRODUCT_TERM = "engine_map", "power_nonlinearity"  # the engine curvature: map, product term (verdict)
PROJECTED_TOGETHER = 2 ** 20  # numbers (samples × columns) of the candidates' columns projected in one product
#   (entries.projected_columns): 8 MB a basis however long the data; 58 columns on a 90-min trip, where a wider
#   product gains nothing


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
    for effect, found in _tests(model, dsm, run, [e for e in candidates if e.id not in included]):
        if found is None:
            untested.append(Candidate(effect.id, effect.name, effect.form, list(effect.signals), list(effect.spns),
                                      effect.physics, "not testable: its bus signals are not in the data"))
        else:
            rows.append(_tested(effect, ENTRIES[effect.enters], found, model, dsm, run))
    family = [c for c in rows if c.effect != MAP_TERM]  # the map term is tested first, alone, at alpha (verdict, 0)
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


def _tests(model: PolyModel, dsm, run: Run, effects: list[fx.Effect]):
    """(effect, what its entry kind's tests found: Evidence, None when its signals are not logged) for each of
    `effects`, in order, on `model` and its run on dsm (the data at its operating point); the columns of consecutive
    candidates projected in one product per basis (entries.projected_columns), up to PROJECTED_TOGETHER numbers."""
    group, size = [], 0
    for k, effect in enumerate(effects):
        cols = ENTRIES[effect.enters].columns(model, dsm, run, effect)
        group.append((effect, cols))
        size += 0 if cols is None else cols.psi.size
        if size >= PROJECTED_TOGETHER or k == len(effects) - 1:
            for (e, c), projected in zip(group, projected_columns(run, [c for _, c in group])):
                yield e, ENTRIES[e.enters].test(model, dsm, run, e, c, projected)
            group, size = [], 0


def _tested(effect: fx.Effect, entry, found: Evidence, model: PolyModel, dsm, run: Run) -> Candidate:
    """The candidate of `effect` whose tests (`entry`'s, on `model` and its run on dsm, the data at its operating
    point) found `found`, explained."""
    tests = found.tests
    log_p = min(0.0, math.log(len(tests)) + min(t.log_p for t in tests.values()))  # Bonferroni over its tests
    df = max(t.df for t in tests.values())
    gains = found.coef.reshape(len(effect.lags), -1).sum(axis=0)
    text, size = explain(entry, effect, found.reg, contribution_on_grid(effect.form, found.x, found.coef, run),
                         gains, [model], dsm, run)
    return Candidate(
        effect.id, effect.name, effect.form, list(effect.signals), list(effect.spns), effect.physics, text,
        spec=effect.id, statistic=max(t.statistic for t in tests.values()), df=df, p_value=math.exp(log_p),
        log10_p=log_p / math.log(10), testable=df > 0,
        tests={name: {"statistic": t.statistic, "df": t.df, "p_value": t.p_value} for name, t in tests.items()},
        estimated_drop_percent=100.0 * (1.0 - found.left), size=size, definition=effect, entry=entry,
        reg=found.reg, x=found.x, w=found.w, ref=found.ref)


def verify(c: Candidate, model: PolyModel, ds, run: Run, base: Baseline) -> None:
    """c's verification against the model as it is (base: its Baseline; the entry kind's), kept on c; an error
    recorded, not raised."""
    try:
        c.verification = v = c.entry.verify(c, model, ds, run, base)
        c.rmse_drop_percent = v["rmse_drop_percent"]
    except (ValueError, np.linalg.LinAlgError) as exc:
        c.verification = {"error": str(exc)}
