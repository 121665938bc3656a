"""Kalman variant: one step equals filterpy's KalmanFilter; tracks a fuel-gain drift."""
import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from ident.kalman import ParameterKalman, gain_drift_Q
from ident.rpem import covariance_update, gain
from tests.ident.online_data import SIGMA_E, dc_gains, diesel_truth, drifting_data, fleet_prior, sim_fit
from tests.ident.synthetic import paper_data


def test_step_equals_filterpy():
    rng = np.random.default_rng(0)
    d = 7
    A = rng.normal(size=(d, d))
    P, Q = A @ A.T + np.eye(d), np.diag(rng.uniform(0, 0.1, d))
    theta, psi, R = rng.normal(size=d), rng.normal(size=d), 0.3
    eps = 0.8
    kf = KalmanFilter(dim_x=d, dim_z=1)
    kf.x, kf.P, kf.Q, kf.R, kf.F, kf.H = theta.copy(), P.copy(), Q, np.array([[R]]), np.eye(d), psi[None, :]
    kf.update(np.array([psi @ theta + eps]))  # z − Hx = ε
    kf.predict()
    Ppsi, K = np.empty(d), np.empty(d)
    denom = gain(P, psi, R, d, Ppsi, K)
    covariance_update(P, Ppsi, denom, 1.0, Q, d)
    assert np.allclose(theta + K * eps, kf.x)
    assert np.allclose(P, kf.P)


@pytest.fixture(scope="module")
def prior():
    return fleet_prior(diesel_truth())


def test_kalman_tracks_fuel_gain_drift(prior):
    truth = diesel_truth()
    n = 16000
    u, y = drifting_data(truth, n, step=0.05)
    est = ParameterKalman(prior=prior, rate=1e-3)
    assert np.allclose(est.Q, gain_drift_Q(prior.theta, truth.structure, 1e-3))
    trace = est.update(u, y, every=250)
    g0 = dc_gains([prior.theta], truth.structure)[0] @ u.mean(axis=0)
    change = dc_gains(trace.theta, truth.structure) @ u.mean(axis=0) / g0 - 1.0
    at = trace.theta_at
    assert np.abs(change[(at > n // 8) & (at < n // 2)]).max() < 0.025
    assert 0.03 < change[at > 7 * n // 8].mean() < 0.07
    assert est.model().info["method"].startswith("Kalman")


def test_needs_q_or_prior():
    with pytest.raises(ValueError):
        ParameterKalman(diesel_truth().structure, 0.3)


def test_kalman_stable_under_bursts_and_restarts(prior):
    truth = diesel_truth()
    u, y, _ = paper_data(truth, n=8000, seed=6, sigma_e=SIGMA_E)
    clean_u, clean_y = u.copy(), y.copy()
    rng = np.random.default_rng(7)
    valid = np.ones(len(y), bool)
    for start in rng.integers(200, len(y) - 400, 30):  # not-available bursts of 1–300 samples
        stop = start + int(rng.integers(1, 300))
        which = rng.integers(3)
        if which == 0:
            u[start:stop, 0] = np.nan
        elif which == 1:
            y[start:stop] = np.nan
        else:
            valid[start:stop] = False
    est = ParameterKalman(prior=prior, rate=1e-3)
    for k, idx in enumerate(np.array_split(np.arange(len(y)), 5)):
        if k == 2:
            est.reset()
        trace = est.update(u[idx], y[idx], valid[idx])
        assert np.all(np.isfinite(trace.yhat[trace.status >= 0]))
    assert np.all(np.isfinite(est.theta)) and np.all(np.isfinite(est.P))
    assert sim_fit(est.model(), clean_u, clean_y) > sim_fit(prior, clean_u, clean_y) - 2.0
