"""Kalman variant: one step equals filterpy's KalmanFilter; the fuel-gain tracker reports an injected drift on
every data set, and no drift without one."""
import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from fuelid.ident.kalman import GainTracker, ParameterKalman, gain_drift_Q
from fuelid.ident.rpem import covariance_update, gain
from tests.ident.online_data import (DRIFT_SEEDS, SIGMA_E, dc_gains, diesel_truth, drifting_data, fleet_prior,
                                    sim_fit)
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


N = 16000  # 80 min at 0.3 s; the change at N/2


@pytest.mark.parametrize("seed", DRIFT_SEEDS)
@pytest.mark.parametrize("kind", ["forgetting", "random walk"])
def test_gain_tracker_reports_injected_drift_and_no_false_drift(prior, seed, kind):
    """+5 % fuel gain half-way (injector drift), fuel not available 6 s every 2.5 min: the reported steady-state
    fuel change ends at +5 % ± 1.5 points with a 95 % interval covering it, and stays at 0 ± 1.5 before the
    change and on the same data without it."""
    truth = diesel_truth()
    settings = {"forgetting": {"lam": 0.9995}, "random walk": {"rate": 3e-4}}[kind]
    for step in (0.05, 0.0):
        u, y = drifting_data(truth, N, step=step, seed=seed, na_every=500)
        est = GainTracker(prior, **settings)
        trace = est.update(u, y, every=250)
        beta = np.where(np.arange(prior.theta.size) < sum(prior.structure.nb), prior.theta, 0.0)
        change = 100.0 * (trace.theta - prior.theta) @ beta / (beta @ beta)  # g − 1 from the θ snapshots [%]
        at = trace.theta_at
        assert np.abs(change[(at > N // 8) & (at < N // 2)]).max() < 1.5
        assert abs(change[at > 7 * N // 8].mean() - 100 * step) < 1.5
        final, ci95 = est.fuel_change()
        assert final == pytest.approx(change[-1]) and abs(final - 100 * step) < min(1.5, ci95) and ci95 < 2.0
    # the exported model: the prior with every DC gain × g, and the report of the run
    gains = dc_gains([est.model().theta, prior.theta], truth.structure)
    assert np.allclose(gains[0] / gains[1], 1.0 + final / 100.0)
    rep = est.model().info
    assert rep["fuel_change_ci95_pct"] == pytest.approx(ci95) and rep["updates"] > 0.85 * N
    assert rep["noise_variance"] == pytest.approx(SIGMA_E**2, rel=0.2)


def test_parameter_kalman_q_along_the_fuel_gain(prior):
    est = ParameterKalman(prior=prior, rate=1e-3)
    assert np.allclose(est.Q, gain_drift_Q(prior.theta, prior.structure, 1e-3))
    assert est.model().info["method"].startswith("Kalman")


@pytest.mark.parametrize("make", [lambda p: ParameterKalman(prior=p, rate=1e-3), lambda p: GainTracker(p, lam=0.9995)],
                         ids=["parameter Kalman", "gain tracker"])
def test_kalman_stable_under_bursts_and_restarts(prior, make):
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
    est = make(prior)
    for k, idx in enumerate(np.array_split(np.arange(len(y)), 5)):
        if k == 2:
            est.reset()
        trace = est.update(u[idx], y[idx], valid[idx])
        assert np.all(np.isfinite(trace.yhat[trace.status >= 0]))
    assert np.all(np.isfinite(est.theta)) and np.all(np.isfinite(est.P))
    assert sim_fit(est.model(), clean_u, clean_y) > sim_fit(prior, clean_u, clean_y) - 2.0


def test_gain_tracker_in_pieces_equals_one_run(prior):
    """Fed sample by sample (as live) or in one block, the same estimate and predictions."""
    u, y = drifting_data(diesel_truth(), 600, seed=3, na_every=200)
    whole, pieces = GainTracker(prior, lam=0.999), GainTracker(prior, lam=0.999)
    trace = whole.update(u, y)
    yhat = np.concatenate([pieces.update(u[k:k + 1], y[k:k + 1]).yhat for k in range(len(y))])
    assert whole.gain != 1.0 and pieces.gain == pytest.approx(whole.gain, rel=1e-12)
    assert np.allclose(yhat, trace.yhat, equal_nan=True)
