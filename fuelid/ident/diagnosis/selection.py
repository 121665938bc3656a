"""Forward selection with the one yardstick, and the engine map's status.

The engine map first. Its curvature (effects engine_map, power_nonlinearity) is part of the engine model, never a
hidden-effect candidate: when the base model has it, its status is IN_MODEL; otherwise engine_map is screened on its
own (at alpha) and, when significant, built and held to the yardstick: ADVISED when it passes (the engine model is
the advice, and the hidden effects are searched on the model with the map), NOT_NEEDED when not.

Then rounds r = 1, 2, …: every candidate still open is screened on the current base (Holm at alpha over them,
ident.diagnosis.screening); the significant ones that explain min_effect_percent are built, the max_builds smallest
p-values, and held to the yardstick (ident.diagnosis.yardstick) against the base; the one with the largest mean
paired gain among those that pass is RECOMMENDED and the base becomes the model refitted with it. A candidate that
passed the screening in an earlier round and no longer does is EXPLAINED_BY the one accepted since. The search stops
when nothing passes.
"""
from __future__ import annotations

import warnings

from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.candidate import CURVATURE, MAP_EFFECT, Candidate, EngineMap, MapStatus, Reason, Status
from fuelid.ident.diagnosis.run import run_gradients
from fuelid.ident.diagnosis.screening import delay_estimate, screen
from fuelid.ident.diagnosis.settings import Settings
from fuelid.ident.diagnosis.yardstick import BUILD_ERRORS, Folds, Scored, compare, refits
from fuelid.ident.identify import refit_with_effects
from fuelid.ident.modelrun import run_model
from fuelid.ident.polymodel import PolyModel

OPEN = (Status.NOT_SIGNIFICANT, Status.TOO_SMALL)  # statuses a later round may change


def candidate_effects(ds, defined=()) -> list[fx.Effect]:
    """The candidate family: the built-in effects, installed plug-ins', the engineer's (`defined`, ident.effectfile)
    and the generic forms of every other decoded bus signal (ident.effects.generic_effects); the first of each id."""
    seen, out = set(), []
    for e in [*fx.EFFECTS.values(), *fx.plugin_effects(), *defined, *fx.generic_effects(ds)]:
        if e.id not in seen:
            seen.add(e.id)
            out.append(e)
    return out


def _spec(c: Candidate) -> str:
    """What a build adds for c: its id, or for the fuel delay fuel_delay=τ̂ (screening.delay_estimate)."""
    return f"{c.effect}={delay_estimate(c.screening):.2f}" if c.definition.enters == "shift" else c.effect


def _refit(model: PolyModel, ds, spec: str, defined, settings: Settings):
    """The model refitted on all of ds with `spec` added (warm start) and its diagnosis Run."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        refit = refit_with_effects(model, ds, [spec], defined=defined, max_iter=settings.refit_max_iter)
    return refit, run_gradients(run_model(refit, ds))


def engine_map(model: PolyModel, ds, run, base: Scored | None, folds: Folds, settings: Settings):
    """(EngineMap, the base the hidden effects are searched on: (model, run, its Scored)) (module docstring)."""
    if set(CURVATURE) & {fx.parse_effect(e)[0] for e in model.effects}:
        return EngineMap(MapStatus.IN_MODEL), (model, run, base)
    s = screen([fx.EFFECTS[MAP_EFFECT]], model, ds, run, settings.alpha)[MAP_EFFECT]
    if s is None:
        return EngineMap(MapStatus.NOT_TESTABLE), (model, run, base)
    if not s.significant or s.explains_percent < settings.min_effect_percent or base is None:
        return EngineMap(MapStatus.NOT_NEEDED, s), (model, run, base)
    try:
        scored = refits(list(base.models), ds, folds, [MAP_EFFECT], settings)
        held = compare(base, scored, folds, settings)
        if not held.passes:
            return EngineMap(MapStatus.NOT_NEEDED, s, held), (model, run, base)
        return EngineMap(MapStatus.ADVISED, s, held), (*_refit(model, ds, MAP_EFFECT, (), settings), scored)
    except BUILD_ERRORS:
        return EngineMap(MapStatus.NOT_NEEDED, s), (model, run, base)


def select(candidates: list[Candidate], model: PolyModel, ds, run, base: Scored | None, folds: Folds,
           settings: Settings, defined=()) -> list[Candidate]:
    """Forward selection (module docstring) over `candidates` (their status set here) from `model` (run: its Run,
    base: its fold refits, None when they failed); returns those recommended, in the order accepted."""
    pool = [c for c in candidates if c.status is not Status.ALREADY_IN_MODEL]
    accepted: list[Candidate] = []
    passed_before: set[str] = set()
    built: dict[str, Scored] = {}  # each candidate's fold models in this round
    for rnd in range(1, settings.max_rounds + 1):
        found = screen([c.definition for c in pool], model, ds, run, settings.alpha)
        eligible = []
        for c in list(pool):
            c.screening, c.round = found[c.effect], rnd
            if c.effect in passed_before and (c.screening is None or not c.screening.significant):
                c.decide(Status.EXPLAINED_BY, explained_by=accepted[-1].effect)
                pool.remove(c)
            elif c.screening is None:
                c.decide(Status.NOT_TESTABLE)
                pool.remove(c)
            elif not c.screening.significant:
                c.decide(Status.NOT_SIGNIFICANT)
            elif c.screening.explains_percent < settings.min_effect_percent:
                c.decide(Status.TOO_SMALL)
            else:
                passed_before.add(c.effect)
                eligible.append(c)
        eligible.sort(key=lambda c: c.screening.log10_p)
        passing = []
        for k, c in enumerate(eligible):
            if k >= settings.max_builds or base is None:
                c.decide(Status.NAMED_NOT_RECOMMENDED, Reason.NOT_BUILT if base is not None else Reason.BUILD_FAILED)
                continue
            c.spec = _spec(c)
            try:
                built[c.effect] = refits(list(base.models), ds, folds, [c.spec], settings, defined)
            except BUILD_ERRORS:
                c.decide(Status.NAMED_NOT_RECOMMENDED, Reason.BUILD_FAILED)
                pool.remove(c)
                continue
            c.held_out = compare(base, built[c.effect], folds, settings)
            if c.held_out.passes:
                passing.append(c)
            else:
                c.decide(Status.NAMED_NOT_RECOMMENDED, Reason.NO_HELD_OUT_GAIN)
                pool.remove(c)
        if not passing:
            break
        best = max(passing, key=lambda c: c.held_out.mean_gain)
        try:
            model, run = _refit(model, ds, best.spec, defined, settings)
        except BUILD_ERRORS:
            best.decide(Status.NAMED_NOT_RECOMMENDED, Reason.BUILD_FAILED)
            break
        best.decide(Status.RECOMMENDED)
        base = built[best.effect]
        accepted.append(best)
        pool.remove(best)
        for c in passing:
            if c is not best:  # re-screened on the new base next round, unless the rounds end here
                c.decide(Status.NAMED_NOT_RECOMMENDED, Reason.SELECTION_STOPPED)
    return accepted
