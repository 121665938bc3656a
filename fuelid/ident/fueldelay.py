"""The fuel-signal delay y_measured(t) = y(t − τ) (effect ``fuel_delay``, ident.effects): the shift that removes
it, seed 2's sweep that estimates τ, and the low-order reference model it is estimated and tested on.

The shift advances the fuel by s = τ/Ts samples, a fraction allowed, by cubic-spline interpolation within each
segment. The sweep scores τ = −1 … 1 s in 0.1 s steps and refines the best by the parabola through it and its
neighbours:

    τ̂ = τ_k + ½ (S_{k−1} − S_{k+1}) / (S_{k−1} − 2 S_k + S_{k+1}) Δτ,   S the score (e.g. RMSE), Δτ = 0.1 s.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from fuelid.ident.polymodel import Structure

DELAY_REFERENCE = Structure(nb=(2, 2), nf=(1, 1), nk=(0, 0))
"""Seed 2's low-order model (output error, two taps and one pole per input, no dead time): the fuel delay is
estimated and tested on it, since its dynamics cannot absorb a delay the way the paper's five torque taps do."""


def shift_signal(y, shift_samples: float, segments=None) -> np.ndarray:
    """y(t + s·Ts): y advanced by s samples (fractional allowed) by cubic-spline interpolation, separately in
    each segment (slices; default the whole array); the samples within |s| of a segment's end are held."""
    from scipy.ndimage import shift as spline_shift  # here: only a model with the fuel delay needs scipy.ndimage

    y = np.asarray(y, float)
    out = np.full_like(y, np.nan)
    for seg in segments or [slice(0, y.size)]:
        out[seg] = spline_shift(y[seg], -shift_samples, order=3, mode="nearest")
    return out


def sweep_fuel_shift(score: Callable[[float], float], shifts_s=None) -> dict:
    """Seed 2's fuel-shift sensitivity sweep: score(τ) [any error, e.g. RMSE] for each advance τ [s] of the
    fuel signal (default −1…1 s in 0.1 s steps), the best τ refined by a parabola through the best point
    and its neighbours. Returns {"shifts_s", "scores", "best_s"}."""
    shifts = np.round(np.arange(-1.0, 1.0001, 0.1), 10) if shifts_s is None else np.asarray(shifts_s, float)
    scores = np.array([score(float(s)) for s in shifts])
    k = int(np.nanargmin(scores))
    best = shifts[k]
    if 0 < k < shifts.size - 1:
        s0, s1, s2 = scores[k - 1: k + 2]
        curv = s0 - 2 * s1 + s2
        if curv > 0:
            best = shifts[k] + 0.5 * (s0 - s2) / curv * (shifts[k + 1] - shifts[k])
    return {"shifts_s": shifts.tolist(), "scores": scores.tolist(), "best_s": float(best)}
