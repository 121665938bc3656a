"""A model's steady-state fuel: what the whole model settles to with engine speed and torque held at a point and
every other signal at a stated reference condition.

The model runs on u = [n, T, x_1 … x_k] (ident.modeldata): engine speed n [rpm], torque T [Nm or %] and the
columns x_j its effects build from the bus signals — some of them functions of n and T themselves (the engine
model's map columns; a regime's I·ñ, I·T̃). Held at a point p = (n, T) for ever, every input is constant,
u_ss(p) = the inputs `model_data` builds on a constant dataset (n and T held, each other signal at its reference
value; a rate of change is then 0), and the output settles at

    y_ss(p) = f(n, T) + Σ_{i ∉ S} G_i (u_ss,i(p) − u0_i),    G_i = B_i(1) / (A(1) F_i(1))   [output unit]

with S = speed, torque and the engine map's three columns, and f the model's own static map over speed and torque
(ident.hammerstein.steady_state_map: the engine model's fitted map under its dynamics' static gains; for a model
without an engine map the plane y0 + G_n ñ + G_T T̃). The other effects' inputs are rebuilt by their own builders,
so this holds for any effect whose inputs depend on speed and torque.

The reference condition is a value per bus signal (`REFERENCE`): a warm engine, no regeneration, standard air,
fan, retarder and PTO off, driving in gear with the clutch closed. A signal with no stated value — the engine's
relative load, a signal only the engineer's effects use — takes the value the truck's own data show at that
point: `data_reference` fits it on the data as a quadratic surface in (n, T) (signals the operating point
decides: the load against the full-load curve) or takes its median (signals it does not), and the fleet's jobs
store that in the model (info["steady_reference"]). An effect centred on a level (``scales:SIG``) is at that
level. A signal with no value at all is an InputError naming it.

Uncertainty by the delta method, σ = √(gᵀ P g + φᵀ C φ): P the covariance of θ = (a, b, f, c, d) (order of
ident.polymodel.parameter_names) and g = ∂y_ss/∂θ by central differences (`steady_gradient`: y_ss is a rational
function of θ whatever the static map does with it; 0 for the noise model c, d); for an engine model, C the
covariance of its map's coefficients c (ident.enginemap.coefficient_covariance) and φ = ∂y_ss/∂c the map's basis at
the point (`map_basis`; the map is fitted given the dynamics, so the two parts are added as independent). A mean
over points has the mean of their gradients and of their φ.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from fuelid.errors import InputError
from fuelid.ident.dataset import Dataset
from fuelid.ident.effectfile import effects_of_model
from fuelid.ident.effects import get_effect, parse_effect
from fuelid.ident.hammerstein import (MAP_COLUMN, MAP_EFFECT, RISE_COLUMN, RISE_MAP_COLUMN, engine_map_of,
                                      steady_state_map)
from fuelid.ident.modeldata import model_data
from fuelid.ident.polymodel import PolyModel, polynomials

# The reference condition: bus signal → (value [its DBC unit], what it states).
REFERENCE: dict[str, tuple[float, str]] = {
    "ET1.EngCoolantTemp": (90.0, "warm engine: coolant at 90 °C"),
    "DPFC1.DPFActiveRegenStatus": (0.0, "no DPF regeneration"),
    "AMB.AmbientAirTemp": (15.0, "standard air: 15 °C"),
    "AMB.BarometricPress": (101.325, "standard air: 101.325 kPa"),
    "FD.EstPercentFanSpeed": (0.0, "engine fan off"),
    "FD.FanDriveState": (0.0, "engine fan off"),
    "ERC1.ActualRetarderPercentTorque": (0.0, "retarder off"),
    "CCVS1.PTOGovernorState": (0.0, "no power take-off"),
    "CCVS1.WheelBasedVehicleSpeed": (80.0, "driving: 80 km/h"),
    "CCVS1.ClutchSwitch": (0.0, "driving: clutch closed"),
    "EEC2.AccelPedalPos1": (50.0, "driving: pedal at 50 %"),
    "ETC2.TransCurrentGear": (12.0, "driving: in gear, no shift"),
    "ETC2.TransSelectedGear": (12.0, "driving: in gear, no shift"),
}
MAP_INPUTS = (MAP_COLUMN, RISE_COLUMN, RISE_MAP_COLUMN)  # the engine map's columns: in its static map f(n, T)
STEP = 1e-6  # central differences' step relative to max(|θ_j|, STEP_FLOOR)
STEP_FLOOR = 1e-2
SAMPLES = 16  # length of the constant dataset: a rate of change by central differences is 0 on it
SURFACE = ("1", "n", "T", "n.T", "n2", "T2", "n2.T")  # data_reference's basis in krpm and kNm (or 100 %)
DECIDED_BY_POINT = 0.05  # at most this share of a signal's variance left by SURFACE: a function of the point


@dataclass(frozen=True)
class SteadyState:
    """y_ss at (speed_rpm [rpm], torque [model's torque unit]): value [unit], its standard error [unit] (None
    without a covariance), and the reference condition used (signal → what it was held at)."""

    speed_rpm: float
    torque: float
    value: float
    std_error: float | None
    unit: str
    reference: dict[str, str]


def static_gains(model: PolyModel) -> np.ndarray:
    """G_i = B_i(1) / (A(1) F_i(1)) [output unit per input unit], one per input."""
    return np.array([b.sum() / (model.A.sum() * f.sum()) for b, f in zip(model.B, model.F)])


def _surface(n: np.ndarray, T: np.ndarray, torque_unit: str) -> np.ndarray:
    n, T = np.asarray(n, float) / 1000.0, np.asarray(T, float) / (1000.0 if torque_unit == "Nm" else 100.0)
    return np.column_stack([np.ones_like(n), n, T, n * T, n * n, T * T, n * n * T])


def _signals_of(effect_id: str, defined) -> tuple[str, ...]:
    """The bus signals an effect's inputs are built from; a generic effect ``FORM:SIG`` (ident.effects.generic_effects)
    names SIG; a shift (the fuel signal's delay) has no input: held for ever, a delayed constant is the constant."""
    if ":" in effect_id:
        return (effect_id.split(":", 1)[1],)
    effect = get_effect(effect_id, None, defined)
    return () if effect.enters == "shift" else effect.signals


def _model_signals(model: PolyModel) -> list[tuple[str, str]]:
    """(effect spec, bus signal) of every signal the model's effects name."""
    defined = effects_of_model(model)
    return [(spec, sig) for spec in model.effects for sig in _signals_of(parse_effect(spec)[0], defined)]


def data_reference(model: PolyModel, ds: Dataset) -> dict:
    """The reference of each signal the model's effects use that `REFERENCE` does not state, from data ds:
    {signal: {"surface": coefficients over SURFACE}} when a quadratic surface in speed and torque leaves at most
    DECIDED_BY_POINT of its variance on the valid samples, else {signal: {"median": value}} [signal unit].
    JSON-ready, for model.info["steady_reference"]."""
    out = {}
    for _, sig in _model_signals(model):
        x = ds.extra.get(sig)
        if sig in REFERENCE or sig in out or x is None:
            continue
        ok = ds.valid & np.isfinite(x) & np.isfinite(ds.u).all(axis=1)
        if ok.sum() < len(SURFACE) * 10:
            continue
        basis = _surface(ds.u[ok, 0], ds.u[ok, 1], ds.input_units[1])
        coef = np.linalg.lstsq(basis, x[ok], rcond=None)[0]
        resid, spread = x[ok] - basis @ coef, x[ok] - x[ok].mean()
        total = float(spread @ spread)
        if total > 0 and float(resid @ resid) <= DECIDED_BY_POINT * total:
            out[sig] = {"surface": [float(c) for c in coef]}
        else:
            out[sig] = {"median": float(np.median(x[ok]))}
    return out


def _signal_values(model: PolyModel, speed: float, torque: float, reference: dict) -> tuple[dict, dict]:
    """(signal → value, signal → what it states) for every signal the model's effects name."""
    stored = model.info.get("steady_reference") or {}
    centred = model.info.get("effect_parameters") or {}
    values, said = {}, {}
    for spec, sig in _model_signals(model):
        eid = parse_effect(spec)[0]
        if sig in values:
            continue
        if sig in reference:
            values[sig], said[sig] = float(reference[sig]), f"{float(reference[sig]):g} (given)"
        elif sig in REFERENCE:
            values[sig], said[sig] = REFERENCE[sig]
        elif eid in centred and eid.startswith("scales:"):
            values[sig], said[sig] = float(centred[eid]), f"{float(centred[eid]):g}: the level the model is centred on"
        elif isinstance(stored.get(sig), dict) and "surface" in stored[sig]:
            coef = np.asarray(stored[sig]["surface"], float)
            values[sig] = float(_surface([speed], [torque], model.input_units[1])[0] @ coef)
            said[sig] = "as the truck's data show it at this speed and torque"
        elif isinstance(stored.get(sig), dict) and "median" in stored[sig]:
            values[sig], said[sig] = float(stored[sig]["median"]), f"{stored[sig]['median']:g}: the truck's median"
        elif sig not in ("EEC1.EngSpeed", "EEC1.ActualEngPercentTorque", "EC1.EngMomentOfInertia",
                         "EC1.EngSpeedAtIdlePoint1", "EC1.EngReferenceTorque"):
            raise InputError(f"steady state: no reference value for {sig} (effect {eid}); give it, or refit the "
                             "model in the fleet, which records the truck's own")
    return values, said


def steady_inputs(model: PolyModel, speed_rpm: float, torque: float,
                  reference: dict | None = None) -> tuple[np.ndarray, dict[str, str]]:
    """(u_ss − u0 for every model input [input units], the reference condition used): `model_data` on a constant
    dataset at the point (module docstring). InputError when the model's first inputs are not engine speed [rpm]
    and torque, or a signal has no reference value."""
    if len(model.B) < 2 or model.input_units[0] != "rpm":
        raise InputError(f"model inputs are in {', '.join(model.input_units)}; a steady state needs engine speed "
                         "[rpm] and torque first")
    values, said = _signal_values(model, speed_rpm, torque, dict(reference or {}))
    # A generic effect is found only on a signal that varies: its signal steps by 1 after the first n samples,
    # and the inputs are read in the middle of the constant part, where every builder sees a held value.
    generic = {sig for spec, sig in _model_signals(model) if ":" in parse_effect(spec)[0]}
    n = SAMPLES
    extra = {k: np.r_[np.full(n, v), np.full(n, v + (k in generic))] for k, v in values.items()}
    ds = Dataset(Ts=model.Ts, t=np.arange(2 * n) * model.Ts, u=np.tile([speed_rpm, torque], (2 * n, 1)).astype(float),
                 y=np.full(2 * n, model.y0), input_names=("engine speed", "engine torque"),
                 input_units=tuple(model.input_units[:2]), output_name=model.output_name,
                 output_unit=model.output_unit, u0=np.asarray(model.u0[:2], float), y0=model.y0,
                 valid=np.ones(2 * n, bool), cycle=np.full(2 * n, -1), extra=extra)
    u, _ = model_data(model, ds)
    return u[n // 2] - np.asarray(model.u0), said


def steady_value(model: PolyModel, speed_rpm: float, torque: float, du: np.ndarray) -> float:
    """y_ss [output unit] at (speed_rpm [rpm], torque [torque unit]) with input deviations du (`steady_inputs`):
    the static map f(n, T) plus Σ G_i du_i over the inputs outside it (module docstring). InputError for an engine
    model without its map's input."""
    if MAP_EFFECT in model.effects and MAP_COLUMN not in model.input_names:
        raise InputError(f"the model carries an engine map but no input named {MAP_COLUMN!r}: not a model fuelid wrote")
    beyond = [i for i, name in enumerate(model.input_names) if i >= 2 and name not in MAP_INPUTS]
    static = float(steady_state_map(model, [speed_rpm], [torque])[0])
    return static + float(static_gains(model)[beyond] @ du[beyond]) if beyond else static


def steady_gradient(model: PolyModel, speed_rpm: float, torque: float, du: np.ndarray) -> np.ndarray:
    """g = ∂y_ss/∂θ [output unit per parameter unit] at the point, in the order of parameter_names: central
    differences of `steady_value` over θ with steps STEP · max(|θ_j|, STEP_FLOOR) (0 for the noise model c, d,
    which the steady state does not depend on)."""
    s, theta = model.structure, model.theta
    g = np.zeros(s.n_params)
    for j in range(s.n_params - s.nc - s.nd):
        h = STEP * max(abs(theta[j]), STEP_FLOOR)
        up, down = theta.copy(), theta.copy()
        up[j] += h
        down[j] -= h
        at = [dataclasses.replace(model, **polynomials(t, s)._asdict(), covariance=None) for t in (up, down)]
        g[j] = (steady_value(at[0], speed_rpm, torque, du) - steady_value(at[1], speed_rpm, torque, du)) / (2 * h)
    return g


def map_basis(model: PolyModel, speed_rpm: float, torque: float) -> np.ndarray | None:
    """φ = ∂y_ss/∂c = G_m(1) × the engine map's basis at the point (kn·kt; G_m the map input's static gain, 1 for a
    model `fuelid identify` wrote), None for a model without a map or without its coefficients' covariance."""
    emap = engine_map_of(model)
    if emap is None or emap.covariance is None:
        return None
    return static_gains(model)[model.input_names.index(MAP_COLUMN)] * emap.basis([speed_rpm], [torque])[0]


def std_error(model: PolyModel, g: np.ndarray, phi: np.ndarray | None = None) -> float | None:
    """σ = √(gᵀ P g + φᵀ C φ) [output unit] for the gradient g of a steady state (`steady_gradient`) and φ its
    gradient over the map's coefficients (`map_basis`, None: no map term), C their covariance; None without a
    covariance of θ."""
    if model.covariance is None:
        return None
    var = float(g @ model.covariance @ g)
    if phi is not None:
        var += float(phi @ engine_map_of(model).covariance @ phi)
    return math.sqrt(max(var, 0.0))


def steady_fuel(model: PolyModel, speed_rpm: float, torque: float, reference: dict | None = None) -> SteadyState:
    """The model's steady-state fuel at (speed_rpm [rpm], torque [the model's torque unit]) with every other
    signal at the reference condition (`REFERENCE`, overridden per signal by `reference` {signal: value}), and
    its standard error by the delta method (module docstring)."""
    du, said = steady_inputs(model, speed_rpm, torque, reference)
    value = steady_value(model, speed_rpm, torque, du)
    error = std_error(model, steady_gradient(model, speed_rpm, torque, du), map_basis(model, speed_rpm, torque)) \
        if model.covariance is not None else None
    return SteadyState(float(speed_rpm), float(torque), value, error, model.output_unit, said)
