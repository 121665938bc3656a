"""RPEM: agrees with the offline PEM, survives gaps and restarts (tracking a fuel-gain drift from a prior:
tests/ident/test_kalman.py, ident.kalman.GainTracker)."""
import warnings

import numpy as np
import pytest

from fuelid.ident.polymodel import Structure
from fuelid.ident.rpem import NO_STATE, NO_UPDATE, RPEM, _stable
from tests.ident.online_data import SIGMA_E, diesel_truth, fleet_prior, sim_fit
from tests.ident.synthetic import paper_data


@pytest.fixture(scope="module")
def truth():
    return diesel_truth()


@pytest.fixture(scope="module")
def data(truth):
    u, y, _ = paper_data(truth, n=12000, seed=0, sigma_e=SIGMA_E)
    return u, y


@pytest.fixture(scope="module")
def prior(truth):
    """An offline PEM model (with its covariance) from independent data: the 'fleet model' to start from."""
    return fleet_prior(truth)


def test_schur_cohn_matches_roots():
    rng = np.random.default_rng(0)
    work = np.empty(12)
    for _ in range(300):
        roots = rng.uniform(0.2, 1.1, 3) * np.exp(1j * rng.uniform(0, np.pi, 3))
        a = np.real(np.poly(np.r_[roots, roots.conj()]))
        assert _stable(a[1:], 0, 6, 0.9999, work) == bool(np.all(np.abs(roots) < 0.9999))


@pytest.mark.parametrize("seed", [0, 5])  # seed 5: 69 % with the earlier λ0 = 0.999 (ident.rpem docstring)
def test_converges_to_offline_pem_from_scratch(truth, seed):
    from fuelid.ident.pem import pem

    u, y, _ = paper_data(truth, n=12000, seed=seed, sigma_e=SIGMA_E)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        offline = pem(u, y, truth.structure, 0.3)
    est = RPEM(truth.structure, 0.3)
    trace = est.update(u, y)
    online = est.model()
    assert abs(sim_fit(online, u, y) - sim_fit(offline, u, y)) < 1.0
    assert sim_fit(online, u, y) > 85.0
    rep = est.report()
    assert rep["rejected_steps"] < 0.01 * rep["updates"]
    assert rep["noise_variance"] == pytest.approx(SIGMA_E**2, rel=0.2)
    assert abs(rep["running_fit_simulation_pct"] - sim_fit(offline, u, y)) < 3.0
    # settled: per-update relative change small (λ is still growing towards 1, so not zero)
    assert np.median(trace.dtheta[-1000:]) < 5e-3 and trace.dtheta[-1000:].max() < 5e-2
    for poly in online.F + [online.C, online.D]:
        assert np.abs(np.roots(poly)).max() < 1.0


def test_gaps_bursts_and_restarts_stay_stable(truth, data):
    u, y = (a.copy() for a in data)
    clean = RPEM(truth.structure, 0.3)
    clean.update(u, y)
    rng = np.random.default_rng(3)
    valid = np.ones(len(y), bool)
    for start in rng.integers(500, len(y) - 400, 40):  # not-available bursts of 1–300 samples
        length = int(rng.integers(1, 300))
        which = rng.integers(3)
        if which == 0:
            u[start:start + length, rng.integers(2)] = np.nan
        elif which == 1:
            y[start:start + length] = np.nan
        else:
            valid[start:start + length] = False
    est = RPEM(truth.structure, 0.3)
    parts = np.array_split(np.arange(len(y)), 7)
    traces = []
    for k, idx in enumerate(parts):
        if k == 3:
            est.reset()  # a restart, as after a jump in the time axis
        traces.append(est.update(u[idx], y[idx], valid[idx]))
    status = np.concatenate([t.status for t in traces])
    yhat = np.concatenate([t.yhat for t in traces])
    assert np.all(np.isfinite(est.theta)) and np.all(np.isfinite(est.P))
    assert np.trace(est.P) <= 10 * 100.0 * truth.structure.n_params * (1 + 1e-12)
    assert np.all(np.isnan(yhat[status == NO_STATE]))
    assert np.all(np.isfinite(yhat[status != NO_STATE]))
    assert (status == NO_STATE).any() and (status == NO_UPDATE).sum() > 0
    assert sim_fit(est.model(), data[0], data[1]) > sim_fit(clean.model(), data[0], data[1]) - 2.0


def test_no_data_no_update_and_prediction_without_output(truth, prior, data):
    u, _ = data
    est = RPEM(prior=prior)
    theta = est.theta.copy()
    trace = est.update(u[:500], np.full(500, np.nan))
    assert np.array_equal(est.theta, theta)
    assert np.allclose(trace.yhat[10:], trace.ysim[10:])  # no output: the prediction is the simulation
    with pytest.raises(ValueError):
        RPEM(Structure((2,), (1,), (0,), na=1), 0.3)
