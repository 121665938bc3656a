"""The effects of a model as its data: the extra inputs (ident.effects' regressors, one MISO input per column,
each with the effect's orders; on an engine model an effect that scales the fuel or a torque the bus does not
report also through the map: `map_scaled`, `map_sloped`) beside engine speed and torque, and the fuel advanced by
the fuel-signal delay when the model includes it (ident.fueldelay),

    u = [speed, torque, x_1 … x_k],   y(t + τ).

`apply_effects` makes them for a fit, `model_data` for a fitted model (its effects, its τ, its operating point).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import numpy as np

from fuelid.errors import InputError
from fuelid.ident.effectfile import effects_of_model
from fuelid.ident.effects import Regressors, centred, get_effect, parse_effect
from fuelid.ident.enginemap import EngineMap
from fuelid.ident.fueldelay import shift_signal
from fuelid.ident.polymodel import Structure


@dataclass
class EffectInputs:
    """What `apply_effects` gives a fit: extra inputs u (N × k) with names, units and orders (nb, nf, nk) per
    column, the fuel y (advanced by the fuel-delay shift when that effect is on), the effect parameters and how
    many columns of u each of `effects` added, in order (0 for the fuel-delay shift)."""

    u: np.ndarray
    names: tuple[str, ...]
    units: tuple[str, ...]
    orders: tuple[tuple[int, int, int], ...]
    y: np.ndarray
    effects: tuple[str, ...]
    parameters: dict
    columns: tuple[int, ...] = ()

    def extend(self, structure):
        """The model structure with one more input per extra column."""
        nb, nf, nk = (tuple(o[j] for o in self.orders) for j in range(3))
        return Structure(nb=structure.nb + nb, nf=structure.nf + nf, nk=structure.nk + nk,
                         nc=structure.nc, nd=structure.nd, na=structure.na)


def apply_effects(ds, ids, parameters: dict | None = None,
                  estimate_shift: Callable[[EffectInputs], float] | None = None, defined=()) -> EffectInputs:
    """Extra inputs and shifted fuel for the effects `ids` ("ID" or "ID=VALUE") on dataset ds.

    parameters: {"fuel_delay": τ [s]} the fuel advance, {"scales:SIG": x_ref} the level a raw bus signal that
    scales the fuel is centred on (default its median on ds: ident.effects.centred), {"engine_map": the engine's
    map (ident.enginemap.EngineMap.to_dict; default its static fit on ds, ident.effects.static_engine_map)}; when fuel_delay is asked for without τ, τ [s] is
    estimate_shift(the EffectInputs of the other effects, fuel not shifted), e.g. ident.identify's sweep with
    the model (required then). defined: effects the engineer defined (ident.effectfile) the ids may name.
    Raises ValueError for an unknown id or an effect whose signals are not logged.
    """
    parameters = dict(parameters or {})
    used, built = [], []
    y = np.asarray(ds.y, float)
    shift = None
    for raw in ids:
        eid, value = parse_effect(raw)
        effect = get_effect(eid, ds, defined)
        used.append(effect.id)
        if effect.reference is not None:  # a parameter kept with the model: every data set built alike
            if value is not None:
                parameters[effect.id] = value
            elif effect.id not in parameters:
                parameters[effect.id] = effect.reference(ds)
            effect = (effect.bind or centred)(effect, parameters[effect.id])
        if effect.enters == "shift":
            built.append((effect, None))
            shift_id = effect.id
            shift = value if value is not None else parameters.get(effect.id, "sweep")
            continue
        reg = effect.build(ds)
        if reg is None:
            raise InputError(f"effect {effect.id}: its signals ({', '.join(effect.signals)}) are not in the data")
        built.append((effect, reg))
    beyond = next((reg.x[:, 0] for effect, reg in built if effect.id == "engine_map"), None)
    cols, names, units, orders, widths = [], [], [], [], []
    for effect, reg in built:
        if reg is None:
            widths.append(0)
            continue
        if effect.enters == "scales_fuel" and beyond is not None:
            reg = map_scaled(reg, beyond, ds.output_unit)
        if effect.enters == "torque" and beyond is not None:
            reg = map_sloped(reg, map_slope(ds, parameters["engine_map"]), ds.output_unit, ds.input_units[1])
        cols.append(reg.x)
        widths.append(reg.x.shape[1])
        names += [f"{effect.id}: {n}" for n in reg.names]
        units += list(reg.units)
        orders += list(reg.orders) if reg.orders is not None else [effect.orders] * reg.x.shape[1]
    u = np.hstack(cols) if cols else np.zeros((len(y), 0))
    if shift == "sweep":
        if estimate_shift is None:
            raise InputError("fuel_delay needs its shift: give fuel_delay=SECONDS (or a structure to sweep with)")
        shift = estimate_shift(EffectInputs(u, (), (), tuple(orders), y, (), {}))
    if shift is not None:
        parameters[shift_id] = float(shift)
        y = shift_signal(y, shift / ds.Ts, ds.segments())
    return EffectInputs(u, tuple(names), tuple(units), tuple(orders), y, tuple(used), parameters, tuple(widths))


def map_scaled(reg: Regressors, beyond: np.ndarray, fuel_unit: str) -> Regressors:
    """The columns of an effect that scales the fuel, y (1 + m x), on an engine model: its own (x and its products
    with the speed and torque deviations, ident.effects.scaling: x times the plane) and x·m(n, T), m the engine map
    beyond its plane [fuel unit] (ident.effects.engine_map_columns). Together they are x times the whole map, so
    that the effect scales the curved fuel as the engine burns it; with the plane's products alone the part of
    m x the plane cannot carry is left to whatever other signal follows it while the effect is on."""
    x = reg.x[:, 0]
    orders = reg.orders + (reg.orders[0],) if reg.orders is not None else None
    return Regressors(np.column_stack([reg.x, x * beyond]), reg.names + (f"{reg.names[0]} x map beyond the plane",),
                      reg.units + (f"{reg.units[0]}.{fuel_unit}",), orders)


def map_sloped(reg: Regressors, slope: np.ndarray, fuel_unit: str, torque_unit: str) -> Regressors:
    """The columns of a torque κ x the engine delivers and the bus does not report, on an engine model: its own
    (x, through the torque path's dynamics) and x·∂m/∂T(n, T), ∂m/∂T the engine map's torque slope beyond its plane
    [fuel unit per torque unit] (`map_slope`). The engine burns f(n, T + κ x) ≈ f(n, T) + κ x ∂f/∂T, and
    ∂f/∂T = g_T + ∂m/∂T (g_T the torque path's static gain): on a curved map the fuel of a hidden torque follows the
    map's marginal fuel, which grows with speed and is 0 where the injection is cut; with x alone it would have the
    torque path's one gain everywhere."""
    orders = reg.orders + (reg.orders[0],) if reg.orders is not None else None
    return Regressors(np.column_stack([reg.x, reg.x[:, 0] * slope]),
                      reg.names + (f"{reg.names[0]} x map torque slope beyond the plane",),
                      reg.units + (f"{reg.units[0]}.{fuel_unit}/{torque_unit}",), orders)


def map_slope(ds, fitted: dict) -> np.ndarray:
    """∂m/∂T = ∂s/∂T − p_T [fuel unit per torque unit] at ds's speed and torque: the torque slope of the engine map
    `fitted` (ident.enginemap.EngineMap.to_dict) beyond its plane's, 0 where the torque is missing."""
    emap = EngineMap.from_dict(fitted)
    n, T = ds.u[:, 0], ds.u[:, 1]
    return np.where(np.isfinite(T), emap.torque_slope(n, T) - emap.plane[2], 0.0)


def at_operating_point(ds, model):
    """ds with the model's speed and torque operating point u0 (regime columns are deviations from it)."""
    return dataclasses.replace(ds, u0=np.asarray(model.u0[:2], float))


def model_data(model, ds) -> tuple[np.ndarray, np.ndarray]:
    """(u, y) on which `model` runs: the dataset's speed and torque plus the extra inputs of the effects the
    model includes (model.effects, shift from model.info['effect_parameters']; regimes use the model's
    operating point; effects the engineer defined from the definitions the model carries), and the (shifted)
    fuel."""
    fx = apply_effects(at_operating_point(ds, model), model.effects, model.info.get("effect_parameters"),
                       defined=effects_of_model(model))
    u = np.hstack([ds.u, fx.u])
    if u.shape[1] != len(model.B):
        raise InputError(f"model has {len(model.B)} inputs but the data and its effects give {u.shape[1]}")
    return u, fx.y


def fuel_shift_s(model) -> float:
    """τ [s]: how far the model's fuel is advanced by a fuel-delay effect (enters "shift": the built-in fuel_delay
    or one the engineer defined), 0 without one. Its simulation delayed by τ (ident.fueldelay.shift_signal by
    −τ/Ts) is its fuel as the bus reports it."""
    defined = effects_of_model(model)
    params = model.info.get("effect_parameters") or {}
    for e in model.effects:
        eid = parse_effect(e)[0]
        if ":" not in eid and get_effect(eid, defined=defined).enters == "shift":  # generic forms never shift
            return float(params.get(eid, 0.0))
    return 0.0
