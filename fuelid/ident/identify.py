"""One offline identification of a fuel model from a Dataset: the code path shared by `fuelid identify` and the
fleet's per-truck jobs (fleet.jobs), so a model identified by the service is the one the command would give.

Steps: the effects' extra inputs (ident.modeldata.apply_effects; a fuel delay asked for without its value
estimated by seed 2's sweep with the model itself, `estimate_fuel_delay`) are appended to engine speed and torque, the
valid stretches of at least `min_segment_s` are taken, the model is estimated by prediction-error minimisation
(ident.pem.pem) and its validation metrics on the whole dataset (ident.validation.evaluate) are stored in it.
"""
from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from fuelid.errors import FuelidError
from fuelid.ident.fueldelay import shift_signal, sweep_fuel_shift
from fuelid.ident.modeldata import EffectInputs, apply_effects
from fuelid.ident.pem import pem
from fuelid.ident.polymodel import PolyModel, Structure, simulate
from fuelid.ident.validation import evaluate, rmse


def estimate_fuel_delay(ds, u, structure, shifts_s=None) -> dict:
    """Seed 2's sweep with the model itself: for each advance τ [s] the fuel is shifted, the model of `structure`
    on inputs u (N × m) refitted by PEM (warm-started from the fit at τ = 0) on the valid segments, and its
    simulation RMSE [fuel unit] taken; `sweep_fuel_shift` picks τ."""
    segs = ds.segments()
    idx = np.concatenate([np.arange(s.start, s.stop) for s in segs])
    u0 = np.r_[ds.u0, np.zeros(u.shape[1] - 2)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        base = pem(u[idx], ds.y[idx], structure, ds.Ts, u0=u0, y0=ds.y0)

        def score(tau):
            y = shift_signal(ds.y, tau / ds.Ts, segs)[idx]
            m = pem(u[idx], y, structure, ds.Ts, init=base, u0=u0, y0=ds.y0, max_iter=20)
            return rmse(y, simulate(m, u[idx]))

        return sweep_fuel_shift(score, shifts_s)


def effect_inputs(ds, effects, structure: Structure) -> EffectInputs:
    """apply_effects for a fit of `structure` (speed, torque inputs) with `effects`; a fuel delay asked for
    without its value is estimated by `estimate_fuel_delay` on the structure with the other effects' inputs."""
    def sweep(others: EffectInputs) -> float:
        return estimate_fuel_delay(ds, np.hstack([ds.u, others.u]), others.extend(structure))["best_s"]

    return apply_effects(ds, effects, estimate_shift=sweep)


def training_segments(ds, u, y, min_s: float) -> list[slice]:
    """The valid stretches of ds at least min_s [s] long where every column of u and y is finite. pem takes
    them as separate segments (filters restarted in each), never joined end to end: a junction would be a
    transient the model does not have."""
    finite = ds.valid & np.isfinite(u).all(axis=1) & np.isfinite(y)
    return dataclasses.replace(ds, valid=finite).segments(min_s)


def identify_model(ds, structure: Structure, effects=(), *, min_segment_s: float = 30.0, files=(),
                   init: PolyModel | None = None) -> PolyModel:
    """The PolyModel of `structure` (speed, torque inputs) plus `effects` ("ID" or "ID=VALUE") identified on
    dataset ds, with names, units, training summary (`files` recorded) and validation metrics filled in.

    init: a model of the final structure (with the effects' inputs) to start PEM from instead of the ARX /
    Steiglitz–McBride initialisation, e.g. the truck's previous model; ignored when its structure differs.
    Raises FuelidError for an unusable effect, too little valid data, or a failed estimation."""
    try:
        fx = effect_inputs(ds, effects, structure)
    except ValueError as exc:
        raise FuelidError(str(exc)) from exc
    u, y = np.hstack([ds.u, fx.u]), fx.y
    structure = fx.extend(structure)
    segs = training_segments(ds, u, y, min_segment_s)
    n_train = sum(s.stop - s.start for s in segs)
    if n_train - len(segs) * structure.n_start <= 2 * structure.n_params:
        raise FuelidError(f"too little valid data to identify {structure.n_params} parameters "
                          f"({int(ds.valid.sum())} valid samples, {len(segs)} stretches ≥ {min_segment_s:g} s)")
    u0 = np.r_[ds.u0, np.zeros(fx.u.shape[1])]
    if init is not None and init.structure != structure:
        init = None
    try:
        with warnings.catch_warnings():  # pem records its warnings in model.info
            warnings.simplefilter("ignore", UserWarning)
            model = pem(u, y, structure, ds.Ts, segments=segs, u0=u0, y0=ds.y0, init=init)
    except ValueError as exc:
        raise FuelidError(f"identification failed: {exc}") from exc

    model = dataclasses.replace(
        model, input_names=ds.input_names + fx.names, input_units=ds.input_units + fx.units,
        output_name=ds.output_name, output_unit=ds.output_unit, effects=fx.effects,
        info={**model.info, "effect_parameters": fx.parameters},
        training={**ds.summary(), "files": list(map(str, files)),
                  "identification_samples": int(n_train), "identification_stretches": len(segs)})
    return dataclasses.replace(model, validation=evaluate(model, ds))
