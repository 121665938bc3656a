"""Fuel-efficiency drift: a model's steady-state fuel at fixed reference operating points, its uncertainty from
the parameter covariance, and the change against the truck's first model and the fleet median.

A reference point p = (engine speed n [rpm], engine torque T [N·m or % of reference torque, the model's
torque unit]) is held for ever; the model's output settles at y_ss(p), the whole model's steady state with
every other signal at the stated reference condition (ident.steady: the effects' inputs rebuilt at the point,
the engine model's static map included). The fleet compares the mean over the K points, S = (1/K) Σ_k y_ss(p_k),
whose standard error by the delta method is σ_S = √(gᵀ P g + φᵀ C φ), g = ∂S/∂θ = (1/K) Σ_k ∂y_ss(p_k)/∂θ
(ident.steady.steady_gradient), P the covariance of θ, and for an engine model φ = (1/K) Σ_k φ(p_k) the mean of
its map's basis at the points and C the covariance of the map's coefficients (ident.steady.map_basis).

Drift of the latest model against the first is d = 100 (S₁/S₀ − 1) [%] with
σ_d = 100 √(σ₁² + (S₁/S₀)² σ₀²) / S₀ (the two fits are on different data, so independent). A truck is
flagged when |d| exceeds the threshold and 2σ_d, so a change within the fits' noise is not called drift.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from fuelid.errors import InputError
from fuelid.ident.polymodel import PolyModel
from fuelid.ident.steady import map_basis, std_error, steady_gradient, steady_inputs, steady_value

TORQUE_UNITS = ("Nm", "%")
_POINT = re.compile(r"^\s*([0-9]+(?:\.[0-9]*)?)\s*x\s*(-?[0-9]+(?:\.[0-9]*)?)\s*(Nm|%)\s*$")


@dataclass(frozen=True)
class ReferencePoint:
    """A steady operating point: engine speed [rpm] and torque in `torque_unit` ('Nm' or '%')."""

    speed_rpm: float
    torque: float
    torque_unit: str

    def __str__(self) -> str:
        return f"{self.speed_rpm:g}x{self.torque:g}{self.torque_unit}"


MAX_SPEED_RPM = 10_000.0  # [rpm] above any truck engine's cut-off speed
MAX_TORQUE = 100_000.0  # [N·m or %] above any truck engine's torque


def parse_points(text: str) -> tuple[ReferencePoint, ...]:
    """Points written 'RPMxTORQUE<Nm|%>' separated by commas, e.g. '1000x600Nm,1400x1800Nm'; one torque unit.
    ValueError with one line when malformed."""
    points = []
    for part in text.split(","):
        m = _POINT.match(part)
        if not m:
            raise ValueError(f"reference point {part.strip()!r} is not RPMxTORQUE followed by Nm or %, "
                             "e.g. 1200x1500Nm")
        speed, torque = float(m[1]), float(m[2])
        if not (0.0 < speed <= MAX_SPEED_RPM and abs(torque) <= MAX_TORQUE):  # 390 digits parse to inf
            raise ValueError(f"reference point {part.strip()!r} is out of range "
                             f"(0 < rpm ≤ {MAX_SPEED_RPM:g}, |torque| ≤ {MAX_TORQUE:g})")
        points.append(ReferencePoint(speed, torque, m[3]))
    if len({p.torque_unit for p in points}) != 1:
        raise ValueError("reference points must all give torque in the same unit (Nm or %)")
    if len(points) > 20:
        raise ValueError("at most 20 reference points")
    return tuple(points)


# A 40 t truck's motorway and climbing region (engines of 2,000-2,600 N·m reference torque).
DEFAULT_POINTS = parse_points("1000x600Nm,1200x1200Nm,1400x1800Nm")


@dataclass(frozen=True)
class SteadyFuel:
    """The model's steady-state fuel at the reference points: per point [unit], their mean S [unit] and its
    standard error σ_S [unit] (None without a covariance), and the reference condition (signal → what it was
    held at: ident.steady)."""

    per_point: tuple[float, ...]
    mean: float
    std_error: float | None
    unit: str
    reference: dict = field(default_factory=dict, compare=False)


def steady_fuel(model: PolyModel, points: tuple[ReferencePoint, ...]) -> SteadyFuel:
    """y_ss at each point (ident.steady) and the mean S with σ_S (module docstring). InputError when the model's
    first two inputs are not engine speed [rpm] and torque in the points' unit, or a signal its effects use has
    no reference value."""
    unit = points[0].torque_unit
    if len(model.B) < 2 or model.input_units[0] != "rpm" or model.input_units[1] != unit:
        raise InputError(f"model inputs are in {', '.join(model.input_units)}; the reference points need rpm "
                         f"and {unit}")
    du, reference = zip(*(steady_inputs(model, p.speed_rpm, p.torque) for p in points))
    per_point = np.array([steady_value(model, p.speed_rpm, p.torque, d) for p, d in zip(points, du)])
    sigma = None
    if model.covariance is not None:
        g = np.mean([steady_gradient(model, p.speed_rpm, p.torque, d) for p, d in zip(points, du)], axis=0)
        phi = [map_basis(model, p.speed_rpm, p.torque) for p in points]
        sigma = std_error(model, g, None if phi[0] is None else np.mean(phi, axis=0))
    return SteadyFuel(tuple(float(v) for v in per_point), float(per_point.mean()), sigma, model.output_unit,
                      reference[0])


@dataclass(frozen=True)
class Drift:
    """Change of S from a reference model (the truck's first) to the current one: 100 (S₁/S₀ − 1) [%] and its
    standard error [%] (None when either model lacks a covariance), and whether it is an alert."""

    percent: float
    std_error_percent: float | None
    alert: bool


def drift(current: SteadyFuel, reference: SteadyFuel, threshold_percent: float = 5.0, k_sigma: float = 2.0) -> Drift:
    """Drift of `current` against `reference` (module docstring). An alert needs |d| > threshold and, when the
    uncertainty is known, |d| > k_sigma σ_d; without covariances the threshold alone decides."""
    if current.unit != reference.unit or reference.mean == 0:
        raise ValueError(f"cannot compare fuel in {current.unit} with {reference.mean} {reference.unit}")
    ratio = current.mean / reference.mean
    d = 100.0 * (ratio - 1.0)
    sigma = None
    if current.std_error is not None and reference.std_error is not None:
        sigma = 100.0 * math.hypot(current.std_error, ratio * reference.std_error) / abs(reference.mean)
    alert = abs(d) > threshold_percent and (sigma is None or abs(d) > k_sigma * sigma)
    return Drift(d, sigma, alert)


def fleet_median(values: list[float]) -> float | None:
    """The median of the trucks' S [unit], None for no trucks."""
    return float(np.median(values)) if values else None


def versus_median(value: float, median: float | None) -> float | None:
    """100 (value / median − 1) [%]: a truck against the fleet; None without a positive median."""
    return 100.0 * (value / median - 1.0) if median is not None and median > 0 else None
