"""`diagnose`: the model run, where it fails, the folds and the base model's refits (the ones the candidates are
held to, and the held-out figures reported), the engine map, forward selection, and the Diagnosis
(ident.diagnosis.render)."""
from __future__ import annotations

from fuelid.blas import in_one_blas_thread
from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.candidate import CURVATURE, MAP_EFFECT, Candidate, Status, carried_by_engine_model
from fuelid.ident.diagnosis.failures import where_it_fails
from fuelid.ident.diagnosis.render import STATUS_ORDER, Diagnosis
from fuelid.ident.diagnosis.run import run_gradients
from fuelid.ident.diagnosis.selection import base_refits, candidate_effects, select
from fuelid.ident.diagnosis.settings import Settings
from fuelid.ident.diagnosis.yardstick import BUILD_ERRORS, held_out_summary, make_folds
from fuelid.ident.identify import FitMemo
from fuelid.ident.modelrun import run_model
from fuelid.ident.polymodel import PolyModel
from fuelid.ident.validation import metrics


@in_one_blas_thread  # narrow N × d products: BLAS threads cost more than they save (fuelid.blas)
def diagnose(model: PolyModel, ds, settings: Settings = Settings(), effects=(), candidates=None,
             progress=None) -> Diagnosis:
    """The diagnosis of `model` on dataset ds (docs/explanation/diagnosis.md). effects: effects the engineer defined
    (ident.effectfile), tested beside the built-in ones; candidates: the effects to test instead of every one
    (`selection.candidate_effects`); progress: called with what is built (`selection.Progress`) before each model
    the yardstick builds, for a progress bar. Runs in this process. Raises InputError when no segment of the data is
    long enough to test."""
    progress = progress or (lambda step: None)
    mrun = run_model(model, ds)
    mrun.require_tested()
    run = run_gradients(mrun)
    folds = make_folds(ds, settings)
    memo = FitMemo()
    try:
        base = base_refits(model, ds, folds, settings, effects, memo, progress)
    except BUILD_ERRORS:
        base = None  # nothing can be built: whatever the screening names is not recommended (BUILD_FAILED)
    held_out = None if base is None else held_out_summary(base, ds)
    family = candidate_effects(ds, effects) if candidates is None else list(candidates)
    included = {fx.parse_effect(e)[0] for e in model.effects}
    rows = [Candidate(e, Status.ALREADY_IN_MODEL if e.id in included else Status.NOT_TESTABLE)
            for e in family if e.id not in CURVATURE]
    if MAP_EFFECT in included:
        carried_by_engine_model(rows)
    accepted, emap = select(rows, model, ds, run, base, folds, settings, effects, memo, progress)
    order = {id(c): k for k, c in enumerate(accepted)}
    rows.sort(key=lambda c: (order.get(id(c), len(order)), STATUS_ORDER.index(c.status),
                             c.screening.log10_p if c.screening else 0.0))
    return Diagnosis(
        model={"effects": list(model.effects), "inputs": list(model.input_names), "Ts": model.Ts},
        data=ds.summary() if hasattr(ds, "summary") else {},
        compare={**metrics(mrun, ds), "unit": ds.output_unit},
        held_out=held_out, where_it_fails=where_it_fails(model, ds, run), candidates=rows, engine_map=emap,
        settings=settings, samples=int(run.e.size), run=mrun)
