"""Physical effects a two-input (engine speed, torque) fuel model lacks: the library the diagnosis tests.

An effect is a named piece of physics with the bus signals that reveal it (DBC names ``MESSAGE.Signal`` and
their SPNs) and the way it enters the Box-Jenkins model

    y(t) = Σ_i B_i/F_i u_i(t − nk_i) + C/D e(t):

- ``input``        an extra MISO input with its own B/F/nk (e.g. J dω/dt for inertia, a coolant-temperature
                   deficit, retarder torque);
- ``nonlinearity`` a static function of the model's own inputs fed as extra inputs (speed × torque power; the
                   engine's own fuel map `engine_map`, which the diagnosis tests first as a property of the
                   engine, ident.diagnosis.verdict);
- ``regime``       an on/off state I(t) ∈ {0, 1} that changes the fuelling: extra inputs I, I·ñ, I·T̃ (an
                   offset and a change of both gains while the state is on; ñ, T̃ deviations of engine speed
                   [rpm] and torque [Nm] from the operating point), e.g. DPF active regeneration or overrun
                   fuel cut-off;
- ``shift``        a time shift of the fuel signal itself (sub-sample): y(t) is replaced by y(t + τ) with
                   cubic-spline fractional-delay interpolation; τ is estimated by seed 2's sweep (±1 s in
                   0.1 s steps, refined by a parabola through the best three) or given.

`EFFECTS` holds the built-in effects; `generic_effects(ds)` adds candidates for every further decoded bus
signal in Dataset.extra, in every form an effect takes that can apply to it — a physical quantity as its level,
its rate of change, a factor that scales the fuel and (a torque or a power only) a torque the bus does not
report; an enumeration as its states — so an effect nobody listed is still
found and named by its DBC signal and SPN. Effect ids are the
same as the simulator's (`fuelid simulate --effect ID=MAG`): the diagnosis says "add effect ID" and
`fuelid identify --effect ID` adds it.

This module is the catalogue only: what an effect is and the regressors it builds. The fuel shift and seed
2's sweep are ident.fueldelay; how a model's effects become its inputs, ident.modeldata; the sweep with the
model itself, ident.identify.

Regressors are plain arrays on the Dataset grid (N samples, Ts [s]); samples where a signal is unknown are
NaN, and `columns` fills a bus signal's short gaps by holding its last value (what the ECU last said), and
leading unknowns by its first value.
"""
from __future__ import annotations

import functools
import importlib.metadata
from dataclasses import dataclass, field, replace
from typing import Callable

import cantools
import numpy as np

from fuelid.errors import InputError
from fuelid.dbc import FMS_DBC
from fuelid.ident.enginemap import EngineMap, fit_map

RPM_TO_RAD_S = 2.0 * np.pi / 60.0

# Signals computed from the fuel itself (the output): as a candidate they would "explain" fuel by fuel.
OUTPUT_DERIVED_SPNS = frozenset({183, 184, 182, 250, 5053, 5054})


@dataclass(frozen=True)
class Effect:
    """One physical effect (module docstring). `build(ds)` returns its regressors: an N × k array with one
    name and unit per column, or None when the signals it needs are not in the data.

    A shift effect has no build: its test regressor is d/dt of the simulated fuel of seed 2's low-order model
    ident.fueldelay.DELAY_REFERENCE, which cannot absorb a delay (the diagnosis makes it), since y(t − τ) ≈ y(t) − τ
    dy/dt. orders (nb, nf, nk) of each extra input when the effect is added to a model; lags [samples] at which the
    diagnosis tests each column (an FIR basis of its dynamics); sign the direction the physics moves the fuel when
    the effect's first regressor x grows (+1 more fuel, −1 less, 0 either): a candidate fitted the other way is not
    this effect (ident.diagnosis); enters how the effect enters the model, which decides how the diagnosis tests it
    (ident.diagnosis.entries): "additive" its columns added as inputs; "scales_fuel" when it multiplies the fuel, y
    (1 + m x) — a regeneration's post-injection, enrichment when cold or in thin air, no injection at all on
    overrun: the diagnosis then tests x and x·ŷ, ŷ the model's simulated fuel (the gradient of y (1 + m x) at m = 0,
    dynamics included), and judges the sign on x·ŷ; `build`'s columns (x, x·ñ, x·T̃ with their own dynamics, and on
    an engine model x·m, ident.modeldata.map_scaled) are what a refit adds; "torque" when the regressor is a torque
    (in the model's torque unit per unit of its coefficient) the engine delivers and the bus does not report: the
    fuel burns for it through the model's torque path, and the diagnosis tests that one column, B_T/F_T x; "shift"
    the fuel signal's delay."""

    id: str
    name: str
    physics: str
    signals: tuple[str, ...]
    spns: tuple[int, ...]
    form: str
    build: Callable | None = field(default=None, compare=False, repr=False)
    orders: tuple[int, int, int] = (1, 1, 0)
    lags: tuple[int, ...] = (0, 1, 2)
    sign: int = 0
    enters: str = "additive"
    template: str | None = None  # an engineer-defined effect's explanation (ident.effectfile)
    source: str = ""  # where an effect defined outside the catalogue comes from: its file or plug-in
    definition: dict | None = field(default=None, compare=False, repr=False)  # its effect-file table
    zero: bool = True  # x = 0 means no effect (a deficit, a state); False for a bus signal's raw value (0 °C is arbitrary)
    # a parameter the regressors depend on, fitted on the data when not given: ds → its JSON-ready value (a raw bus
    # signal that scales the fuel is centred, x − x_ref: x_ref [signal unit], `centred`; the engine's map)
    reference: Callable | None = field(default=None, compare=False, repr=False)
    # (effect, parameter) → the effect with that parameter (default `centred`)
    bind: Callable | None = field(default=None, compare=False, repr=False)


@dataclass
class Regressors:
    """Columns x (N × k) of one effect on the dataset grid with a name and a unit per column; orders (nb, nf, nk)
    per column when they differ from the effect's own (Effect.orders)."""

    x: np.ndarray
    names: tuple[str, ...]
    units: tuple[str, ...]
    orders: tuple[tuple[int, int, int], ...] | None = None


# ---- helpers over dataset arrays ------------------------------------------------------------------------

@functools.lru_cache(maxsize=1)
def _dbc_spns() -> dict[str, int]:
    db = cantools.database.load_file(str(FMS_DBC))
    return {f"{m.name}.{s.name}": s.spn for m in db.messages for s in m.signals if s.spn is not None}


def spn_of(signal: str) -> int | None:
    """The SPN of a DBC signal named MESSAGE.Signal (fuelid/dbc/fms.dbc), None when it has none."""
    return _dbc_spns().get(signal)


def held(x) -> np.ndarray:
    """x with NaN samples replaced by the last finite value before them (the first finite value at the start);
    all-NaN stays all-NaN."""
    x = np.asarray(x, float)
    ok = np.isfinite(x)
    if not ok.any():
        return x.copy()
    idx = np.where(ok, np.arange(x.size), 0)
    np.maximum.accumulate(idx, out=idx)
    idx[: np.argmax(ok)] = np.argmax(ok)
    return x[idx]


def _signal(ds, name: str) -> np.ndarray | None:
    """A bus signal of ds.extra, held across gaps; None when absent or never valid."""
    x = ds.extra.get(name)
    if x is None or not np.isfinite(x[ds.valid]).any():
        return None
    return held(x)


def rate(x, t) -> np.ndarray:
    """dx/dt by central differences over the sample times t [s] (unit of x per s); NaN next to gaps."""
    return np.gradient(np.asarray(x, float), np.asarray(t, float))


def deviations(ds) -> tuple[np.ndarray, np.ndarray]:
    """ñ = speed − u0 [rpm] and T̃ = torque − u0 [Nm or %] from the dataset's operating point."""
    du = ds.u - ds.u0
    return du[:, 0], du[:, 1]


def regime(ds, on: np.ndarray, label: str) -> Regressors:
    """Regressors of an on/off regime: I, I·ñ, I·T̃ (offset and gain changes while the state is on)."""
    n, T = deviations(ds)
    i = np.asarray(on, float)
    return Regressors(np.column_stack([i, i * n, i * T]), (label, f"{label} x speed", f"{label} x torque"),
                      ("1", ds.input_units[0], ds.input_units[1]))


def reference_torque(ds) -> float | None:
    """The engine's reference torque [Nm] (EC1 SPN 544), None when it never arrived."""
    ref = _signal(ds, "EC1.EngReferenceTorque")
    return None if ref is None else float(np.median(ref))


def _percent_torque_in_model_unit(ds, pct: np.ndarray) -> tuple[np.ndarray, str]:
    """A J1939 percent-of-reference-torque signal in the unit of the model's torque input (Nm when known)."""
    ref = reference_torque(ds)
    if ds.input_units[1] == "Nm" and ref:
        return pct * ref / 100.0, "Nm"
    return pct, "%"


# ---- the built-in effects --------------------------------------------------------------------------------

def _inertia(ds):
    domega = rate(held(ds.u[:, 0]) * RPM_TO_RAD_S, ds.t)
    J = _signal(ds, "EC1.EngMomentOfInertia")
    if J is not None and np.nanmedian(J) > 0:
        return Regressors((float(np.nanmedian(J)) * domega)[:, None], ("J_EC1 dω/dt",), ("Nm",))
    return Regressors(domega[:, None], ("dω/dt",), ("rad/s2",))


def _power(ds):
    n, T = ds.u[:, 0], ds.u[:, 1]
    n0, T0 = ds.u0
    if ds.input_units[1] == "Nm":
        p = RPM_TO_RAD_S * ((n * T) - (n0 * T0)) / 1000.0
        return Regressors(p[:, None], ("engine power",), ("kW",))
    return Regressors((n * T - n0 * T0)[:, None], ("speed x torque",), (f"rpm.{ds.input_units[1]}",))


def _map_scales(ds) -> tuple[float, str, float, str]:
    """(speed scale, its unit, torque scale, its unit) of the map's columns: krpm and kNm (100 % of reference torque
    when the model's torque is in %), so every column is of order one."""
    return (1000.0, "krpm") + torque_scale(ds.input_units[1])


MAP_ALIGN_LAGS = 5  # [samples] the static map's start aligns the fuel to the torque within this many samples


def static_engine_map(ds) -> dict:
    """The engine map's start (ident.enginemap.fit_map, as its `to_dict`): the static P-spline of the fuel over the
    valid samples' speed and torque, the fuel advanced by the lag (0 … MAP_ALIGN_LAGS samples) at which it
    correlates best with the torque (the fuel's response lags its demand), within each valid stretch; the plane about
    the dataset's operating point."""
    segs = [s for s in ds.segments() if s.stop - s.start > MAP_ALIGN_LAGS]
    if not segs:
        raise InputError("engine map: no valid stretch of the data is long enough")

    def pairs(k):
        n = np.concatenate([ds.u[s.start: s.stop - k, 0] for s in segs])
        T = np.concatenate([ds.u[s.start: s.stop - k, 1] for s in segs])
        y = np.concatenate([ds.y[s.start + k: s.stop] for s in segs])
        return n, T, y

    def corr(k):
        _, T, y = pairs(k)
        ok = np.isfinite(T) & np.isfinite(y)
        return np.corrcoef(T[ok], y[ok])[0, 1]

    lag = max(range(MAP_ALIGN_LAGS + 1), key=corr)
    n, T, y = pairs(lag)
    return fit_map(n, T, y, tuple(map(float, ds.u0)), float(ds.y0), (*ds.input_units, ds.output_unit)).to_dict()


def _engine_map(ds, fitted: dict | None = None):
    """The engine's own fuelling beyond the model's plane in speed and torque: the static map's part beyond its
    plane, x_map = m(n, T) [fuel unit] (ident.enginemap; `fitted` its to_dict, fitted on ds by `static_engine_map`
    when not given), through one transfer function of unit static gain (ident.hammerstein); and its transient
    fuelling, the extra fuel while the torque builds up faster than the turbocharger's boost: the torque's rise
    r = max(dT/dt, 0) (`torque_rise`) and r·f/f_scale (the surcharge grows with the
    fuel the map gives, f = s(n, T))."""
    emap = EngineMap.from_dict(fitted if fitted is not None else static_engine_map(ds))
    n, T = ds.u[:, 0], ds.u[:, 1]
    # x_map: B/F with a direct term and one pole, the fuel's response to the map being about that of the torque's
    # own path at low order; the transient columns: a first-order lag, the turbocharger's spool-up (a PT1)
    return Regressors(engine_map_columns(emap, n, T, torque_rise(T, ds.t, ds.input_units[1])),
                      MAP_COLUMNS, map_column_units(ds.input_units[1], ds.output_unit),
                      orders=(MAP_ORDERS, RISE_ORDERS, RISE_ORDERS))


MAP_COLUMNS = ("map beyond the plane", "torque rise", "torque rise x map fuel")  # the engine map's input columns


def map_column_units(torque_unit: str, fuel_unit: str) -> tuple[str, str, str]:
    """The units of MAP_COLUMNS for a model's torque unit ('Nm' or '%') and fuel unit."""
    return fuel_unit, f"{torque_scale(torque_unit)[1]}/s", f"{torque_scale(torque_unit)[1]}/s"


def torque_scale(torque_unit: str) -> tuple[float, str]:
    """The torque scale of the map's columns and its unit: kNm for a torque in N·m, 100 % for a torque in %."""
    return (1000.0, "kNm") if torque_unit == "Nm" else (100.0, "100 %")


def torque_rise(T, t, torque_unit: str) -> np.ndarray:
    """The torque's rise r = max(dT/dt, 0) / scale [kNm/s or 100 %/s] of the torque T held across missing samples
    (`held`: a gradient would spread a missing sample to its neighbours), at sample times t [s], by central
    differences (`rate`; one-sided at the ends). r at sample k needs sample k + 1: the online estimator computes it
    one sample late (ident.live)."""
    return np.fmax(rate(held(T), t), 0.0) / torque_scale(torque_unit)[0]  # fmax: 0 where a torque is never known


def engine_map_columns(emap: EngineMap, n, T, rise) -> np.ndarray:
    """The engine map's input columns (N × 3, MAP_COLUMNS) at speeds n [rpm], torques T [torque unit] and torque
    rises r (`torque_rise`): [m(n, T), r, r·s(n, T)/f_scale], m the map beyond its plane, s the map (ident.enginemap)."""
    s = emap(n, T)
    return np.column_stack([emap.beyond_plane(n, T, s), rise, rise * s / emap.fuel_scale])


MAP_ORDERS = (2, 1, 0)  # (nb, nf, nk) of the map input: B_m/F_m normalised to G_m(1) = 1 (ident.hammerstein)
RISE_ORDERS = (1, 1, 0)  # of the torque-rise columns: a first-order lag


def _bind_engine_map(effect, fitted: dict):
    """engine_map with its map given (the model's, from model.info["effect_parameters"]["engine_map"])."""
    return replace(effect, build=functools.partial(_engine_map, fitted=fitted), reference=None)


def _pedal_released(ds) -> np.ndarray | None:
    pedal = _signal(ds, "EEC2.AccelPedalPos1")
    return None if pedal is None else pedal < 1.0


def _idle_speed(ds) -> float:
    idle = _signal(ds, "EC1.EngSpeedAtIdlePoint1")
    return float(np.median(idle)) if idle is not None else float(ds.u0[0])


def _overrun(ds):
    """Motoring: the reported (indicated) torque at most 1 % of the reference torque (its resolution), above idle
    speed, pedal released (EEC2), and the driveline closed — not while the clutch is open (CCVS1 SPN 598) or a
    gear change is under way (ETC2 selected ≠ current gear, and the bin either side): there the torque dips to
    0 but the wheels do not drive the engine, and the fuel still follows its last demand."""
    n, T = ds.u[:, 0], ds.u[:, 1]
    on = (T <= _percent_torque_in_model_unit(ds, 1.0)[0]) & (n > _idle_speed(ds) + 100.0)
    released = _pedal_released(ds)
    if released is not None:
        on &= released
    clutch = _signal(ds, "CCVS1.ClutchSwitch")
    if clutch is not None:
        on &= clutch != 1
    gear, selected = _signal(ds, "ETC2.TransCurrentGear"), _signal(ds, "ETC2.TransSelectedGear")
    if gear is not None and selected is not None:
        shifting = (selected != gear) | np.r_[False, np.diff(gear) != 0]
        on &= ~(shifting | np.r_[shifting[1:], False] | np.r_[False, shifting[:-1]])
    return regime(ds, on, "overrun")


def _idle(ds):
    on = np.abs(ds.u[:, 0] - _idle_speed(ds)) <= 50.0
    v = _signal(ds, "CCVS1.WheelBasedVehicleSpeed")
    if v is not None:
        on &= v < 2.0
    released = _pedal_released(ds)
    if released is not None:
        on &= released
    return regime(ds, on, "idle")


def _gear_shift(ds, after_s: float = 1.5):
    """Two states of a gear change (ETC2): during the shift (selected ≠ current gear: torque ramped down, clutch
    open, engine synchronised) an offset; for after_s [s] after the clutch closes into the new gear (the current
    gear changes to a non-zero one), when torque ramps up with low boost, a regime (offset and gain changes)."""
    gear = _signal(ds, "ETC2.TransCurrentGear")
    if gear is None:
        return None
    closes = np.flatnonzero((np.diff(gear) != 0) & (gear[1:] > 0)) + 1
    after = np.zeros(len(gear), bool)
    width = max(int(round(after_s / ds.Ts)), 1)
    for k in closes:
        after[k: k + width] = True
    selected = _signal(ds, "ETC2.TransSelectedGear")
    during = (selected != gear) if selected is not None else (gear == 0) & (ds.u[:, 0] > _idle_speed(ds) + 100.0)
    reg = regime(ds, after & ~during, "after a shift")
    return Regressors(np.column_stack([reg.x, during]), reg.names + ("shifting",), reg.units + ("1",))


def _state(name, active: Callable, label: str):
    def build(ds):
        x = _signal(ds, name)
        return None if x is None else regime(ds, active(x), label)
    return build


def _warm_coolant_c(theta: np.ndarray) -> float:
    """The coolant temperature the thermostat holds once warm [°C]: the 90th percentile of the trip's coolant
    temperature, at least 80 °C (thermostats open at 80–90 °C; a trip that never warms up still has a deficit)."""
    return max(80.0, float(np.percentile(theta, 90)))


def _cold(ds):
    """Deficit Δθ = max(θ_warm − θ, 0) [K] of the coolant below its warm level (`_warm_coolant_c`) and, since
    friction and enrichment scale the fuel, Δθ·ñ and Δθ·T̃."""
    theta = _signal(ds, "ET1.EngCoolantTemp")
    if theta is None:
        return None
    deficit = np.maximum(_warm_coolant_c(theta[ds.valid]) - theta, 0.0)
    n, T = deviations(ds)
    return Regressors(np.column_stack([deficit, deficit * n, deficit * T]),
                      ("coolant deficit", "coolant deficit x speed", "coolant deficit x torque"),
                      ("K", f"K.{ds.input_units[0]}", f"K.{ds.input_units[1]}"))


def _ambient(ds):
    """Relative air-density deficit δ = 1 − ρ/ρ_ref, ρ = p/(R T) from barometric pressure [kPa] and ambient
    temperature [°C] (ρ_ref at 15 °C and 101.325 kPa; a missing one held at its reference), and δ·ñ, δ·T̃:
    thin air changes the fuel in proportion to the fuel itself."""
    temp, press = _signal(ds, "AMB.AmbientAirTemp"), _signal(ds, "AMB.BarometricPress")
    if temp is None and press is None:
        return None
    temp = np.full(len(ds.t), 15.0) if temp is None else temp
    press = np.full(len(ds.t), 101.325) if press is None else press
    delta = 1.0 - (press / 101.325) * (288.15 / (temp + 273.15))
    n, T = deviations(ds)
    return Regressors(np.column_stack([delta, delta * n, delta * T]),
                      ("air-density deficit", "air-density deficit x speed", "air-density deficit x torque"),
                      ("1", ds.input_units[0], ds.input_units[1]))


def _fan(ds):
    """The fan's torque per kW of its power at full speed, T = 1000 (s/100)³ / ω [Nm/kW] (its power grows with
    the cube of its speed s [%], ω the engine speed [rad/s]), in the model's torque unit per kW; from the drive
    state (engaged: full speed) when the speed is not sent."""
    fan = _signal(ds, "FD.EstPercentFanSpeed")
    if fan is not None:
        share = (fan / 100.0) ** 3
    else:
        state = _signal(ds, "FD.FanDriveState")
        if state is None:
            return None
        share = ((state > 0) & (state < 15)).astype(float)
    torque_nm = 1000.0 * share / (np.maximum(ds.u[:, 0], 300.0) * RPM_TO_RAD_S)
    if ds.input_units[1] == "Nm":
        return Regressors(torque_nm[:, None], ("fan torque per kW of fan power at full speed",), ("Nm/kW",))
    ref = reference_torque(ds)
    return None if not ref else Regressors((100.0 * torque_nm / ref)[:, None],
                                           ("fan torque per kW of fan power at full speed",),
                                           (f"{ds.input_units[1]}/kW",))


def _percent_input(name: str, label: str, absolute: bool = False):
    def build(ds):
        pct = _signal(ds, name)
        if pct is None:
            return None
        x, unit = _percent_torque_in_model_unit(ds, np.abs(pct) if absolute else pct)
        return Regressors(x[:, None], (label,), (unit,))
    return build


EFFECTS: dict[str, Effect] = {e.id: e for e in [
    Effect("inertia", "rotational inertia",
           "The bus reports net (flywheel) torque, but fuel burns for the indicated torque, which also "
           "accelerates the crankshaft and flywheel: T_ind = T_net + J dω/dt, ω [rad/s], J [kg·m²] (seed 2's EB*).",
           ("EEC1.EngSpeed", "EC1.EngMomentOfInertia"), (190, 1794), "input", _inertia, orders=(2, 1, 0),
           lags=(0,), sign=+1, enters="torque"),
    Effect("fuel_delay", "fuel-signal delay",
           "The fuel-rate signal lags speed and torque (fuel-system and ECU filtering; seed 2 found 0.4 s): "
           "y_measured(t) = y(t − τ). Removed by advancing the fuel signal by τ.",
           ("LFE1.EngFuelRate",), (183,), "shift", None, orders=(0, 0, 0), lags=(0,), sign=+1, enters="shift"),
    Effect("overrun_cutoff", "overrun fuel cut-off",
           "With the pedal released above idle speed the engine is motored and injects no fuel; a linear model "
           "extrapolates its torque gain to negative fuel instead.",
           ("EEC1.ActualEngPercentTorque", "EEC2.AccelPedalPos1", "EEC1.EngSpeed", "CCVS1.ClutchSwitch",
            "ETC2.TransCurrentGear", "ETC2.TransSelectedGear"), (513, 91, 190, 598, 523, 524), "regime",
           _overrun, lags=(0,), sign=-1, enters="scales_fuel"),
    Effect("power_nonlinearity", "speed × torque (power) nonlinearity",
           "Fuel follows power P = ω T and the efficiency map, not a plane in speed and torque; the product "
           "term is the first missing term of the map.",
           ("EEC1.EngSpeed", "EEC1.ActualEngPercentTorque"), (190, 513), "nonlinearity", _power, orders=(2, 1, 0)),
    Effect("engine_map", "engine fuel map (the engine's own static map, transient fuelling)",
           "A real engine's fuel map is curved: its efficiency varies over speed and torque, so fuel is not a "
           "plane in them; and while the torque builds up the turbocharger lags and the engine burns more per "
           "unit of torque than its steady map says (VECTO's WHTC correction). The map term is the engine's static "
           "map beyond a plane, a smooth monotone surface over speed and torque (ident.enginemap) through one "
           "transfer function of unit gain, identified jointly with the model's dynamics (ident.hammerstein), and "
           "the torque's rise (r, r·f) through a first-order lag.",
           ("EEC1.EngSpeed", "EEC1.ActualEngPercentTorque"), (190, 513),
           "nonlinearity", _engine_map, orders=MAP_ORDERS, lags=(0,), reference=static_engine_map,
           bind=_bind_engine_map),
    Effect("idle_fuelling", "idle fuelling",
           "At idle (vehicle stopped, pedal released) the idle governor fuels to hold speed against friction "
           "and auxiliaries, a different regime from driving.",
           ("EEC1.EngSpeed", "CCVS1.WheelBasedVehicleSpeed", "EEC2.AccelPedalPos1", "EC1.EngSpeedAtIdlePoint1"),
           (190, 84, 91, 188), "regime", _idle, lags=(0,)),
    Effect("gear_shift", "gear-shift transients",
           "During a gear change (ETC2 selected ≠ current gear) traction is interrupted and the engine speed "
           "synchronised; for a moment after the clutch closes into the new gear the torque ramps up with low "
           "boost: more fuel per torque. Torque and fuel do not follow the steady relation in either.",
           ("ETC2.TransCurrentGear", "ETC2.TransSelectedGear"), (523, 524), "regime", _gear_shift, lags=(0,),
           sign=+1),
    Effect("dpf_regeneration", "DPF active regeneration",
           "While the diesel particulate filter regenerates actively (DPFC1 SPN 3700 = 1) the engine injects "
           "extra (post-injection) fuel that produces no torque.",
           ("DPFC1.DPFActiveRegenStatus",), (3700,), "regime",
           _state("DPFC1.DPFActiveRegenStatus", lambda x: x == 1, "DPF regeneration"), lags=(0,), sign=+1,
           enters="scales_fuel"),
    Effect("cold_engine", "cold engine (coolant temperature)",
           "Below operating temperature (the coolant's warm level, 80–90 °C) friction is higher and the ECU "
           "enriches: extra fuel grows with the coolant-temperature deficit and with the fuel itself.",
           ("ET1.EngCoolantTemp",), (110,), "input", _cold, lags=(0,), sign=+1, enters="scales_fuel"),
    Effect("ambient", "ambient temperature and pressure",
           "Air density ρ = p/(R T) (ambient temperature, barometric pressure) changes charge air, boost and "
           "pumping work: thin (warm, high) air changes the fuel in proportion to the fuel.",
           ("AMB.AmbientAirTemp", "AMB.BarometricPress"), (171, 108), "input", _ambient, lags=(0,), sign=+1,
           enters="scales_fuel"),
    Effect("engine_fan", "engine fan",
           "A viscous or clutched engine fan takes power ∝ (fan speed)³ from the crankshaft that the reported "
           "torque does not include.",
           ("FD.EstPercentFanSpeed", "FD.FanDriveState"), (975, 977), "input", _fan, lags=(0,), sign=+1,
           enters="torque"),
    Effect("retarder", "retarder / engine brake",
           "While the retarder or engine brake works (ERC1 SPN 520) no fuel is injected and the engine absorbs "
           "torque.",
           ("ERC1.ActualRetarderPercentTorque",), (520,), "input",
           _percent_input("ERC1.ActualRetarderPercentTorque", "retarder torque", absolute=True)),
    Effect("pto", "power take-off",
           "A PTO (CCVS1 PTO governor state SPN 976 active) drives equipment from the engine, usually at a "
           "governed speed: a different fuelling regime.",
           ("CCVS1.PTOGovernorState",), (976,), "regime",
           _state("CCVS1.PTOGovernorState", lambda x: (x > 0) & (x < 31), "PTO active"), lags=(0,)),
    Effect("friction", "engine friction",
           "Nominal friction torque (EEC3 SPN 514) changes with speed and temperature; fuel burns for it.",
           ("EEC3.NominalFrictionPercentTorque",), (514,), "input",
           _percent_input("EEC3.NominalFrictionPercentTorque", "friction torque")),
]}
ALIASES = {"coolant_temperature": "cold_engine", "fan": "engine_fan"}


# ---- generic candidates: every other decoded bus signal, in every form an effect takes ---------------------

def scaling(ds, x: np.ndarray, label: str, unit: str) -> Regressors:
    """The columns a refit adds for an effect that scales the fuel, y (1 + m x): x, x·ñ, x·T̃ (the first-order
    terms of y (1 + m x) in the model's inputs, ñ and T̃ their deviations from the operating point)."""
    n, T = deviations(ds)
    return Regressors(np.column_stack([x, x * n, x * T]), (label, f"{label} x speed", f"{label} x torque"),
                      (unit, f"{unit}.{ds.input_units[0]}", f"{unit}.{ds.input_units[1]}"))


@functools.lru_cache(maxsize=1)
def _dbc_units() -> dict[str, tuple[str, float]]:
    db = cantools.database.load_file(str(FMS_DBC))
    return {f"{m.name}.{s.name}": (s.unit or "", float(s.scale)) for m in db.messages for s in m.signals}


def _is_state(signal: str, values: np.ndarray, max_states: int) -> bool:
    """Whether a bus signal is an enumeration (a mode, a switch, a status) rather than a physical quantity: in the
    DBC, no unit and whole raw steps (a temperature sent in whole °C is still a quantity); a signal the DBC does
    not know, whole values only. Either way at most max_states distinct values."""
    if values.size > max_states or not np.all(values == np.round(values)):
        return False
    unit, scale = _dbc_units().get(signal, ("", 1.0))
    return not unit and scale == round(scale)


def _torque_unit_factor(signal: str) -> str | None:
    """How a bus signal is a torque, from its DBC unit and name: "Nm"; "%" of the reference torque (J1939's
    percent-torque signals, e.g. EEC3 SPN 2978 parasitic losses); "kW", a power the engine delivers; None when it is
    neither (a torque form for it could never apply, and would only add to the multiple-testing count)."""
    unit, _ = _dbc_units().get(signal, ("", 1.0))
    if unit in ("Nm", "kW"):
        return unit
    return "%" if unit == "%" and "PercentTorque" in signal else None


def _as_model_torque(ds, x: np.ndarray, kind: str) -> tuple[np.ndarray, str] | None:
    """A torque-like signal x (Nm, % of the reference torque, or kW) in the unit of the model's torque input; None
    when it cannot be converted (a percent model without the reference torque)."""
    if kind == "%":
        return _percent_torque_in_model_unit(ds, x)
    nm = x if kind == "Nm" else 1000.0 * x / (np.maximum(ds.u[:, 0], 300.0) * RPM_TO_RAD_S)  # P/ω [Nm]
    if ds.input_units[1] == "Nm":
        return nm, "Nm"
    ref = reference_torque(ds)
    return (100.0 * nm / ref, ds.input_units[1]) if ref else None


def _median(signal: str):
    def reference(ds) -> float:
        return float(np.nanmedian(ds.extra[signal][ds.valid]))
    return reference


def centred(effect: Effect, ref: float) -> Effect:
    """A generic ``scales:SIG`` of a physical quantity centred on ref [the signal's unit]: x − ref scales the fuel.
    With x's arbitrary origin (0 °C) its mean level times the fuel would be a change of the model's own gains,
    which x·ñ and x·T̃ with their own dynamics fit badly and carry to another day with that day's level; centred
    on a level kept with the model (ident.modeldata records it), every data set is centred alike."""
    return replace(effect, build=_generic_build(effect.signals[0], "scales", ref=ref), reference=None)


def _generic_build(signal: str, form: str, values=(), torque: str | None = None, ref: float | None = None):
    def build(ds):
        x = _signal(ds, signal)
        if x is None:
            return None
        unit = _dbc_units().get(signal, ("", 1.0))[0]
        if form == "level":
            return Regressors(x[:, None], (signal,), (unit,))
        if form == "rate":
            return Regressors(rate(x, ds.t)[:, None], (f"d/dt {signal}",), (f"{unit}/s" if unit else "1/s",))
        if form == "state":
            return Regressors(np.column_stack([x == v for v in values]).astype(float),
                              tuple(f"{signal} = {v:g}" for v in values), ("1",) * len(values))
        if form == "scales":
            r = _median(signal)(ds) if ref is None else ref
            return scaling(ds, x - r, f"{signal} - {r:g}", unit)
        converted = _as_model_torque(ds, x, torque)
        return None if converted is None else Regressors(converted[0][:, None], (signal,), (converted[1],))
    return build


def _quadratic_surface(ds) -> np.ndarray:
    """Columns of a static quadratic map of speed and torque beyond a plane, over the operating point: ñ·T̃, ñ², T̃²
    (krpm and kNm, or 100 %), the relative load L = T / T_max(n) (EEC2 SPN 92) when logged, and the torque's rise r
    = max(dT/dt, 0) and r·T̃."""
    n, T = deviations(ds)
    sn, _, sT, _ = _map_scales(ds)
    n, T = n / sn, T / sT
    cols = [n * T, n * n, T * T]
    load = _signal(ds, "EEC2.EngPercentLoadAtCurrentSpeed")
    if load is not None:
        cols.append(load / 100.0)
    rise = np.maximum(rate(held(ds.u[:, 1]), ds.t), 0.0) / sT
    return np.column_stack(cols + [rise, rise * T])


def share_beyond_inputs(ds, signal: str) -> float:
    """The share [1] of bus signal `signal`'s variance that a static map of the model's inputs leaves: 1 − R² of
    its values regressed by least squares on 1, ñ, T̃ and a quadratic map beyond them (`_quadratic_surface`), over
    the valid samples where it is known; 0 when it is constant there. A desired engine speed that is the engine
    speed but in neutral leaves a fraction of a %: whatever it explains, speed and torque could. (A low-order
    surface on purpose: a signal that drifts over the trip is not explained by chance by a rich one.)"""
    n, T = deviations(ds)
    sn, _, sT, _ = _map_scales(ds)
    basis = np.column_stack([np.ones_like(n), n / sn, T / sT, _quadratic_surface(ds)])
    x = ds.extra[signal]
    ok = ds.valid & np.isfinite(x) & np.isfinite(basis).all(axis=1)
    xc = x[ok] - x[ok].mean()
    total = float(xc @ xc)
    if total == 0.0:
        return 0.0
    r = x[ok] - basis[ok] @ np.linalg.lstsq(basis[ok], x[ok], rcond=None)[0]
    return float(r @ r) / total


def generic_effects(ds, max_states: int = 16) -> list[Effect]:
    """Candidates from every bus signal in ds.extra that no built-in effect uses and that is not computed from
    the fuel (OUTPUT_DERIVED_SPNS, the flow meter), in every form an effect takes (Effect.enters) that can apply
    to it:

    - a physical quantity (`_is_state`: a DBC unit, or values that are not a few whole numbers): ``level:SIG``
      and ``rate:SIG`` (additive), ``scales:SIG`` (scales the fuel: tested as x and x·ŷ, as cold engine and
      ambient air are; x centred on its median, `centred`), and, for a torque or a power (DBC unit Nm, kW, or a J1939 percent torque),
      ``torque:SIG`` (a torque the bus does not report, through the model's torque path, as the engine fan is);
    - an enumeration: ``state:SIG`` (indicators of its three most frequent non-modal values, additive). Not as a
      regime scaling the fuel "off its most frequent value": that lumps unordered states, and on the simulator
      the retarder's mode (on exactly while the engine is motored) took overrun cut-off's place with it and
      raised another day's error (README, issue 16).

    Signals valid on less than half of the valid samples, or constant, are left out. They are tested in the same
    Holm family as the built-in effects (ident.diagnosis.ranking), so every form counts in the correction."""
    claimed = {s for e in EFFECTS.values() for s in e.signals}
    out = []
    for sig in sorted(ds.extra):
        spn = spn_of(sig)
        if sig in claimed or sig.startswith("flowmeter.") or spn in OUTPUT_DERIVED_SPNS:
            continue
        x = ds.extra[sig][ds.valid]
        fin = x[np.isfinite(x)]
        if fin.size < 0.5 * max(x.size, 1) or np.ptp(fin) == 0:
            continue
        spns = (spn,) if spn is not None else ()
        vals, counts = np.unique(fin, return_counts=True)

        def effect(form, name, physics, kind, enters, values=(), torque=None):
            return Effect(f"{form}:{sig}", name, f"Bus signal {sig} {physics}.", (sig,), spns, kind,
                          _generic_build(sig, form, values, torque), lags=(0,) if enters != "additive" or
                          kind == "regime" else (0, 1, 2), enters=enters, zero=kind == "regime",
                          reference=_median(sig) if form == "scales" else None)

        if _is_state(sig, vals, max_states):
            by_count = tuple(float(v) for v in vals[np.argsort(-counts, kind="stable")])
            out.append(effect("state", f"state of {sig}", "in each of its states", "regime", "additive", by_count[1:4]))
            continue
        out += [effect("level", f"level of {sig}", "(its value)", "input", "additive"),
                effect("rate", f"rate of change of {sig}", "(its time derivative)", "input", "additive"),
                effect("scales", f"fuel scaled by {sig}", "scaling the fuel, y (1 + m x)", "input", "scales_fuel")]
        torque = _torque_unit_factor(sig)
        if torque is not None:
            out.append(effect("torque", f"torque the bus does not report: {sig}",
                              "as a torque the engine delivers and the bus does not report", "input", "torque",
                              torque=torque))
    return out


PLUGIN_GROUP = "fuelid.effects"


@functools.lru_cache(maxsize=1)
def plugin_effects() -> tuple[Effect, ...]:
    """Effects installed packages define in Python: each entry point of the group `fuelid.effects` names an
    Effect or a list of Effects (e.g. ``[project.entry-points."fuelid.effects"] mine = "pkg.mod:EFFECTS"``)."""
    out = []
    for ep in importlib.metadata.entry_points(group=PLUGIN_GROUP):
        try:
            obj = ep.load()
        except Exception as exc:  # a broken plug-in is the user's input: say which one
            raise InputError(f"effect plug-in {ep.name} ({ep.value}): cannot load ({exc})") from None
        items = [obj] if isinstance(obj, Effect) else list(obj) if isinstance(obj, (list, tuple)) else [None]
        if not all(isinstance(e, Effect) for e in items):
            raise InputError(f"effect plug-in {ep.name} ({ep.value}): not an Effect or a list of Effects")
        out += [e if e.source else replace(e, source=f"plug-in {ep.name}") for e in items]
    return tuple(out)


def get_effect(effect_id: str, ds=None, defined=()) -> Effect:
    """The effect with this id: built-in (or an alias), one of `defined` (effects the engineer defined,
    ident.effectfile), an installed plug-in's (`plugin_effects`), else a generic ``level:``/``rate:``/``scales:``/``torque:``/``state:SIG``
    (needs ds to see the signal)."""
    effect_id = ALIASES.get(effect_id, effect_id)
    if effect_id in EFFECTS:
        return EFFECTS[effect_id]
    for e in (*defined, *plugin_effects()):
        if e.id == effect_id:
            return e
    if ds is not None:
        for e in generic_effects(ds):
            if e.id == effect_id:
                return e
    known = ", ".join(EFFECTS)
    raise InputError(f"unknown effect {effect_id!r}: built in are {known}; any logged signal SIG also as "
                     "level:SIG, rate:SIG, scales:SIG, torque:SIG (a torque or power) or state:SIG; an effect you "
                     "define, from its --effects-file")


def parse_effect(spec: str) -> tuple[str, float | None]:
    """'ID' or 'ID=VALUE' (fuel_delay=0.4 fixes the shift [s]) → (id, value or None)."""
    name, _, value = spec.partition("=")
    return ALIASES.get(name.strip(), name.strip()), (float(value) if value else None)
