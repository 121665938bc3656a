"""Synthetic datasets with a known Box-Jenkins fuel model and optionally one hidden physical effect
(tests of ident.effects and ident.diagnosis).

Truth: y = y0 + Gn ñ + GT T̃ + C/D e at Ts = 0.3 s, ñ [rpm] and T̃ [Nm] deviations from idle (600 rpm,
112 Nm), Gn = 0.0019 q⁻² (1 − 0.5)/(1 − 0.5 q⁻¹) [L/h per rpm], GT = 0.03 (0.6 + 0.4 q⁻¹)/(1 − 0.2 q⁻¹)·0.8
[L/h per Nm] (steady gains 0.0019 and 0.03), noise C/D = (1 + 0.3 q⁻¹)/(1 − 0.6 q⁻¹) with std ≈ 0.5 L/h.
The bus extras are those a real FMS gateway sends (DBC names), plus unknown signals (random walks) that
should never be flagged. Hidden effects:

- "dpf_regeneration": fuel +11 % while DPFC1.DPFActiveRegenStatus = 1 (two 4-minute regenerations);
- "inertia": the bus torque is net of J dω/dt (J = 3.2 kg·m², EC1 SPN 1794), fuel follows the indicated one;
- "cold_engine": +0.04 L/h per K of coolant below 80 °C (a cold start warming up);
- "fuel_delay": the fuel signal lags by `delay_s` (fractional, spline-interpolated).
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import shift as spline_shift
from scipy.signal import lfilter

from ident.dataset import Dataset
from ident.polymodel import PolyModel, Structure

TS = 0.3
J = 3.2  # kg·m²
TRUE = PolyModel(A=[1.0], B=[[0, 0, 0.0019 * 0.5], [0.03 * 0.8 * 0.6, 0.03 * 0.8 * 0.4]],
                 F=[[1, -0.5], [1, -0.2]], C=[1, 0.3], D=[1, -0.6], Ts=TS, nk=(2, 0),
                 u0=(600.0, 112.0), y0=2.5)
STRUCTURE = Structure(nb=(1, 2), nf=(1, 1), nk=(2, 0), nc=1, nd=1)


def _lag(x, tau):
    a = np.exp(-TS / tau)
    return lfilter([1 - a], [1, -a], x, zi=[a * x[0]])[0]


def _held(n, rng, lo, hi, hold=(3.0, 40.0)):
    out = np.empty(n)
    i = 0
    while i < n:
        k = int(rng.uniform(*hold) / TS)
        out[i:i + k] = rng.uniform(lo, hi)
        i += k
    return out


def make(effect: str | None = None, n: int = 8000, seed: int = 0, noise: float = 0.5, size: float | None = None,
         delay_s: float = 0.4) -> Dataset:
    """A Dataset of n samples (n·0.3 s) with the hidden `effect` (module docstring) of magnitude `size`."""
    rng = np.random.default_rng(seed)
    speed = np.clip(600 + _lag(_held(n, rng, 0, 1300), 2.0) + _lag(rng.normal(0, 30, n), 1.0), 550, 2000)
    torque = np.clip(112 + _lag(_held(n, rng, -100, 1500), 0.6) + _lag(rng.normal(0, 60, n), 0.5), -150, 1700)
    domega = np.gradient(speed * 2 * np.pi / 60, TS)
    t = np.arange(n) * TS
    regen = np.zeros(n)
    for start in (0.2, 0.65):
        a = int(start * n)
        regen[a:a + int(240 / TS)] = 1.0
    coolant = 85 + 3 * np.sin(2 * np.pi * t / 900)
    if effect == "cold_engine":
        coolant = 85 - 60 * np.exp(-t / 600)
    indicated = torque + (J * domega if effect == "inertia" else 0.0)
    clean = TRUE.y0 + lfilter(TRUE.B[0], TRUE.F[0], speed - 600) + lfilter(TRUE.B[1], TRUE.F[1], indicated - 112)
    if effect == "dpf_regeneration":
        clean = clean * (1 + (0.11 if size is None else size) * regen)
    if effect == "cold_engine":
        clean = clean + (0.04 if size is None else size) * np.maximum(80 - coolant, 0)
    e = rng.normal(0, noise / 1.3, n)
    y = clean + lfilter(TRUE.C, TRUE.D, e)
    if effect == "fuel_delay":
        y = spline_shift(y, delay_s / TS, order=3, mode="nearest")
    walk = lambda s: np.cumsum(rng.normal(0, s, n))  # noqa: E731
    extra = {
        "CCVS1.WheelBasedVehicleSpeed": np.clip((speed - 600) / 15, 0, 90),
        "EEC2.AccelPedalPos1": np.clip(torque / 16, 0, 100),
        "ETC2.TransCurrentGear": np.floor(_held(n, rng, 1, 12, (5, 60))),
        "DPFC1.DPFActiveRegenStatus": regen,
        "ET1.EngCoolantTemp": np.round(coolant),
        "ET1.EngOilTemp1": np.round(coolant + 5 + walk(0.02), 1),
        "AMB.AmbientAirTemp": 18 + walk(0.002),
        "AMB.BarometricPress": np.full(n, 99.0),
        "EC1.EngMomentOfInertia": np.full(n, J),
        "EC1.EngReferenceTorque": np.full(n, 1600.0),
        "FD.EstPercentFanSpeed": np.clip(_held(n, rng, -60, 100, (20, 120)), 0, 100),
        "XX.UnknownSignal": walk(1.0),
        "XX.UnknownState": np.floor(_held(n, rng, 0, 3, (5, 60))),
    }
    return Dataset(Ts=TS, t=t, u=np.column_stack([speed, torque]), y=y, input_names=("EEC1.EngSpeed", "EngTorque"),
                   input_units=("rpm", "Nm"), output_name="LFE1.EngFuelRate", output_unit="L/h",
                   u0=np.array([600.0, 112.0]), y0=2.5, valid=np.ones(n, bool),
                   cycle=(np.arange(n) // int(600 / TS)).astype(np.int64), extra=extra)
