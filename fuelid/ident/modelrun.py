"""One run of a fitted model over a dataset: what the validation metrics (ident.validation), the diagnosis
(ident.diagnosis) and the report (ident.report) all read, so a model is simulated and predicted once.

The model runs on its own inputs and fuel (ident.modeldata.model_data: speed, torque, the effects' inputs, the
fuel advanced by its delay) on each valid segment of the data separately, its filters started from zero state
(ident.polymodel):

    ŷ_s(t)  = y0 + 1/A Σ_i B_i/F_i ũ_i(t)                    simulation
    ŷ_1(t)  = ŷ(t | t − 1)                                   one-step prediction
    ε(t)    = D/C (A ỹ(t) − Σ_i B_i/F_i ũ_i(t))               one-step prediction error

The first n_start samples of each segment, where the unknown initial state still shows, are left out of the
metrics (`settled`); the segments long enough for the diagnosis's initial-state columns (`tested`) are the ones it
tests and the report draws.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fuelid.errors import InputError
from fuelid.ident.modeldata import model_data
from fuelid.ident.polymodel import PolyModel, predict, residuals, simulate

MIN_TESTED = 50  # samples a tested segment has beyond the model's n_start and its initial-state columns


@dataclass(frozen=True)
class ModelRun:
    """`model` run over every valid segment `segments` (slices) of a dataset: u (N × m) its inputs, y (N) its
    (shifted) fuel; ysim, ypred the simulation and one-step prediction (NaN outside the segments); eps the one-step
    prediction errors, NaN outside the segments and during each one's first n_start samples; tested the segments
    at least n_start + (initial-state columns) + MIN_TESTED samples long with every input and the fuel finite."""

    model: PolyModel
    u: np.ndarray
    y: np.ndarray
    segments: list
    ysim: np.ndarray
    ypred: np.ndarray
    eps: np.ndarray
    tested: list

    def settled(self, x: np.ndarray) -> np.ndarray:
        """x (N) with each segment's first n_start samples NaN (and NaN outside the segments)."""
        out = np.full(len(x), np.nan)
        for s in self.segments:
            out[s] = x[s]
            out[s.start: s.start + self.model.structure.n_start] = np.nan
        return out

    def on_tested(self, x: np.ndarray) -> np.ndarray:
        """x (N) on the tested segments, NaN elsewhere."""
        out = np.full(len(x), np.nan)
        for s in self.tested:
            out[s] = x[s]
        return out

    @property
    def tested_index(self) -> np.ndarray:
        """Dataset indices of the tested segments' samples after each one's first n_start (what the diagnosis
        tests)."""
        n_start = self.model.structure.n_start
        return np.concatenate([np.arange(s.start + n_start, s.stop) for s in self.tested])

    def require_tested(self) -> None:
        """Raise ValueError when no segment is long enough to be tested."""
        if not self.tested:
            raise InputError(f"no valid segment of the data is longer than {min_tested_length(self.model)} samples, "
                             "what the model's initial state and the tests need")


def min_tested_length(model: PolyModel) -> int:
    """The shortest segment [samples] the diagnosis tests: n_start, the initial-state columns of the simulation and
    prediction errors (2 Σ deg F_i + deg C), and MIN_TESTED more."""
    return model.structure.n_start + sum(f.size - 1 for f in model.F) * 2 + model.C.size - 1 + MIN_TESTED


def run_model(model: PolyModel, ds) -> ModelRun:
    """The ModelRun of `model` on dataset ds. Raises ValueError when the data lack the signals of its effects."""
    u, y = model_data(model, ds)
    n, n_start = len(y), model.structure.n_start
    ysim, ypred, eps = (np.full(n, np.nan) for _ in range(3))
    segments, tested = ds.segments(), []
    for seg in segments:
        ysim[seg] = simulate(model, u[seg])
        ypred[seg] = predict(model, u[seg], y[seg], 1)
        eps[seg] = residuals(model, u[seg], y[seg])
        eps[seg.start: seg.start + n_start] = np.nan
        ok = np.isfinite(y[seg]) & np.isfinite(u[seg]).all(axis=1)
        if seg.stop - seg.start >= min_tested_length(model) and ok.all():
            tested.append(seg)
    return ModelRun(model, u, y, segments, ysim, ypred, eps, tested)
