"""Forward selection with the one yardstick; the engine map as a term of its own.

Rounds r = 1, 2, …: every candidate still open is screened on the current base (Holm at alpha over them,
ident.diagnosis.screening); the significant ones that explain min_effect_percent are built, the max_builds that
explain the largest share of the simulation error, and held to the yardstick (ident.diagnosis.yardstick) against the
base (and, when its floors are met but its block gains' own spread hides the gain, against its placebo: the same
build on its bus signals shifted by half the data). One that passes but whose fold models fit it against the
direction its physics states, beyond their spread (ident.diagnosis.size.against_physics), is NAMED_NOT_RECOMMENDED
(AGAINST_ITS_PHYSICS): what it gains is not that effect. Of the others that pass, the one with the largest mean
paired gain is accepted (an effect with stated physics — catalogued or the engineer's — before a generic form of a
bus signal, which can stand in for it on one trip) — RECOMMENDED — and the base becomes the model refitted with it.
The others that pass and whose models neither beat nor are beaten by the accepted one's, by the same yardstick, are
its `alternatives`: these data cannot tell them apart (two temperatures that rise together over a trip), and the
engineer is told so.

Forward selection's blind spot is two effects that mask each other: the model with either one alone fits it to data
the other distorts, and neither passes although both together would. So when nothing passes in a round, each pair of
the candidates with stated physics built in it is built: a pair whose model passes the yardstick against the base and
against each member's model alone (each adds beyond the other, in the direction its physics states) is accepted
whole, the one with the largest mean gain over the base, both RECOMMENDED with `together_with` the other and, as
evidence, the gain beyond the other's model. Generic forms are left out of pairs: a pair of stand-ins is not advice.
A candidate
on a bus signal that engine speed and torque determine (Settings.min_share_beyond_inputs) is
NAMED_NOT_RECOMMENDED (DETERMINED_BY_INPUTS) without a build: it can only stand in for the engine's map. A candidate
that passed the screening (significant and relevant) in an earlier round and no longer does is EXPLAINED_BY the one
accepted since. The search stops when nothing passes; each recommended effect is then sized in the model with all of
them (ident.diagnosis.size).

The engine's curvature (effects engine_map, power_nonlinearity) is part of the engine model, never a hidden-effect
candidate: when the base model has it its status is IN_MODEL. Otherwise, in every round until it is accepted,
engine_map is screened on its own (at alpha: a family of its own, outside the hidden effects' Holm) and, when
significant and relevant, built and held to the same yardstick beside the candidates. When it passes it is accepted
before any candidate of its round, being part of the engine model the hidden effects are searched on (a signal that
speed and torque determine would otherwise stand in for the map); its status is ADVISED — the engine model is the
advice. Re-tested every round, a map whose gain a large hidden effect (a regeneration) masked at first is found once
that effect is accepted; never accepted, NOT_NEEDED. The engine model also carries the injection cut (its map is 0
fuel at and below zero torque): on an engine-model base, and once the map is accepted, overrun_cutoff
(candidate.IN_ENGINE_MODEL) is ALREADY_IN_MODEL.
"""
from __future__ import annotations

import dataclasses
import functools
import itertools
import warnings

import numpy as np

from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.candidate import (CURVATURE, MAP_EFFECT, Candidate, EngineMap, HeldOut, MapStatus, Reason,
                                              Status, carried_by_engine_model)
from fuelid.ident.diagnosis.run import run_gradients
from fuelid.ident.diagnosis.screening import delay_estimate, screen
from fuelid.ident.diagnosis.settings import Settings
from fuelid.ident.diagnosis.size import EffectSize, against_physics, effect_size
from fuelid.ident.diagnosis.yardstick import BUILD_ERRORS, Folds, Scored, compare, placebo, refits
from fuelid.ident.effectfile import effects_of_model
from fuelid.ident.identify import FitMemo, identify_model, refit_with_effects
from fuelid.ident.modelrun import run_model
from fuelid.ident.polymodel import PolyModel, Structure
from fuelid.parallel import side_by_side

OPEN = (Status.NOT_SIGNIFICANT, Status.TOO_SMALL)  # statuses a later round may change


@dataclasses.dataclass(frozen=True)
class Progress:
    """What the yardstick builds next, for a progress bar: the round (0: the base model's refits), the effects added
    to the base (none for the base), and whether it is a placebo (the effects on their bus signals shifted)."""

    round: int
    effects: tuple[str, ...] = ()
    placebo: bool = False

    def __str__(self) -> str:
        built = " + ".join(self.effects) or "the base model"
        return f"round {self.round}: {built}{' (placebo)' if self.placebo else ''}" if self.round else built


def candidate_effects(ds, defined=()) -> list[fx.Effect]:
    """The candidate family: the built-in effects, installed plug-ins', the engineer's (`defined`, ident.effectfile)
    and the generic forms of every other decoded bus signal (ident.effects.generic_effects); the first of each id."""
    seen, out = set(), []
    for e in [*fx.EFFECTS.values(), *fx.plugin_effects(), *defined, *fx.generic_effects(ds)]:
        if e.id not in seen:
            seen.add(e.id)
            out.append(e)
    return out


def _generic(c: Candidate) -> bool:
    """A generic form of a bus signal (ident.effects.generic_effects: ids FORM:MESSAGE.Signal), whose physics nobody
    stated: of the candidates that pass in one round, a catalogued or engineer-defined one is accepted before it."""
    return ":" in c.effect


def _determined(ds, c: Candidate, settings: Settings) -> bool:
    """Whether engine speed and torque determine the bus signal of generic candidate c (Settings.min_share_beyond_inputs)."""
    return fx.share_beyond_inputs(ds, c.definition.signals[0]) < settings.min_share_beyond_inputs


def _spec(c: Candidate) -> str:
    """What a build adds for c: its id, or for the fuel delay fuel_delay=τ̂ (screening.delay_estimate)."""
    return f"{c.effect}={delay_estimate(c.screening):.2f}" if c.definition.enters == "shift" else c.effect


def _specs(model: PolyModel) -> list[str]:
    """The model's own effects as identify_model takes them again: a shift with the value it was fitted with."""
    params = model.info.get("effect_parameters") or {}
    return [f"{e}={params[e]}" if e in params and e in fx.EFFECTS and fx.EFFECTS[e].enters == "shift" else e
            for e in model.effects]


def built(model: PolyModel, ds, specs: list[str], defined, memo: FitMemo) -> PolyModel:
    """The model `fuelid identify` builds on all of ds with the model's effects and `specs` (ident.identify.
    identify_model: PEM from its initialisation and from the linear model with the effects added in turn, one kept;
    with the engine map, the map and the dynamics jointly; the fits of earlier builds on these data, the linear
    model and the stages the builds share, served by `memo`): exactly the model `--effects-from` will add, so that
    what the yardstick judges is what the engineer gets."""
    s = model.structure
    structure = Structure(nb=s.nb[:2], nf=s.nf[:2], nk=model.nk[:2], nc=s.nc, nd=s.nd, na=s.na)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return identify_model(ds, structure, _specs(model) + specs,
                              defined=tuple(effects_of_model(model)) + tuple(defined), memo=memo)


def refitted(model: PolyModel, ds, specs: list[str], defined, memo: FitMemo) -> PolyModel:
    """The base of the next round once `specs` are accepted, on all of ds: the model refitted by PEM from itself with
    the effects' coefficients at zero (ident.identify.refit_with_effects)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return refit_with_effects(model, ds, specs, defined=defined, memo=memo)


def _fold_sizes(c: Candidate, scored: Scored, ds) -> list[EffectSize]:
    """c's size (ident.diagnosis.size) in each of its fold models (fitted without that fold, run over all of ds)."""
    return [z for z in (effect_size(m, ds, c.definition) for m in scored.models) if z is not None]


def _median(sizes: list[EffectSize]) -> EffectSize | None:
    """The sizes' median, figure by figure; None without any."""
    if not sizes:
        return None
    figures = ("value", "relative", "percent", "rms", "baseline")
    median = {f: float(np.median([getattr(z, f) for z in sizes])) for f in figures}
    return dataclasses.replace(sizes[0], **median)


def _joint(model: PolyModel) -> bool:
    """Whether the model has a part a PEM refit holds fixed (the engine map, fitted jointly with the dynamics)."""
    return MAP_EFFECT in {fx.parse_effect(e)[0] for e in model.effects}


def base_refits(model: PolyModel, ds, folds: Folds, settings: Settings, defined, memo: FitMemo,
                progress) -> Scored:
    """The fold refits the candidates are held to: on an engine-model base, of the model `fuelid identify` builds on
    ds with the model's effects (`built`: the candidates are built so too); otherwise of `model` itself; progress is
    told `Progress(0)` first. Raises BUILD_ERRORS."""
    progress(Progress(0))
    start = built(model, ds, [], defined, memo) if _joint(model) else model
    return refits(start, ds, folds, [], settings, defined)


@dataclasses.dataclass(frozen=True)
class _Judged:
    """A candidate held to the yardstick (`_Builds._judged`): why it failed (None: it passes), and its size."""

    failed: Reason | None
    size: EffectSize | None


def _with_specs(model: PolyModel, base_models, ds, specs: list[str], folds: Folds, settings: Settings, defined,
                memo: FitMemo) -> tuple[tuple[Scored, PolyModel | None] | Exception, FitMemo]:
    """((the fold refits, the model on all of ds or None), memo) of the base `model` with `specs` on ds: on an
    engine-model base the candidate's model as identify builds it (`built`) and its fold refits; else nested in the
    base's fold models (base_models, each refitted with the candidate's coefficients at zero). A BUILD_ERRORS
    exception comes back in place of the pair: a pure call for fuelid.parallel, whose memo (a copy, in a worker)
    comes back with the fits made."""
    try:
        if _joint(model):
            whole = built(model, ds, specs, defined, memo)
            return (refits(whole, ds, folds, [], settings, defined), whole), memo
        return (refits(list(base_models), ds, folds, specs, settings, defined), None), memo
    except BUILD_ERRORS as exc:
        return exc, memo


class _Builds:
    """One round's builds against its base: each candidate's model (on an engine-model base, as `fuelid identify`
    builds it on all of ds: `built`; else nested in the base's fold models), its fold refits, and the yardstick.
    The builds of a round are independent of each other: they run side by side (fuelid.parallel)."""

    def __init__(self, model: PolyModel, base: Scored, ds, folds: Folds, settings: Settings, defined, memo: FitMemo,
                 rnd: int, progress):
        self.model, self.base, self.ds, self.folds, self.settings = model, base, ds, folds, settings
        self.defined, self.memo, self.round, self.progress = defined, memo, rnd, progress
        self.tried: set[str] = set()
        self.scored: dict[str, Scored] = {}  # a candidate's fold refits (each without its fold)
        self.whole: dict[str, PolyModel] = {}  # its model on all of ds (an engine-model base)

    def _built(self, wanted: list[tuple[list[str], object]]) -> list[tuple[Scored, PolyModel | None] | Exception]:
        """`_with_specs` of the base with each (specs, ds) of `wanted` (ds None: the round's; else a placebo's),
        side by side, progress told of each first: (the fold refits, the model on all of ds or None) or the
        BUILD_ERRORS exception its build raised."""
        for specs, ds in wanted:
            self.progress(Progress(self.round, tuple(specs), placebo=ds is not None))
        calls = [functools.partial(_with_specs, self.model, self.base.models, self.ds if ds is None else ds,
                                   list(specs), self.folds, self.settings, self.defined, self.memo)
                 for specs, ds in wanted]
        out = []
        for result, memo in side_by_side(calls):
            self.memo.update(memo)
            out.append(result)
        return out

    def held(self, candidates: list[Candidate]) -> list[Candidate]:
        """Builds each of `candidates`, holds it to the yardstick against the base (and, when its floors are met but
        not the margin, against its placebo: ident.diagnosis.yardstick.placebo, c built as it is on its bus signals
        shifted by half the data, when c has one) and decides it unless it passes; those that pass, in order."""
        for c in candidates:
            self.tried.add(c.effect)
            c.spec = _spec(c)
        held: dict[int, HeldOut] = {}
        for k, (c, made) in enumerate(zip(candidates, self._built([([c.spec], None) for c in candidates]))):
            if isinstance(made, Exception):
                c.decide(Status.NAMED_NOT_RECOMMENDED, Reason.BUILD_FAILED)
                continue
            self.scored[c.effect], whole = made
            if whole is not None:
                self.whole[c.effect] = whole
            held[k] = compare(self.base, made[0], self.folds, self.settings)
        # a gain in few blocks decides its own spread: the placebo's
        shifted = {k: placebo(self.ds, candidates[k].definition.signals) for k, h in held.items()
                   if not h.passes and h.floors_met}
        shifted = {k: d for k, d in shifted.items() if d is not None}
        for k, made in zip(shifted, self._built([([candidates[k].spec], d) for k, d in shifted.items()])):
            if not isinstance(made, Exception):
                held[k] = compare(self.base, self.scored[candidates[k].effect], self.folds, self.settings, made[0])
        return [c for k, c in enumerate(candidates) if k in held and self._decided(
            c, held[k], self._judged(c, held[k], self.scored[c.effect], self.whole.get(c.effect)))]

    def _judged(self, c: Candidate, held_out: HeldOut, scored: Scored, whole: PolyModel | None) -> _Judged:
        """c judged from a model built with it (held_out: against the model without it, scored: its fold refits):
        it fails without a held-out gain, or when its fold models fit it against the direction its physics states."""
        sized = held_out.passes and c.effect != MAP_EFFECT  # its size: evidence once it helps
        # the fold models' sizes: the physics' direction judged on their spread, and a linear base's size
        fold_sizes = _fold_sizes(c, scored, self.ds) if sized and (c.definition.sign or whole is None) else []
        size = None if not sized else (effect_size(whole, self.ds, c.definition) if whole is not None
                                       else _median(fold_sizes))
        if not held_out.passes:  # open: a later round's base (without what masked it) may show its gain
            return _Judged(Reason.NO_HELD_OUT_GAIN, size)
        if against_physics(c.definition, fold_sizes, self.settings.margin_se):  # open: another base may differ
            return _Judged(Reason.AGAINST_ITS_PHYSICS, size)
        return _Judged(None, size)

    @staticmethod
    def _decided(c: Candidate, held_out: HeldOut, judged: _Judged) -> bool:
        """Records c's evidence and decides it NAMED_NOT_RECOMMENDED for the reason it failed; whether it passed."""
        c.held_out, c.size = held_out, judged.size
        if judged.failed is not None:
            c.decide(Status.NAMED_NOT_RECOMMENDED, judged.failed)
            return False
        return True

    def alternatives(self, best: Candidate, passing: list[Candidate]) -> tuple[str, ...]:
        """The others of `passing` (built this round, each passing) that these data cannot tell from best: neither's
        fold refits pass the yardstick against the other's."""
        def beats(a: Candidate, b: Candidate) -> bool:
            return compare(self.scored[b.effect], self.scored[a.effect], self.folds, self.settings).passes

        return tuple(c.effect for c in passing if c is not best and not beats(best, c) and not beats(c, best))

    def passing_pair(self, single: list[Candidate]) -> tuple[list[Candidate], PolyModel | None, Scored] | None:
        """Of the pairs of `single` (built alone this round, none passing), the one whose model passes the
        yardstick against the base and against each member's model alone (each adds beyond the other), in the
        direction each one's physics states, with the largest mean gain over the base: ([a, b] with their
        evidence beyond each other, the pair's model on all of ds or None, its fold refits); None when none does."""
        best = None
        pairs = list(itertools.combinations(single, 2))
        for (a, b), made in zip(pairs, self._built([([a.spec, b.spec], None) for a, b in pairs])):
            if isinstance(made, Exception):
                continue
            scored, whole = made
            gain = compare(self.base, scored, self.folds, self.settings)
            if not gain.passes or (best is not None and gain.mean_gain <= best[0].mean_gain):
                continue
            beyond = {a: compare(self.scored[b.effect], scored, self.folds, self.settings),
                      b: compare(self.scored[a.effect], scored, self.folds, self.settings)}
            judged = {c: self._judged(c, h, scored, whole) for c, h in beyond.items()}
            if all(j.failed is None for j in judged.values()):
                best = (gain, beyond, judged, scored, whole)
        if best is None:
            return None
        _, beyond, judged, scored, whole = best
        (a, b) = beyond
        for c, other in ((a, b), (b, a)):
            self._decided(c, beyond[c], judged[c])
            c.together_with = other.effect
        return [a, b], whole, scored


def select(candidates: list[Candidate], model: PolyModel, ds, run, base: Scored | None, folds: Folds,
           settings: Settings, defined, memo: FitMemo, progress) -> tuple[list[Candidate], EngineMap]:
    """Forward selection (module docstring) over `candidates` (their status set here) from `model` (run: its Run,
    base: `base_refits`, None when they failed; defined: the engineer's effects; memo: the FitMemo base_refits used,
    which the builds share; progress: told each build, `Progress`); returns (those recommended in the order
    accepted, the engine map's status)."""
    pool = [c for c in candidates if c.status is not Status.ALREADY_IN_MODEL]
    in_model = bool(set(CURVATURE) & {fx.parse_effect(e)[0] for e in model.effects})
    term = None if in_model else Candidate(fx.EFFECTS[MAP_EFFECT])  # the engine map, while not accepted
    accepted: list[Candidate] = []
    passed_before: set[str] = set()
    for rnd in range(1, settings.max_rounds + 1):
        found = screen([c.definition for c in pool], model, ds, run, settings.alpha)
        if term is not None:
            found.update(screen([term.definition], model, ds, run, settings.alpha))
        eligible = []
        for c in list(pool) + ([term] if term is not None else []):
            c.screening, c.round = found[c.effect], rnd
            relevant = c.screening is not None and c.screening.significant \
                and c.screening.explains_percent >= settings.min_effect_percent
            if c.effect in passed_before and not relevant:
                c.decide(Status.EXPLAINED_BY, explained_by=accepted[-1].effect)
                if c is not term:
                    pool.remove(c)
            elif c.screening is None:
                c.decide(Status.NOT_TESTABLE)
                if c is not term:
                    pool.remove(c)
            elif not c.screening.significant:
                c.decide(Status.NOT_SIGNIFICANT)
            elif not relevant:
                c.decide(Status.TOO_SMALL)
            elif _generic(c) and c is not term and _determined(ds, c, settings):
                c.decide(Status.NAMED_NOT_RECOMMENDED, Reason.DETERMINED_BY_INPUTS)
                pool.remove(c)
            else:
                passed_before.add(c.effect)
                eligible.append(c)
        # by the share of the simulation error each explains: on long data every p-value underflows toward 0, and the
        # smallest ones go to signals that track the operating point, not to the largest effect
        eligible.sort(key=lambda c: (c is not term, -c.screening.explains_percent, c.screening.log10_p))
        if base is None:
            for c in eligible:
                c.decide(Status.NAMED_NOT_RECOMMENDED, Reason.BUILD_FAILED)
            break
        builds = _Builds(model, base, ds, folds, settings, defined, memo, rnd, progress)
        passing = builds.held(eligible[:settings.max_builds + (term in eligible)])
        for c in eligible:
            if c.effect not in builds.tried:
                c.decide(Status.NAMED_NOT_RECOMMENDED, Reason.NOT_BUILT)
            elif c.reason is Reason.BUILD_FAILED and c is not term:
                pool.remove(c)
        if passing:
            best = term if term in passing else max(passing, key=lambda c: (not _generic(c), c.held_out.mean_gain))
            chosen, whole, scored = [best], builds.whole.get(best.effect), builds.scored[best.effect]
        else:
            # forward selection's blind spot, effects that mask each other (module docstring)
            pair = builds.passing_pair([c for c in eligible if c.effect in builds.scored and c is not term
                                        and not _generic(c)])
            if pair is None:
                break
            chosen, whole, scored = pair
        try:
            model = (built(model, ds, [term.spec], defined, memo) if term in chosen else whole if whole is not None
                     else refitted(model, ds, [c.spec for c in chosen], defined, memo))
            run = run_gradients(run_model(model, ds))
        except BUILD_ERRORS:
            for c in chosen:
                c.decide(Status.NAMED_NOT_RECOMMENDED, Reason.BUILD_FAILED)
            break
        base = scored
        for c in chosen:
            c.decide(Status.RECOMMENDED)
            accepted.append(c)
        if passing and term not in chosen:  # accepted alone: the others that pass which these data cannot tell from it
            chosen[0].alternatives = builds.alternatives(chosen[0], passing)
        for c in passing:
            if c not in chosen:  # re-screened on the new base next round, unless the rounds end here
                c.decide(Status.NAMED_NOT_RECOMMENDED, Reason.SELECTION_STOPPED)
        if term in chosen:  # the engine model carries what IN_ENGINE_MODEL lists: no longer a candidate
            term = None
            for c in carried_by_engine_model(pool):
                pool.remove(c)
        else:
            for c in chosen:
                pool.remove(c)
    recommended = [c for c in accepted if c.effect != MAP_EFFECT]
    ids = {c.effect for c in recommended}
    for c in recommended:  # sized in the model with everything recommended: one accepted later may have masked it
        c.size = effect_size(model, ds, c.definition) or c.size
        c.alternatives = tuple(a for a in c.alternatives if a not in ids)  # one accepted later adds beyond c
    return recommended, _map_status(in_model, accepted, term)


def _map_status(in_model: bool, accepted: list[Candidate], term: Candidate | None) -> EngineMap:
    """The engine map's status from its term: accepted (ADVISED, with the evidence it was accepted on), still open
    (NOT_NEEDED, or NOT_TESTABLE when it could not be screened) or in the model."""
    if in_model:
        return EngineMap(MapStatus.IN_MODEL)
    advised = next((c for c in accepted if c.effect == MAP_EFFECT), None)
    if advised is not None:
        return EngineMap(MapStatus.ADVISED, advised.screening, advised.held_out)
    status = MapStatus.NOT_TESTABLE if term.screening is None else MapStatus.NOT_NEEDED
    return EngineMap(status, term.screening, term.held_out)
