"""Synthetic trips of a Hammerstein engine (tests of ident.enginemap, ident.hammerstein, ident.modelchoice).

    y = y0 + G_n ñ + G_T T̃ + G_m k·curve(n, T) + C/D e,      Ts = 0.3 s

G_n, G_T, C/D those of tests.ident.hidden (steady gains 0.0019 L/h per rpm and 0.03 L/h per Nm about 600 rpm,
112 Nm), G_m = 0.8 (0.6 + 0.4 q⁻¹)/(1 − 0.2 q⁻¹) (unit static gain), the curvature

    curve(n, T) = 6 ((T − 600)/1000)² + 2 ((n − 1200)/600)² (T/1700)      [L/h]

monotone in torque with the plane's 0.03 L/h per Nm; k = 0 is the paper's linear model. Torque stays above 20 Nm
(the engine fuels: no cut-off in these data). The dataset's operating point is the idle one, (600 rpm, 112 Nm) and
the steady-state fuel there (as ident.dataset takes it from the idle samples).
"""
from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

from fuelid.ident.dataset import Dataset
from tests.ident.hidden import TRUE, _held, _lag

TS = 0.3
B_MAP, F_MAP = np.array([0.48, 0.32]), np.array([1.0, -0.2])


def curve(n, T) -> np.ndarray:
    """The curvature beyond the plane [L/h] at speed n [rpm] and torque T [Nm]."""
    n, T = np.asarray(n, float), np.asarray(T, float)
    return 6.0 * ((T - 600.0) / 1000.0) ** 2 + 2.0 * ((n - 1200.0) / 600.0) ** 2 * (T / 1700.0)


def steady_state(n, T, k: float = 1.0) -> np.ndarray:
    """The true steady-state fuel [L/h]."""
    return TRUE.y0 + 0.0019 * (np.asarray(n) - 600.0) + 0.03 * (np.asarray(T) - 112.0) + k * curve(n, T)


def noise_floor(noise: float = 0.3) -> float:
    """The RMS [L/h] of the noise C/D e in `trip` (e of standard deviation noise/1.3): what no simulation can lose."""
    impulse = lfilter(TRUE.C, TRUE.D, np.r_[1.0, np.zeros(200)])
    return noise / 1.3 * float(np.sqrt(np.sum(impulse ** 2)))


def trip(k: float = 1.0, n: int = 12000, seed: int = 0, noise: float = 0.3, fan_kw: float = 0.0) -> Dataset:
    """A Dataset of n samples of the engine above with curvature k; with fan_kw [kW] a fan that takes
    fan_kw (s/100)³ from the crankshaft at its speed s [%] (FD.EstPercentFanSpeed, on in held stretches of about a
    third of the trip): the engine delivers T + T_fan, the bus reports T, and the fuel burns for both."""
    rng = np.random.default_rng(seed)
    speed = np.clip(600 + _lag(_held(n, rng, 0, 1300), 2.0) + _lag(rng.normal(0, 30, n), 1.0), 550, 2000)
    torque = np.clip(112 + _lag(_held(n, rng, -90, 1550), 0.6) + _lag(rng.normal(0, 60, n), 0.5), 20, 1700)
    fan_rng = np.random.default_rng([seed, 1])  # its own stream: the trips without a fan stay as they were
    fan = np.where(_held(n, fan_rng, 0, 1) > 0.65, _held(n, fan_rng, 50, 100), 0.0) if fan_kw else np.zeros(n)
    engine = torque + 1000.0 * fan_kw * (fan / 100.0) ** 3 / (speed * 2.0 * np.pi / 60.0)
    clean = TRUE.y0 + lfilter(TRUE.B[0], TRUE.F[0], speed - 600) + lfilter(TRUE.B[1], TRUE.F[1], engine - 112)
    clean = clean + k * lfilter(B_MAP, F_MAP, curve(speed, engine))
    y = clean + lfilter(TRUE.C, TRUE.D, rng.normal(0, noise / 1.3, n))
    t = np.arange(n) * TS
    return Dataset(Ts=TS, t=t, u=np.column_stack([speed, torque]), y=y, input_names=("EEC1.EngSpeed", "EngTorque"),
                   input_units=("rpm", "Nm"), output_name="LFE1.EngFuelRate", output_unit="L/h",
                   u0=np.array([600.0, 112.0]), y0=float(steady_state(600.0, 112.0, k)), valid=np.ones(n, bool),
                   cycle=(np.arange(n) // int(600 / TS)).astype(np.int64),
                   extra={"FD.EstPercentFanSpeed": fan} if fan_kw else {})
