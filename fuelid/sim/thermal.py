"""Temperatures and air: ambient conditions along the route, coolant warm-up, the cooling fan.

These are always simulated and always on the bus (AMB, ET1, FD); whether they change the fuel is decided by
the effects in fuelid/sim/effects.py.
"""
import numpy as np
from scipy import signal

from fuelid.sim.driver import lowpass_noise

THERMOSTAT_C = 86.0
"""Coolant temperature the thermostat holds once the engine is warm [°C]."""
FAN_ON_C = 95.0
"""Coolant temperature at which the viscous fan engages [°C] (FD SPN 977 state 4, coolant)."""


def pressure_kpa(altitude_m, offset_kpa: float = 0.0):
    """Barometric pressure of the standard atmosphere p = 101.325 (1 - 2.25577e-5 h)^5.25588 [kPa] plus a
    weather offset [kPa]; h altitude [m]."""
    return 101.325 * (1.0 - 2.25577e-5 * np.asarray(altitude_m)) ** 5.25588 + offset_kpa


def ambient_temperature_c(t_s, altitude_m, start_c: float, drift_c: float, rng: np.random.Generator):
    """T_amb(t) = T_0 + drift t/t_end - 6.5 K/km (h - h_0) + weather noise (std 0.3 K, τ 5 min) [°C]."""
    t_s, altitude_m = np.asarray(t_s), np.asarray(altitude_m)
    dt = t_s[1] - t_s[0]
    weather = 0.3 * lowpass_noise(len(t_s), dt, 300.0, rng)
    return start_c + drift_c * t_s / t_s[-1] - 6.5e-3 * (altitude_m - altitude_m[0]) + weather


def coolant_temperature_c(t_s, fuel_power_kw, ambient_c, start_c: float, fan_on=None):
    """Coolant temperature from a lumped heat balance, on a 1 s grid then interpolated [°C]:

        C dT/dt = k_heat P_fuel - h (T - T_amb),   T ≤ T_thermostat while the fan is off

    P_fuel: fuel power [kW]; C = 120 kJ/K (block and coolant), k_heat = 0.25 (share of fuel power going to
    the coolant), h = 0.15 kW/K (losses with the thermostat shut). While the fan is engaged the coolant is
    above the fan switch-on point (it engaged because of that), otherwise the thermostat caps it.
    Hand-written loop: the thermostat clamp makes the ODE non-linear; at 1 s steps it costs nothing.
    """
    t_s = np.asarray(t_s)
    grid = np.arange(0.0, t_s[-1] + 1.0, 1.0)
    p = np.interp(grid, t_s, fuel_power_kw)
    amb = np.interp(grid, t_s, ambient_c)
    temp = np.empty(len(grid))
    x = start_c
    for k in range(len(grid)):
        x += (0.25 * p[k] - 0.15 * (x - amb[k])) / 120.0
        x = min(x, THERMOSTAT_C)
        temp[k] = x
    coolant = np.interp(t_s, grid, temp)
    if fan_on is not None and np.any(fan_on):
        # The coolant climbs past the switch-on point before the fan engages and falls after it: the fan
        # state smoothed forwards and backwards (τ = 20 s) blends towards FAN_ON_C + 1.5 °C.
        a = np.exp(-(t_s[1] - t_s[0]) / 20.0)
        heat = np.clip(signal.filtfilt([1 - a], [1, -a], fan_on.astype(float)) * 2.0, 0.0, 1.0)
        coolant = coolant + heat * (FAN_ON_C + 1.5 - coolant)
    return coolant


def fan_episodes(t_s, load, rng: np.random.Generator, share: float = 0.15):
    """Fan engaged (bool per sample): episodes of 40-150 s starting where the engine load (0..1, smoothed
    over a minute) is high, covering about `share` of the trip: hard climbs heat the coolant."""
    t_s = np.asarray(t_s)
    dt = t_s[1] - t_s[0]
    n = len(t_s)
    window = max(1, int(60.0 / dt))
    smooth = np.convolve(load, np.ones(window) / window, mode="same")
    on = np.zeros(n, bool)
    candidates = np.argsort(-smooth)
    for start in candidates[:: max(1, int(20.0 / dt))]:
        if on.mean() >= share:
            break
        if on[max(0, start - int(30 / dt)):start + 1].any():
            continue
        length = int(rng.uniform(40.0, 150.0) / dt)
        on[start:start + length] = True
    return on


def fan_speed_pct(on, engine_speed_rpm, dt: float):
    """Estimated fan speed (FD SPN 975) [%]: a viscous fan slips to ~8 % when disengaged and runs at ~1.25 x
    engine speed when engaged (100 % = 2600 rpm fan speed); engagement takes ~3 s (first order)."""
    a = np.exp(-dt / 3.0)
    engagement = signal.lfilter([1 - a], [1, -a], on.astype(float))
    full = np.clip(1.25 * engine_speed_rpm / 2600.0 * 100.0, 0, 100)
    return 8.0 + engagement * (full - 8.0)
