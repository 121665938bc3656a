"""Order search: the lowest orders whose residuals pass the paper's tests (eqs. 18–19, 99 % bounds).

The authors tuned the orders by hand until the prediction-error autocorrelation and its cross-correlation with
every input stayed inside the 99 % bounds. `search_orders` does the same greedily, from the lowest BJ orders up:

    fit by `pem`; ε the one-step residuals (first n0 samples dropped)
    all tests pass                      → done: these are the lowest orders on the path
    cross-correlation with u_i fails    → G_i is short of dynamics: nb_i += 1, nf_i += 1
    only the autocorrelation fails      → the noise model is: nc += 1, nd += 1

Delays nk_i, when not given, come from `estimate_delays`: the first lag whose coefficient in a high-order ARX
model is significant. With `segments` (records split by gaps) every fit and test runs per segment (`pem`).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from fuelid.errors import FuelidError, InputError
from fuelid.ident.identify import MIN_SEGMENT_S, training_segments
from fuelid.ident.pem import pem
from fuelid.ident.polymodel import PolyModel, Structure, as_inputs, residuals
from fuelid.ident.validation import autocorr_test, crosscorr_test


@dataclass
class OrderTrial:
    """One fitted candidate: its structure, loss V, and which residual tests passed."""

    structure: Structure
    loss_V: float
    autocorr_pass: bool
    crosscorr_pass: tuple[bool, ...]

    @property
    def passed(self) -> bool:
        return self.autocorr_pass and all(self.crosscorr_pass)


@dataclass
class OrderSearch:
    """The chosen structure and model (the first passing candidate, else the last tried) and every trial."""

    structure: Structure
    model: PolyModel
    passed: bool
    trials: list[OrderTrial] = field(default_factory=list)


def estimate_delays(u, y, *, segments=None, max_delay: int = 10, order: int = 10, z: float = 3.29) -> tuple[int, ...]:
    """nk_i: the first lag l ≤ max_delay at which b_i,l of an ARX(order, order + max_delay + 1, 0) model exceeds
    z standard errors (3.29: two-sided 99.9 %); max_delay when none does. u, y deviation data; segments as
    in `pem`."""
    u = as_inputs(u)
    m = u.shape[1]
    nb = order + max_delay + 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            arx = pem(u, y, Structure.arx(order, (nb,) * m, (0,) * m), 1.0, segments=segments, max_iter=5)
        except InputError as exc:
            raise InputError(f"too little data to estimate the delays for --orders auto ({exc}, in a high-order ARX "
                             "model); give the orders (--orders paper or a SPEC) or use longer data") from None
    t = np.abs(arx.theta / arx.std_errors)[order:].reshape(m, nb)[:, : max_delay + 1]
    return tuple(int(np.argmax(row > z)) if np.any(row > z) else max_delay for row in t)


def residual_tests(model: PolyModel, u, y, max_lag: int = 25, segments=None) -> tuple[bool, tuple[bool, ...]]:
    """(autocorrelation passed, cross-correlation passed per input) of the one-step residuals, eqs. 18–19;
    run per segment (as in `pem`), the first n0 residuals of each and everything outside left out (NaN)."""
    u = as_inputs(u)
    n0 = model.structure.n_start
    e = np.full(len(u), np.nan)
    for a, b in [(0, len(u))] if segments is None else [(s.start, s.stop) if isinstance(s, slice) else s
                                                          for s in segments]:
        e[a + n0 : b] = residuals(model, u[a:b], y[a:b])[n0:]
    cross = crosscorr_test(e, np.where(np.isfinite(e)[:, None], u, np.nan), max_lag)
    return autocorr_test(e, max_lag).passed, tuple(c.passed for c in cross)


def search_orders(u, y, Ts: float, *, segments=None, nk=None, u0=None, y0: float = 0.0, max_order: int = 6,
                  max_noise_order: int = 12, max_lag: int = 25, max_fits: int = 40) -> OrderSearch:
    """Lowest BJ orders passing the residual tests (module docstring). u: N × m, y: N, Ts [s]; segments as in
    `pem`.

    nk: delays per input (estimated when None); max_order bounds nb_i and nf_i, max_noise_order nc and nd;
    max_fits bounds the number of PEM fits. Returns the first passing candidate, else the last one tried.
    """
    u = as_inputs(u)
    m = u.shape[1]
    u0 = np.zeros(m) if u0 is None else np.broadcast_to(np.asarray(u0, float), (m,))
    nk = (estimate_delays(u - u0, np.asarray(y, float) - y0, segments=segments) if nk is None else tuple(nk))
    nb, nf, nc = [1] * m, [1] * m, 1
    trials = []
    while True:
        s = Structure.bj(tuple(nb), tuple(nf), nk, nc, nc)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = pem(u, y, s, Ts, segments=segments, u0=u0, y0=y0)
        auto, cross = residual_tests(model, u, y, max_lag, segments)
        trials.append(OrderTrial(s, model.info["loss_V"], auto, cross))
        if trials[-1].passed:
            return OrderSearch(s, model, True, trials)
        grow = [i for i in range(m) if not cross[i] and nb[i] < max_order]
        for i in grow:
            nb[i] += 1
            nf[i] += 1
        if not grow:
            if nc >= max_noise_order:
                return OrderSearch(s, model, False, trials)
            nc += 1
        if len(trials) >= max_fits:
            return OrderSearch(s, model, False, trials)


def search_dataset_orders(ds, min_segment_s: float = MIN_SEGMENT_S) -> OrderSearch:
    """`search_orders` on a Dataset's engine speed and torque → fuel, on the stretches `fuelid identify` fits
    (valid, at least min_segment_s [s] long), each a segment. Raises FuelidError when there are none."""
    segs = training_segments(ds, ds.u, ds.y, min_segment_s)
    if not segs:
        raise FuelidError(f"no valid stretch of at least {min_segment_s:g} s to search the orders on")
    return search_orders(ds.u, ds.y, ds.Ts, segments=segs, u0=ds.u0, y0=ds.y0)
