"""Synthetic identification data from the paper's appendix diesel model (tests and benchmarks/bench_pem.py).

Inputs are deviations from idle, truck-like: engine speed 600–1900 rpm and torque 0–100 %, each a sequence of
random set-points held 3–40 s, smoothed by first-order lags (speed τ = 2 s; torque τ = 0.3 s, as gear shifts
and pedal steps are fast) plus jitter (speed lagged τ = 0.5 s, torque white); torque partly follows speed
changes (acceleration needs torque). Output y = G u + H e, e white with std sigma_e [L/h]:
- `true_model`: the appendix Gw, GT, C over the printed D stabilised (its pair at |z| = 1.033 reflected);
- `minimal_truth`: the appendix G without its near pole–zero cancellations, with a simple ARMA noise model
  (identifiable, for checking coefficients against standard errors).
"""
from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

from fuelid.ident.pem import stabilize
from fuelid.ident.polymodel import PolyModel, simulate

TS = 0.3


def truck_inputs(n: int, rng: np.random.Generator, ts: float = TS) -> np.ndarray:
    """N × 2 inputs [engine speed − 600 rpm, torque %]."""

    def held_steps(lo, hi):
        out = np.empty(n)
        i = 0
        while i < n:
            hold = int(rng.uniform(3.0, 40.0) / ts)
            out[i : i + hold] = rng.uniform(lo, hi)
            i += hold
        return out

    def lag(x, tau):
        a = np.exp(-ts / tau)
        return lfilter([1 - a], [1, -a], x, zi=[a * x[0]])[0]

    speed = lag(held_steps(0.0, 1300.0), 2.0) + lag(rng.normal(0, 40.0, n), 0.5)
    accel = np.gradient(speed) / ts
    torque = lag(held_steps(0.0, 80.0), 0.3) + 0.02 * accel + rng.normal(0, 4.0, n)
    return np.column_stack([np.clip(speed, 0.0, 1300.0), np.clip(torque, 0.0, 100.0)])


def true_model(paper: PolyModel) -> PolyModel:
    """The paper's model with its noise denominator D stabilised (a stationary noise model)."""
    return PolyModel(A=paper.A, B=paper.B, F=paper.F, C=paper.C, D=stabilize(paper.D), Ts=paper.Ts, nk=paper.nk,
                     input_names=paper.input_names, input_units=paper.input_units)


def paper_data(truth: PolyModel, n: int = 18000, seed: int = 0, sigma_e: float = 0.05):
    """(u, y, y_noise_free) simulated from `truth` on truck-like inputs; e white, std sigma_e."""
    rng = np.random.default_rng(seed)
    u = truck_inputs(n, rng)
    y0 = simulate(truth, u)
    v = lfilter(truth.C, truth.D, rng.normal(0.0, sigma_e, n))
    return u, y0 + v, y0


def _cancel_pairs(b: np.ndarray, f: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """b/f without its zero–pole pairs closer than tol, rescaled to the same DC gain."""
    zeros, poles = list(np.roots(b)), list(np.roots(f))
    for z in list(zeros):
        d = [abs(z - p) for p in poles]
        if d and min(d) < tol:
            zeros.remove(z)
            poles.pop(int(np.argmin(d)))
    b2, f2 = b[0] * np.real(np.poly(zeros)), np.real(np.poly(poles))
    return b2 * (b.sum() / f.sum()) / (b2.sum() / f2.sum()), f2


def minimal_truth(paper: PolyModel, C=(1.0, -0.5), D=(1.0, -1.6, 0.7), tol: float = 0.02) -> PolyModel:
    """The appendix G with its near pole–zero cancellations (closer than tol) removed, DC gains kept, and a
    simple stable noise model C/D: identifiable, so its coefficients can be checked against standard errors."""
    B, F = zip(*(_cancel_pairs(b[k:], f, tol) for b, f, k in zip(paper.B, paper.F, paper.nk)))
    return PolyModel(A=[1.0], B=[np.r_[np.zeros(k), b] for b, k in zip(B, paper.nk)], F=list(F), C=C, D=D,
                     Ts=paper.Ts, nk=paper.nk, input_names=paper.input_names, input_units=paper.input_units)
