"""Physical effects a two-input (engine speed, torque) linear fuel model lacks.

Each effect is switchable with a magnitude (`--effect NAME[=MAGNITUDE]`) and is visible on the bus where it
physically would be (the `signals`/`spns` below). Three kinds:

- hidden torque: the engine produces torque the bus does not report (fan, inertia): fuel follows the true
  indicated torque, SPN 513 reports less;
- fuel change: the engine injects fuel that produces no reported torque (DPF post-injection, cold enrichment,
  shift transients, air density, power non-linearity) or none at all (overrun cut-off);
- signal path: the reported fuel rate lags the engine (fuel-signal delay).

The fuel-change functions return a factor or an addend on the fine time grid; `sim.trip` applies them in the
order additive, multiplicative, cut-off, then the delay.
"""
from dataclasses import dataclass

import numpy as np

from fuelid.errors import InputError
from fuelid.sim.thermal import THERMOSTAT_C


@dataclass(frozen=True)
class Effect:
    name: str
    default: float
    unit: str
    signals: tuple   # DBC message.signal names where the effect shows on the bus
    spns: tuple
    description: str


EFFECTS = {e.name: e for e in [
    Effect("fuel_delay", 0.4, "s", ("LFE1.EngFuelRate",), (183,),
           "The reported fuel rate lags the engine by a pure delay (fuel-meter and signal-path dynamics); "
           "seed paper 001 found 0.4 s on a test bed, real J1939 logs show about 0.17 s."),
    Effect("inertia", 3.2, "kg.m2", ("EEC1.ActualEngPercentTorque", "EEC1.EngSpeed", "EC1.EngMomentOfInertia"),
           (513, 190, 1794),
           "The engine reports net torque T_ind - J dω/dt (what reaches the clutch plus friction) while the "
           "fuel follows the indicated torque; the magnitude is the J the ECU nets out (the paper engine's own "
           "3.2 kg·m² by default). The engine's mechanics are unchanged: it keeps its own inertia, which EC1 "
           "SPN 1794 reports."),
    Effect("overrun_cutoff", 1.0, "fraction of fuel cut", ("EEC2.AccelPedalPos1", "EEC2.AccelPedal1LowIdleSwitch",
                                                             "EEC1.ActualEngPercentTorque", "EEC1.EngSpeed"),
           (91, 558, 513, 190),
           "No injection while the engine is motoring above 800 rpm with the pedal released (fuel cut-off on "
           "overrun): the fuel rate is exactly zero where a linear model still predicts some."),
    Effect("power_nonlinearity", 8.0, "L/h (kg/h gas) at 1000 rpm above idle and 100 % torque",
           ("EEC1.EngSpeed", "EEC1.ActualEngPercentTorque"), (190, 513),
           "Fuel grows with the product of speed and torque (power), not only with each: "
           "Δf = m (n - n_idle)/1000 rpm x T/100 %."),
    Effect("dpf_regeneration", 0.10, "fraction of extra fuel while active", ("DPFC1.DPFActiveRegenStatus",), (3700,),
           "Active regeneration of the diesel particulate filter: late post-injection that makes heat, not "
           "torque, while SPN 3700 reports 'active' (events of about 20 min)."),
    Effect("cold_engine", 0.15, "fraction of extra fuel at 70 K below thermostat temperature",
           ("ET1.EngCoolantTemp",), (110,),
           "Cold start: the coolant (SPN 110) warms from ambient; friction and enrichment add fuel in "
           "proportion to how far the coolant is below the thermostat temperature."),
    Effect("engine_fan", 25.0, "kW fan power at 100 % fan speed", ("FD.EstPercentFanSpeed", "FD.FanDriveState"),
           (975, 977),
           "The viscous fan engages when the coolant is hot (SPN 977 state 4); its power P = m (s/100)³ is "
           "produced by the engine but not included in the reported torque."),
    Effect("gear_shift", 0.3, "fraction of extra fuel at the end of a shift (decays with τ = 0.5 s)",
           ("ETC2.TransCurrentGear", "ETC2.TransSelectedGear", "ETC2.TransActualGearRatio"), (523, 524, 526),
           "After the clutch closes the torque ramps up with low boost pressure: more fuel per torque for "
           "about 1.5 s after each gear change."),
    Effect("ambient", 0.5, "relative fuel change per relative air-density drop",
           ("AMB.AmbientAirTemp", "AMB.BarometricPress"), (171, 108),
           "Thin (warm, high) air lowers boost and efficiency: f x (1 + m (ρ_ref - ρ)/ρ_ref), ρ = p/(R T) from "
           "SPN 108 and SPN 171, ρ_ref at 15 °C and 101.325 kPa."),
]}

# Generic effects: physics fuelid's effect catalogue (ident.effects) has no entry for, acting only through bus
# signals the DBC decodes, so the diagnosis can find them only as "some bus signal" or as an effect the engineer
# defines (ident.effectfile).
GENERIC_EFFECTS = {e.name: e for e in [
    Effect("hot_intake_air", 0.15, "fraction of extra fuel per 10 K of intake air above 30 °C",
           ("AMB.EngAirInletTemp",), (172,),
           "Hot charge air is thin: while the intake air (SPN 172, which follows the load over about 30 s) is "
           "above 30 °C the engine burns more fuel for the same torque, f x (1 + m max(T_inlet - 30 °C, 0)/10 K) "
           "(the default is strong on purpose: a test of whether the diagnosis finds the form, not of its "
           "detection limit)."),
    Effect("auxiliary_load", 80.0, "Nm of auxiliary torque while the auxiliary runs",
           ("EEC3.EstEngParasiticLossesPercentTorque",), (2978,),
           "An auxiliary (air-conditioning or air compressor) cycles on and off (episodes of 1-4 min, off 1-6 "
           "min); the ECU's parasitic-loss estimate (EEC3 SPN 2978) includes its torque, the actual engine torque "
           "(EEC1 SPN 513) does not, and the fuel burns for it."),
]}
ALL_EFFECTS = {**EFFECTS, **GENERIC_EFFECTS}
"""Every effect `fuelid simulate --effect` takes: the catalogued ones and the generic ones."""

AIR_DENSITY_REF_KG_M3 = 101325.0 / (287.05 * 288.15)
HOT_INTAKE_LEVEL_C = 30.0
OVERRUN_MIN_RPM = 800.0
SHIFT_TRANSIENT_TAU_S = 0.5
SHIFT_TRANSIENT_S = 1.5
COLD_SPAN_K = 70.0


def parse_effects(specs) -> dict:
    """{name: magnitude} from strings "NAME" or "NAME=MAGNITUDE"; InputError names the bad one."""
    out = {}
    for spec in specs or ():
        name, _, value = spec.partition("=")
        name = name.strip()
        if name not in ALL_EFFECTS:
            raise InputError(f"unknown effect {name!r}; known: {', '.join(ALL_EFFECTS)}")
        try:
            out[name] = float(value) if value else ALL_EFFECTS[name].default
        except ValueError:
            raise InputError(f"effect {name}: magnitude {value!r} is not a number") from None
        if out[name] < 0:
            raise InputError(f"effect {name}: magnitude must be >= 0")
    return out


def describe(effects: dict) -> list:
    """Truth-file entries: name, magnitude, unit, signals, SPNs, explanation."""
    return [{"name": name, "magnitude": m, "unit": ALL_EFFECTS[name].unit,
             "signals": list(ALL_EFFECTS[name].signals), "spns": list(ALL_EFFECTS[name].spns),
             "description": ALL_EFFECTS[name].description, **({"generic": True} if name in GENERIC_EFFECTS else {})}
            for name, m in effects.items()]


# --- hidden torque [Nm] ------------------------------------------------------------------------------------

def fan_torque_nm(fan_power_kw: float, fan_speed_pct, engine_speed_rpm):
    """T_fan = P / ω = m (s/100)³ x 1000 / (2π n/60)  [Nm], s fan speed [%], n engine speed [rpm]."""
    omega = np.maximum(np.asarray(engine_speed_rpm), 300.0) * 2.0 * np.pi / 60.0
    return fan_power_kw * 1000.0 * (np.asarray(fan_speed_pct) / 100.0) ** 3 / omega


def inertia_torque_nm(inertia_kgm2: float, engine_speed_rpm, dt: float):
    """J dω/dt [Nm] with ω = 2π n/60, the derivative by central differences over ±20 ms."""
    omega = np.asarray(engine_speed_rpm) * 2.0 * np.pi / 60.0
    k = max(1, int(round(0.02 / dt)))
    d = np.zeros_like(omega)
    d[k:-k] = (omega[2 * k:] - omega[:-2 * k]) / (2 * k * dt)
    return inertia_kgm2 * d


# --- fuel changes ----------------------------------------------------------------------------------------

def power_nonlinearity_add(m: float, engine_speed_rpm, torque_pct, idle_rpm: float):
    """Δf = m (n - n_idle)/1000 x T/100  [fuel unit]."""
    return m * (np.asarray(engine_speed_rpm) - idle_rpm) / 1000.0 * np.asarray(torque_pct) / 100.0


def dpf_factor(m: float, regen_active):
    """1 + m while SPN 3700 is active, else 1."""
    return 1.0 + m * np.asarray(regen_active, float)


def cold_factor(m: float, coolant_c):
    """1 + m clip((T_thermostat - T_coolant)/70 K, 0, 1)."""
    return 1.0 + m * np.clip((THERMOSTAT_C - np.asarray(coolant_c)) / COLD_SPAN_K, 0.0, 1.0)


def shift_factor(m: float, t_s, shift_end_s):
    """1 + m exp(-(t - t_end)/τ) for 0 <= t - t_end < 1.5 s after the end of each shift t_end [s]."""
    t_s = np.asarray(t_s)
    since = np.full(len(t_s), np.inf)
    ends = np.asarray(shift_end_s)
    if len(ends):
        k = np.searchsorted(ends, t_s, side="right") - 1
        valid = k >= 0
        since[valid] = t_s[valid] - ends[k[valid]]
    return 1.0 + np.where(since < SHIFT_TRANSIENT_S, m * np.exp(-since / SHIFT_TRANSIENT_TAU_S), 0.0)


def ambient_factor(m: float, air_density_kg_m3):
    """1 + m (ρ_ref - ρ)/ρ_ref."""
    return 1.0 + m * (AIR_DENSITY_REF_KG_M3 - np.asarray(air_density_kg_m3)) / AIR_DENSITY_REF_KG_M3


def overrun_mask(indicated_torque_pct, pedal, engine_speed_rpm, clutch_closed):
    """True where the engine is motoring (no indicated torque) above 800 rpm, pedal released, clutch closed."""
    return ((np.asarray(indicated_torque_pct) <= 0.5) & (np.asarray(pedal) <= 0.0)
            & (np.asarray(engine_speed_rpm) > OVERRUN_MIN_RPM) & np.asarray(clutch_closed))


def overrun_factor(m: float, mask):
    """1 - m where `overrun_mask`, else 1."""
    return 1.0 - m * np.asarray(mask, float)


def hot_intake_factor(m: float, inlet_c):
    """1 + m max(T_inlet - 30 °C, 0)/10 K."""
    return 1.0 + m * np.maximum(np.asarray(inlet_c) - HOT_INTAKE_LEVEL_C, 0.0) / 10.0


def auxiliary_episodes(t_s, rng: np.random.Generator, on_s=(60.0, 240.0), off_s=(60.0, 360.0)):
    """Auxiliary running (bool per sample): alternating off and on episodes of uniform random lengths [s],
    starting off."""
    t_s = np.asarray(t_s)
    on = np.zeros(len(t_s), bool)
    edge = rng.uniform(*off_s)
    while edge < t_s[-1]:
        length = rng.uniform(*on_s)
        on |= (t_s >= edge) & (t_s < edge + length)
        edge += length + rng.uniform(*off_s)
    return on


def delayed(t_s, values, delay_s: float):
    """values(t - delay) by linear interpolation, the first value held before the start."""
    return np.interp(np.asarray(t_s) - delay_s, t_s, values)


def dpf_events(t_s, rng: np.random.Generator, event_s: float = 1200.0):
    """SPN 3700 active (bool per sample): one regeneration of `event_s` [s] at a random time between 20 % and
    90 % of the trip; on trips shorter than two events it covers the middle half instead."""
    t_s = np.asarray(t_s)
    end = t_s[-1]
    if end > 2.0 * event_s:
        start, length = rng.uniform(0.2 * end, 0.9 * end - event_s), event_s
    else:
        start, length = 0.25 * end, 0.5 * end
    return (t_s >= start) & (t_s < start + length)
