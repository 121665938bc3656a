"""The size of a recommended effect in the model built with it: what the engineer reads beside the evidence, and
what an engineer-defined effect's explanation template is filled with (ident.effectfile).

The effect's fuel contribution over the data, its columns x_j (j ∈ the effect) from 0, simulated from rest on each
valid segment after its first n_start samples:

    c(t) = 1/A(q) Σ_j B_j(q)/F_j(q) x_j(t)      [output unit],

ŷ₀ = ŷ − c the model's simulation with the effect's columns at 0, and x the effect's first column. The figure its
form states (least squares over those samples):
- a state (a regime I, I·ñ, I·T̃; a bus signal's states): the mean of c while on [output unit], its relative
  change over the mean of ŷ₀ there, and that in % where ŷ₀ is at least as large as the change (a percentage of a
  smaller baseline, such as the fuel in overrun, says nothing);
- scales_fuel, y (1 + m x): m from c ≈ m · x · ŷ₀ [1 per unit of x], percent = 100 m;
- torque: the torque k per unit of x the fuel burns for through the torque path, c ≈ k · 1/A · B_T/F_T x [torque
  unit per unit of x], on an engine model c ≈ k · 1/A (B_T/F_T x + B_m/F_m x·∂m/∂T) (its map's marginal fuel,
  ident.modeldata.map_sloped);
- additive: the fuel g per unit of x, c ≈ g x [output unit per unit of x];
- shift (the fuel signal's delay): τ [s], c = ŷ(t − τ) − ŷ(t).
rms is the RMS of c [output unit]. The sign of the size (of the relative change, for an effect that scales the fuel) is
what the physics of a catalogued or defined effect states (Effect.sign): a candidate fitted the other way is not that
effect (`against_physics`, beyond the spread of the folds' fits).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from fuelid.ident import effects as fx
from fuelid.ident.filters import lfilter
from fuelid.ident.fueldelay import shift_signal
from fuelid.ident.hammerstein import MAP_COLUMN
from fuelid.ident.modeldata import fuel_shift_s, model_data
from fuelid.ident.polymodel import PolyModel, simulate

NAN = float("nan")


@dataclass(frozen=True)
class EffectSize:
    """An effect's size (module docstring): value in value_unit (per its form), relative the fuel's relative change
    (a state: mean change over ŷ₀ while on; scales_fuel: m; NaN for the other forms), percent 100 × relative where
    it is stated (NaN where not), rms [unit] of its fuel contribution, unit the fuel's, x_unit the unit of its first
    column, baseline [unit] the mean of ŷ₀ while a state is on (NaN for the other forms)."""

    form: str  # "state", "scales_fuel", "torque", "additive" or "shift"
    value: float
    value_unit: str
    relative: float
    percent: float
    rms: float
    unit: str
    x_unit: str
    baseline: float = NAN

    def to_json(self) -> dict:
        return asdict(self)  # NaN becomes null where the JSON is written (fuelid.output.json_safe)


def _columns(model: PolyModel, effect_id: str) -> list[int]:
    return [i for i, name in enumerate(model.input_names) if name.startswith(f"{effect_id}: ")]


def _fit(c: np.ndarray, x: np.ndarray) -> float:
    """The least-squares k in c ≈ k x (NaN when x is 0 throughout)."""
    xx = float(x @ x)
    return float(c @ x) / xx if xx > 0 else NAN


def effect_size(model: PolyModel, ds, effect: fx.Effect) -> EffectSize | None:
    """The size of `effect` in `model` (built with it) on dataset ds (module docstring); None when the model does
    not carry it or no sample is simulated."""
    u, _ = model_data(model, ds)
    n0 = model.structure.n_start
    segments = [s for s in ds.segments() if s.stop - s.start > n0]
    if not segments:
        return None
    unit = model.output_unit
    if effect.enters == "shift":
        tau = fuel_shift_s(model)
        c = [shift_signal(y, -tau / ds.Ts) - y for y in (simulate(model, u[s]) for s in segments)]
        c = np.concatenate([ci[n0:] for ci in c])
        return EffectSize("shift", tau, "s", NAN, NAN, float(np.sqrt(np.mean(c ** 2))), unit, "s")
    cols = _columns(model, effect.id)
    if not cols:
        return None

    def through(i: int, x: np.ndarray) -> np.ndarray:  # 1/A · B_i/F_i x, from rest
        return lfilter([1.0], model.A, lfilter(model.B[i], model.F[i], x))

    c, y0, x, on = [], [], [], []
    for s in segments:
        cs = sum(through(i, u[s, i]) for i in cols)
        c.append(cs[n0:])
        y0.append((simulate(model, u[s]) - cs)[n0:])
        x.append(u[s, cols[0]][n0:])
        on.append((u[s][:, cols] != 0).any(axis=1)[n0:])
    c, y0, x, on = map(np.concatenate, (c, y0, x, on))
    rms = float(np.sqrt(np.mean(c ** 2)))
    x_unit = model.input_units[cols[0]] or "1"  # a dimensionless bus signal (a gear ratio) has no DBC unit
    if effect.form == "regime":
        if not on.any():
            return EffectSize("state", NAN, unit, NAN, NAN, rms, unit, "1")
        change, baseline = float(c[on].mean()), float(y0[on].mean())
        relative = change / baseline if baseline != 0 else NAN
        return EffectSize("state", change, unit, relative, 100.0 * relative if baseline >= abs(change) else NAN,
                          rms, unit, "1", baseline)
    if effect.enters == "scales_fuel":
        m = _fit(c, x * y0)
        return EffectSize("scales_fuel", m, f"1 per {x_unit}", m, 100.0 * m, rms, unit, x_unit)
    if effect.enters == "torque":  # the fuel the model burns for the torque x (on an engine model, x·∂m/∂T too)
        j = model.input_names.index(MAP_COLUMN) if MAP_COLUMN in model.input_names else None
        cT = np.concatenate([(through(1, u[s, cols[0]]) + (through(j, u[s, cols[1]]) if j is not None else 0.0))[n0:]
                             for s in segments])
        return EffectSize("torque", _fit(c, cT), f"{model.input_units[1]} per {x_unit}", NAN, NAN, rms, unit, x_unit)
    return EffectSize("additive", _fit(c, x), f"{unit} per {x_unit}", NAN, NAN, rms, unit, x_unit)


def _direction(effect: fx.Effect, z: EffectSize) -> float:
    """The figure whose sign Effect.sign states (`against_physics`)."""
    if effect.enters != "scales_fuel":
        return z.value
    return z.value * float(np.sign(z.baseline)) if z.form == "state" else z.relative


def against_physics(effect: fx.Effect, sizes: list[EffectSize], margin: float) -> bool:
    """Whether the models built with `effect` fit it against the direction its physics states (Effect.sign: +1 more
    fuel as its x grows or while it is on, a lag for a shift; −1 less; 0 either way), beyond the spread of fits:
    with d_k its size in the model fitted without fold k — of an effect that scales the fuel, the direction of its
    relative change: m, or for a state its change while on times the sign of the fuel ŷ₀ it scales (a cut-off that
    lifts a linear model's negative fuel in overrun to 0 adds fuel, yet scales it down) — when

        sign · d̄ < −margin · SE,    SE² = (K − 1)/K · Σ_k (d_k − d̄)²

    (the delete-a-group jackknife's standard error; B. Efron, R. Tibshirani, An Introduction to the Bootstrap, 1993,
    ch. 11). What the model gains from it then is not this effect."""
    if effect.sign == 0:
        return False
    d = np.array([_direction(effect, z) for z in sizes], float)
    d = d[np.isfinite(d)]
    if d.size < 2:
        return False
    se = math.sqrt((d.size - 1) / d.size * float(np.sum((d - d.mean()) ** 2)))
    return effect.sign * float(d.mean()) < -margin * se
