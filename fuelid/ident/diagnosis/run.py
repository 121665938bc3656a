"""The model run the diagnosis tests (ident.modelrun.ModelRun on the segments long enough) and its gradients:
the prediction errors ε with the nuisance columns of test 1 and the errors w before the noise filter with those
of test 2 (ident.diagnosis.statistics)."""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from fuelid.ident.diagnosis.statistics import NuisanceBasis, free_responses, nuisance_basis
from fuelid.ident.filters import lfilter
from fuelid.ident.modelrun import ModelRun
from fuelid.ident.pem import prediction_errors
from fuelid.ident.polymodel import Structure


@dataclass
class Run:
    """The diagnosis's view of a model run (ident.modelrun.ModelRun) over the segments it tests: y the model's
    (shifted) fuel, ysim its simulation on the tested segments (NaN elsewhere); segs those segments; after each
    one's first `warm` (= n_start) samples, stacked: e the prediction errors and Q a basis of their nuisance
    columns (test 1), r the errors w = A ỹ − Σ B_i/F_i ũ_i before the noise filter (the simulation errors when
    A = 1) with the basis QG of their nuisance columns projected out (test 2). u and eps
    (the prediction errors on every segment, as ident.validation reads them for its whiteness verdict, so the
    diagnosis and the compare table never disagree on it) are the ModelRun's."""

    model_run: ModelRun
    y: np.ndarray
    ysim: np.ndarray
    segs: list
    warm: int
    e: np.ndarray
    Q: NuisanceBasis
    r: np.ndarray
    QG: NuisanceBasis

    @property
    def u(self) -> np.ndarray:
        return self.model_run.u

    @property
    def eps(self) -> np.ndarray:
        return self.model_run.eps

    @property
    def lens(self) -> list[int]:
        """Samples of each segment after its first `warm` (the blocks e, r and the columns are stacked from)."""
        return [s.stop - s.start - self.warm for s in self.segs]

    @functools.cached_property
    def e_projected(self) -> np.ndarray:
        """M_Z ε: the prediction errors with their nuisance columns (Q) projected out, the same in every
        candidate's score test (ident.diagnosis.statistics.score_test)."""
        return self.Q.project_out(self.e)

    @property
    def index(self) -> np.ndarray:
        """Dataset indices of the stacked samples."""
        return self.model_run.tested_index


def run_gradients(mrun: ModelRun) -> Run:
    """ε, w and their gradients for the model of `mrun` on each of its tested segments (ModelRun.tested). Each
    segment's filters start from zero state; the free responses of 1/F_i (for w) and of D/C·1/F_i and 1/C (for ε)
    are nuisance columns of that segment alone (free_responses), so its first minutes are tested rather than
    thrown away as a warm-up."""
    mrun.require_tested()
    model, u, y = mrun.model, mrun.u, mrun.y
    s = model.structure
    warm = s.n_start
    no_noise = Structure(nb=s.nb, nf=s.nf, nk=s.nk, na=s.na)  # the same model with C = D = 1
    theta_g = model.theta[: no_noise.n_params]  # θ lists a, b, f before c, d
    Zs, es, ZGs, ws, ICs, ICGs = [], [], [], [], [], []
    for seg in mrun.tested:
        us, ys = u[seg] - np.asarray(model.u0), y[seg] - model.y0
        e, psi = prediction_errors(model.theta, s, us, ys, jacobian=True)
        w, psi_g = prediction_errors(theta_g, no_noise, us, ys, jacobian=True)
        ones = np.ones(len(ys))
        free = free_responses(model.F, len(ys))
        ICGs.append(free[warm:])
        noise_free = free_responses([model.C], len(ys))
        ICs.append(np.column_stack([lfilter(model.D, model.C, free, axis=0), noise_free])[warm:])
        Zs.append(np.column_stack([psi, lfilter(model.D, model.C, ones)])[warm:])
        ZGs.append(np.column_stack([psi_g, ones])[warm:])
        es.append(e[warm:])
        ws.append(w[warm:])
    Q = nuisance_basis(np.vstack(Zs), ICs)
    QG = nuisance_basis(np.vstack(ZGs), ICGs)
    r = QG.project_out(np.concatenate(ws))
    return Run(mrun, y, mrun.on_tested(mrun.ysim), list(mrun.tested), warm, np.concatenate(es), Q, r, QG)
