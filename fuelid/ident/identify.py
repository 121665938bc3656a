"""One offline identification of a fuel model from a Dataset: the code path shared by `fuelid identify` and the
fleet's per-truck jobs (fleet.jobs), so a model identified by the service is the one the command would give.

Steps: the effects' extra inputs (ident.modeldata.apply_effects; a fuel delay asked for without its value
estimated by seed 2's sweep with the model itself, `estimate_fuel_delay`) are appended to engine speed and torque, the
valid stretches of at least `min_segment_s` are taken, the model is estimated by prediction-error minimisation
(ident.pem.pem) and its validation metrics on the whole dataset (ident.validation.evaluate) are stored in it.

With effects that add inputs, PEM is run from two starts and one fit kept (`kept_fit`): the usual initialisation of
the whole structure, and the effects added in turn (`effects_added_in_turn`): the model without the effects
(given, or identified first on the same samples), then with the first effect, the first two, … each stage
identified from the usual initialisation and from the stage before it with the new coefficients at zero
(`with_inputs`, from which Levenberg–Marquardt only descends), one fit kept the same way. A start that falls into a
poor local minimum (a pole pressed against the stability bound, or the initialisation of many collinear inputs)
is not the one kept.
Which fit: the lower loss V, PEM's own criterion — unless another simulates the identification data better by more
than SIMULATION_MARGIN (RMS simulation error, `simulation_rmse`). The model is used and judged in simulation (fit
%, cycle fuel error), and of two local minima the lower V can simulate far worse, the high-order noise model then
carrying what the inputs' part should; where the two simulate alike, the lower V has been the better model on
another day's data, so the simulation error overrides V only when it differs grossly (README: the cases measured).

Callers that identify nested sets of effects on one dataset (the diagnosis builds the model with effects E, then with
E and one more, whose in-turn stages are the fits of E again) pass one `FitMemo` to every call: PEM is
deterministic, so a fit asked for again from the same data and start is served, the same to the bit.
"""
from __future__ import annotations

import copy
import dataclasses
import functools
import hashlib
import warnings

import numpy as np

from fuelid.errors import FuelidError, InputError
from fuelid.ident.effectfile import effects_of_model
from fuelid.ident.fueldelay import shift_signal, sweep_fuel_shift
from fuelid.ident.hammerstein import JOINT_ROUNDS, MAP_EFFECT, joint_fit
from fuelid.ident.modeldata import EffectInputs, apply_effects, at_operating_point
from fuelid.ident.pem import LMResult, pem, pem_with_search
from fuelid.ident.polymodel import PolyModel, Structure, simulate
from fuelid.ident.validation import evaluate, rmse
from fuelid.parallel import side_by_side

MIN_SEGMENT_S = 30.0  # [s] shortest valid stretch a model is fitted on (`fuelid identify --min-segment`)


class FitMemo:
    """PEM fits (ident.pem.pem) kept by everything each was fitted from: inputs u (N × m), output y (N), structure,
    Ts [s], segments, operating point u0, y0 and start (init's θ, or the initialisation). pem is deterministic, so a
    fit asked for again from the same is the model already fitted; served as a copy (a caller changing it cannot
    change the next one's). A fit asked for with more iterations (max_iter) than one kept that stopped at its limit
    continues that one's search (ident.pem.pem_with_search, `after`). A fit kept that stopped before its limit
    (converged, or no damping lowered V) is the fit to any limit above its iterations too: Levenberg–Marquardt's
    iterates do not depend on the limit. A memo serves one process's calls and is never stored; a copy a worker
    process used (fuelid.parallel) hands its fits back by `update`."""

    def __init__(self):
        self._fits: dict[tuple[bytes, int], tuple[PolyModel, LMResult]] = {}  # (key, max_iter) → model, search
        self.made = 0  # the fits made by this memo's calls (not served; a copy's own are not counted here)

    def update(self, other: FitMemo) -> None:
        """Keep the fits of `other` (a copy of this memo a worker process used) that this one lacks."""
        if other is not self:
            for key, fit in other._fits.items():
                self._fits.setdefault(key, fit)

    def __len__(self) -> int:
        """The number of fits kept (made here, or served by one kept)."""
        return len(self._fits)

    @staticmethod
    def _key(u, y, structure: Structure, Ts: float, segments, u0, y0: float, init: PolyModel | None) -> bytes:
        """A digest of everything pem's result depends on but its iteration limit (the start: init's θ, which is
        all pem takes of it)."""
        h = hashlib.blake2b(digest_size=32)
        for a in [u, y, u0] + ([] if init is None else [init.theta]):
            a = np.ascontiguousarray(a, dtype=float)
            h.update(repr(a.shape).encode())
            h.update(a.tobytes())
        spans = [(s.start, s.stop) if isinstance(s, slice) else tuple(map(int, s)) for s in segments]
        h.update(repr((structure, float(Ts), spans, float(y0),
                       None if init is None else init.structure)).encode())
        return h.digest()

    def pem(self, u, y, structure: Structure, Ts: float, *, segments, u0, y0: float,
            init: PolyModel | None = None, max_iter: int = 100) -> PolyModel:
        """pem(u, y, structure, Ts, segments=segments, u0=u0, y0=y0, init=init, max_iter=max_iter), fitted once
        per distinct call, or continued from a kept fit with fewer iterations that stopped at its limit when
        warm-started."""
        key = self._key(u, y, structure, Ts, segments, u0, y0, init)
        if (key, max_iter) not in self._fits:
            fit = functools.partial(pem_with_search, u, y, structure, Ts, segments=segments, u0=u0, y0=y0, init=init)
            self._fits[key, max_iter] = self._stopped_before(key, max_iter) or self._fitted(key, max_iter, fit,
                                                                                            init is not None)
        return copy.deepcopy(self._fits[key, max_iter][0])

    def _fitted(self, key: bytes, limit: int, fit, warm: bool) -> tuple[PolyModel, LMResult]:
        """fit(max_iter=limit, after=...) (pem_with_search of the call of key), continued from the longest kept
        search of key stopped at its limit when warm-started (init given)."""
        shorter = [search for (k, kept), (_, search) in self._fits.items()
                   if k == key and kept < limit and search.reason == "max_iterations"]
        after = max(shorter, key=lambda search: search.iterations) if shorter and warm else None
        made = fit(max_iter=limit, after=after)
        self.made += 1
        return made

    def _stopped_before(self, key: bytes, limit: int) -> tuple[PolyModel, LMResult] | None:
        """A kept fit (model, search) of key that stopped before its own limit, after fewer iterations than `limit`,
        as the fit to `limit` (the same search, its model's info["stopping"] saying `limit`); None when none is."""
        for (k, _), (model, search) in self._fits.items():
            if k == key and search.reason != "max_iterations" and search.iterations < limit:
                info = {**model.info, "stopping": {**model.info["stopping"], "max_iter": limit}}
                return dataclasses.replace(model, info=info), search
        return None


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


def effect_inputs(ds, effects, structure: Structure, defined=(), parameters: dict | None = None) -> EffectInputs:
    """apply_effects for a fit of `structure` (speed, torque inputs) with `effects` (built-in, or among `defined`,
    effects the engineer defined) and apply_effects' `parameters`; a fuel delay asked for without its value is
    estimated by `estimate_fuel_delay` on the structure with the other effects' inputs."""
    def sweep(others: EffectInputs) -> float:
        return estimate_fuel_delay(ds, np.hstack([ds.u, others.u]), others.extend(structure))["best_s"]

    return apply_effects(ds, effects, parameters, estimate_shift=sweep, defined=defined)


def training_segments(ds, u, y, min_s: float) -> list[slice]:
    """The valid stretches of ds at least min_s [s] long where every column of u and y is finite. pem takes
    them as separate segments (filters restarted in each), never joined end to end: a junction would be a
    transient the model does not have."""
    finite = ds.valid & np.isfinite(u).all(axis=1) & np.isfinite(y)
    return dataclasses.replace(ds, valid=finite).segments(min_s)


def identify_model(ds, structure: Structure, effects=(), *, min_segment_s: float = MIN_SEGMENT_S, files=(),
                   init: PolyModel | None = None, defined=(), base: PolyModel | None = None,
                   memo: FitMemo | None = None, initialisation: bool = True,
                   joint_rounds: int = JOINT_ROUNDS) -> PolyModel:
    """The PolyModel of `structure` (speed, torque inputs) plus `effects` ("ID" or "ID=VALUE") identified on
    dataset ds, with names, units, training summary (`files` recorded) and validation metrics filled in.

    init: a model of the final structure (with the effects' inputs) to start PEM from instead of the ARX /
    Steiglitz–McBride initialisation, e.g. the truck's previous model; ignored when its structure differs. An
    engine model's map is the map's start too, and with its structure the joint fit goes on from it (no static
    start: ident.hammerstein.joint_fit).
    base: the model of `structure` without the effects (e.g. the one diagnosed) for the second start (module
    docstring); identified here on the same samples when not given or of another structure.
    defined: effects the engineer defined (ident.effectfile) that `effects` may name; the model carries the
    definitions of those it uses (info["effect_definitions"]), so it runs without their file.
    info["starts"] records the loss V and simulation RMS error each start reached, which was kept, and the stages.
    memo: PEM fits of earlier calls on these data, served instead of fitted again (`FitMemo`; the same model).
    initialisation: False leaves out the start from the ARX / Steiglitz–McBride
    initialisation when `base` is given (the engine model from the linear one: only the starts from init and base).
    With the engine_map effect the map and the dynamics are then refined jointly (ident.hammerstein.joint_fit, at
    most joint_rounds rounds).
    Raises FuelidError for an unusable effect, too little valid data, or a failed estimation."""
    # a given engine model goes on from its own map (a fresh static fit would be another start: ident.hammerstein)
    kept_map = (init.info.get("effect_parameters") or {}).get(MAP_EFFECT) if init is not None else None
    fx = effect_inputs(ds, effects, structure, defined,
                       {MAP_EFFECT: kept_map} if kept_map and MAP_EFFECT in map(str, effects) else None)
    u, y = np.hstack([ds.u, fx.u]), fx.y
    extended = fx.extend(structure)
    segs = training_segments(ds, u, y, min_segment_s)
    n_train = sum(s.stop - s.start for s in segs)
    if n_train - len(segs) * extended.n_start <= 2 * extended.n_params:
        raise FuelidError(f"too little valid data to identify {extended.n_params} parameters "
                          f"({int(ds.valid.sum())} valid samples, {len(segs)} stretches ≥ {min_segment_s:g} s)")
    check_variation(ds, u, y, np.concatenate([np.arange(s.start, s.stop) for s in segs]))
    u0 = np.r_[ds.u0, np.zeros(fx.u.shape[1])]
    given = init if init is not None and init.structure == extended else None
    starts = {"initialisation" if given is None else "given model": given}
    if given is None and not initialisation and base is not None and fx.u.shape[1]:
        starts = {}
    fit = memo.pem if memo is not None else pem
    with warnings.catch_warnings():  # pem records its warnings in model.info
        warnings.simplefilter("ignore", UserWarning)
        stages = []
        if fx.u.shape[1]:
            if base is None or base.structure != structure:
                base = fit(ds.u, y, structure, ds.Ts, segments=segs, u0=ds.u0, y0=ds.y0)
            nested, stages = effects_added_in_turn(base, u, y, fx, segs, ds.Ts, y0=ds.y0, memo=memo)
            starts["effects added in turn"] = with_inputs(nested, extended)
        fits = dict(zip(starts, fits_from(list(starts.values()), u, y, extended, ds.Ts, segments=segs, u0=u0,
                                          y0=ds.y0, memo=memo)))
    scores = {name: simulation_rmse(m, u, y, segs) for name, m in fits.items()}
    kept = list(fits)[kept_fit(list(fits.values()), list(scores.values()))]
    model = fits[kept]
    model = dataclasses.replace(
        model, input_names=ds.input_names + fx.names, input_units=ds.input_units + fx.units,
        output_name=ds.output_name, output_unit=ds.output_unit, effects=fx.effects,
        info={**model.info, "effect_parameters": fx.parameters,
              "starts": {"loss_V": {name: m.info["loss_V"] for name, m in fits.items()},
                         "simulation_rmse": scores, "kept": kept,
                         "stages": stages},
              **effect_definitions(fx.effects, defined)},
        training={**ds.summary(), "files": list(map(str, files)),
                  "identification_samples": int(n_train), "identification_stretches": len(segs)})
    if MAP_EFFECT in fx.effects:  # the engine's map and the dynamics jointly (ident.hammerstein)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            model = joint_fit(model, ds, segs, keep=kept_fit, fit=fit, rounds=joint_rounds, from_static=given is None)
    model = dataclasses.replace(model, validation=evaluate(model, ds))
    model.info["data_warnings"] = data_warnings(model, ds, u[np.concatenate([np.arange(s.start, s.stop) for s in segs])],
                                                n_train - len(segs) * extended.n_start)
    return model


def check_variation(ds, u: np.ndarray, y: np.ndarray, used: np.ndarray) -> None:
    """InputError when the samples `used` (indices into ds) cannot identify anything: the fuel y, or engine speed
    and torque (u's first two columns) both, constant over them (a recording of an engine that is off or standing
    still, a fuel signal stuck at one value)."""
    seconds = f"{len(used) * ds.Ts:.0f} s"
    if len(used) and np.ptp(y[used]) == 0:
        raise InputError(f"the fuel flow never varies in these data ({y[used[0]]:g} {ds.output_unit} over "
                         f"{seconds}): there is nothing to identify")
    if len(used) and not np.ptp(u[used, :2], axis=0).any():
        raise InputError(f"engine speed and torque never vary in these data ({u[used[0], 0]:g} "
                         f"{ds.input_units[0]}, {u[used[0], 1]:g} {ds.input_units[1]} over {seconds}): the fuel's "
                         "dependence on them is not in the data")


def _first_inputs(s: Structure, m: int) -> Structure:
    """Structure s with its first m inputs only."""
    return Structure(nb=s.nb[:m], nf=s.nf[:m], nk=s.nk[:m], nc=s.nc, nd=s.nd, na=s.na)


SIMULATION_MARGIN = 1.1  # another fit's RMS simulation error this many times lower overrides the lower loss V


def kept_fit(fits: list[PolyModel], simulation: list[float]) -> int:
    """Index of the fit to keep of PEM fits of one structure on the same data (module docstring): the lowest loss
    V, unless another's RMS simulation error (`simulation`, [fuel unit]) is lower by more than SIMULATION_MARGIN;
    then the best-simulating one."""
    by_v = min(range(len(fits)), key=lambda k: fits[k].info["loss_V"])
    by_sim = int(np.argmin(simulation))
    return by_sim if simulation[by_sim] * SIMULATION_MARGIN < simulation[by_v] else by_v


def simulation_rmse(model: PolyModel, u: np.ndarray, y: np.ndarray, segments) -> float:
    """RMS simulation error [fuel unit] of `model` on the slices `segments` of u (N × inputs), y (N), each simulated
    from zero state, its first n_start samples left out (as the validation metrics)."""
    n0 = model.structure.n_start
    err = [(y[s] - simulate(model, u[s]))[n0:] for s in segments]
    return float(np.sqrt(np.mean(np.concatenate(err) ** 2)))


def fits_from(starts: list[PolyModel | None], u, y, structure: Structure, Ts: float, *, segments, u0, y0: float,
              memo: FitMemo | None = None) -> list[PolyModel]:
    """[pem(u, y, structure, Ts, segments=segments, u0=u0, y0=y0, init=start) for start in starts] (None: from the
    initialisation), through memo's pem when given: fits independent of each other, run side by side
    (fuelid.parallel; the copy of memo a worker used hands its fits back)."""
    calls = [functools.partial(_fitted_from, start, u, y, structure, Ts, segments, u0, y0, memo) for start in starts]
    out = []
    for model, used in side_by_side(calls):
        if memo is not None:
            memo.update(used)
        out.append(model)
    return out


def _fitted_from(start: PolyModel | None, u, y, structure: Structure, Ts: float, segments, u0, y0: float,
                 memo: FitMemo | None) -> tuple[PolyModel, FitMemo | None]:
    """(pem's fit from start, through memo when given, its warnings left out: they are in its info; memo)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        fit = memo.pem if memo is not None else pem
        return fit(u, y, structure, Ts, segments=segments, u0=u0, y0=y0, init=start), memo


def effects_added_in_turn(base: PolyModel, u: np.ndarray, y: np.ndarray, fx: EffectInputs, segments, Ts: float, *,
                          y0: float, memo: FitMemo | None = None) -> tuple[PolyModel, list[dict]]:
    """The model with every effect of fx that adds inputs but the last, built from `base` (the model of u's first
    inputs, speed and torque, identified on the same samples) by adding them in turn: each stage identified by PEM
    on u's leading columns from the usual initialisation and from the stage before with the new coefficients at
    zero (`with_inputs`), one kept by `kept_fit` (module docstring). u: N × (2 + k) inputs (speed [rpm], torque,
    then fx.u), y: the (shifted) fuel [L/h], segments as in `pem`, Ts [s], y0 the fuel's operating point [L/h];
    memo: the `FitMemo` to fit through (`fits_from`). Returns (that model, [{effects, loss_V, simulation_rmse} per
    stage])."""
    model, stages = base, []
    n_base = len(base.B)
    full = fx.extend(base.structure)
    ends = np.cumsum(fx.columns)
    for j, end in enumerate(ends):
        if not fx.columns[j] or end == fx.u.shape[1]:
            continue
        m = n_base + int(end)
        sub = _first_inputs(full, m)
        u0 = np.r_[base.u0, np.zeros(m - n_base)]
        fits = fits_from([None, with_inputs(model, sub)], u[:, :m], y, sub, Ts, segments=segments, u0=u0, y0=y0,
                         memo=memo)
        scores = [simulation_rmse(f, u[:, :m], y, segments) for f in fits]
        k = kept_fit(fits, scores)
        model = fits[k]
        stages.append({"effects": list(fx.effects[: j + 1]), "loss_V": model.info["loss_V"],
                       "simulation_rmse": scores[k]})
    return model, stages


def with_inputs(model: PolyModel, structure: Structure) -> PolyModel:
    """`model` as a model of `structure`, which has the same noise model and A and adds inputs after model's: those
    inputs' B_i = 0 and F_i = 1 (the model itself, as a start for PEM with them)."""
    m = len(model.B)
    if structure.nb[:m] != model.structure.nb or structure.nf[:m] != model.structure.nf \
            or structure.nk[:m] != model.nk or (structure.na, structure.nc, structure.nd) != \
            (model.structure.na, model.structure.nc, model.structure.nd):
        raise ValueError(f"{structure} does not extend the model's structure {model.structure}")
    added = range(m, structure.n_inputs)
    return PolyModel(A=model.A, B=list(model.B) + [np.zeros(structure.nk[i] + structure.nb[i]) for i in added],
                     F=list(model.F) + [np.r_[1.0, np.zeros(structure.nf[i])] for i in added], C=model.C, D=model.D,
                     Ts=model.Ts, nk=structure.nk, u0=tuple(model.u0) + (0.0,) * len(added), y0=model.y0)


def refit_with_effects(model: PolyModel, ds, effects, *, defined=(), min_segment_s: float = MIN_SEGMENT_S,
                       max_iter: int = 100, memo: FitMemo | None = None) -> PolyModel:
    """`model` with `effects` added ("ID" or "ID=VALUE", after its own), identified by PEM on dataset ds from the
    model itself with their coefficients at zero (`with_inputs`): a warm start, so V never rises above the model's
    own on these samples and a few iterations usually suffice (max_iter caps them). Its effects' parameters and
    engineer-defined effects' definitions are carried over; defined: those `effects` may name. memo: the fits of
    calls on these data (`FitMemo`), this one kept among them."""
    own = effects_of_model(model)
    defined = tuple(own) + tuple(e for e in defined if e.id not in {d.id for d in own})
    ids = list(model.effects) + [e for e in effects if e not in model.effects]
    fx = apply_effects(at_operating_point(ds, model), ids, model.info.get("effect_parameters"), defined=defined)
    u = np.hstack([ds.u, fx.u])
    n_own = len(model.B)
    extended = fx.extend(Structure(nb=model.structure.nb[:2], nf=model.structure.nf[:2], nk=model.nk[:2],
                                   nc=model.structure.nc, nd=model.structure.nd, na=model.structure.na))
    segs = training_segments(ds, u, fx.y, min_segment_s)
    start = with_inputs(model, extended)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        fit = (memo.pem if memo is not None else pem)(
            u, fx.y, extended, ds.Ts, segments=segs, u0=np.r_[model.u0[:n_own], np.zeros(u.shape[1] - n_own)],
            y0=model.y0, init=start, max_iter=max_iter)
    return dataclasses.replace(
        fit, input_names=ds.input_names + fx.names, input_units=ds.input_units + fx.units,
        output_name=model.output_name, output_unit=model.output_unit, effects=fx.effects,
        info={**fit.info, "effect_parameters": fx.parameters, **effect_definitions(fx.effects, defined)})


def effect_definitions(used, defined) -> dict:
    """{"effect_definitions": {id: effect-file table}} for the effects among `used` defined in a file (plug-ins'
    are found again by their id), or {} when there are none."""
    tables = {e.id: e.definition for e in defined if e.id in used and e.definition is not None}
    return {"effect_definitions": tables} if tables else {}


FPE_WARN = 1.1  # warn when Akaike's FPE expects the error on new data ≥ 10 % above the fit's
EXCITATION_MIN = 0.05  # an input whose standard deviation is below 5 % of its physical scale is barely excited


def excitation_scales(ds, input_units) -> list[float | None]:
    """The physical scale each input's variation is judged against: engine speed [rpm] its idle speed (the
    operating point), torque its reference torque (EC1 SPN 544) [Nm] or 100 [%]; None for the effects'
    inputs, which are judged only on whether they vary at all."""
    ref = ds.extra.get("EC1.EngReferenceTorque")
    ref_nm = float(np.nanmedian(ref)) if ref is not None and np.isfinite(ref).any() else None
    torque = {"%": 100.0, "Nm": ref_nm}.get(input_units[1])
    return [abs(float(ds.u0[0])) or None, torque] + [None] * (len(input_units) - 2)


def data_warnings(model: PolyModel, ds, u: np.ndarray, n_used: int) -> list[str]:
    """Plain warnings when the data cannot support the model. Too few samples per parameter: Akaike's final
    prediction error FPE = V (1 + d/N)/(1 − d/N) (d parameters, N samples in the loss) says how much larger the
    error on new data is expected to be than on the data fitted. An input the data barely excite: its standard
    deviation over the identification samples u [input units] is below EXCITATION_MIN of its physical scale
    (`excitation_scales`), or an effect's input never varies."""
    d = model.structure.n_params
    out = []
    fpe = (1 + d / n_used) / (1 - d / n_used)
    if fpe >= FPE_WARN:
        out.append(f"only {n_used} samples for {d} parameters ({n_used / d:.0f} per parameter): the error on new "
                   f"data is expected to be about {100 * (fpe - 1):.0f} % above the figures here (Akaike's FPE); "
                   "use longer data or lower orders (--orders auto)")
    for name, unit, std, scale in zip(model.input_names, model.input_units, u.std(axis=0),
                                      excitation_scales(ds, model.input_units)):
        if scale is None and std == 0:
            out.append(f"{name} never varies in these data: its effect on the fuel is not determined by them")
        elif scale is not None and std < EXCITATION_MIN * scale:
            out.append(f"the data barely excite {name}: it varies by {std:.3g} {unit} (standard deviation), under "
                       f"{100 * EXCITATION_MIN:.0f} % of {scale:.4g} {unit}; its effect on the fuel is not "
                       f"determined by these data")
    return out
