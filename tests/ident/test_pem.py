"""ident.pem: the analytic gradient, recovery of ARX/ARMAX/OE/BJ systems, the paper's accuracy target,
stability enforcement, covariance against Monte-Carlo spread, the pole–zero cancellation warning."""
import math
import warnings

import numpy as np
import pytest
from scipy.signal import lfilter

from ident.modelfile import PAPER_MODELS, load_paper_model
from ident.pem import pem, prediction_errors, stabilize
from ident.polymodel import PolyModel, Structure, simulate
from ident.validation import fit_percent
from tests.ident.synthetic import minimal_truth, paper_data, true_model


def generate(truth: PolyModel, n: int, seed: int, sigma: float = 0.1):
    rng = np.random.default_rng(seed)
    u = lfilter([1.0], [1.0, -0.5], rng.normal(size=(n, len(truth.B))), axis=0)
    y0 = simulate(truth, u)
    v = lfilter([1.0], truth.A, lfilter(truth.C, truth.D, sigma * rng.normal(size=n)))
    return u, y0 + v, y0


def fit_quiet(u, y, s, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return pem(u, y, s, 1.0, **kw)


def zscores(est, truth):
    return (est.theta - truth.theta) / est.std_errors


def test_gradient_matches_finite_differences():
    m = PolyModel(A=[1, -0.3], B=[[0, 0.5, 0.2], [0.3, 0.1]], F=[[1, -0.7], [1, 0.2, 0.1]], C=[1, 0.4],
                  D=[1, -0.9, 0.2], Ts=1.0, nk=(1, 0))
    u, y, _ = generate(m, 400, 0)
    s, th = m.structure, m.theta + 0.05
    eps, psi = prediction_errors(th, s, u, y, jacobian=True)
    for k in range(th.size):
        h = 1e-6
        d = np.zeros_like(th)
        d[k] = h
        fd = -(prediction_errors(th + d, s, u, y) - prediction_errors(th - d, s, u, y)) / (2 * h)
        np.testing.assert_allclose(psi[:, k], fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


@pytest.mark.parametrize("truth", [
    PolyModel(A=[1, -1.2, 0.5], B=[[0, 1.0, 0.5], [0.8]], F=[[1], [1]], C=[1], D=[1], Ts=1.0, nk=(1, 0)),  # ARX
    PolyModel(A=[1, -0.8], B=[[0, 0, 1.0, 0.4]], F=[[1]], C=[1, 0.6], D=[1], Ts=1.0, nk=(2,)),  # ARMAX
    PolyModel(A=[1], B=[[0.5, 0.3], [0, 0.2]], F=[[1, -0.9], [1, -1.2, 0.6]], C=[1], D=[1], Ts=1.0, nk=(0, 1)),  # OE
    PolyModel(A=[1], B=[[0.5, 0.3], [0, 0.2]], F=[[1, -0.9], [1, -1.2, 0.6]], C=[1, 0.5], D=[1, -0.95],
              Ts=1.0, nk=(0, 1)),  # BJ, nk = 0 on the first input
], ids=["arx", "armax", "oe", "bj"])
def test_recovers_known_systems(truth):
    u, y, y0 = generate(truth, 4000, 1)
    est = fit_quiet(u, y, truth.structure)
    assert est.structure.kind == truth.structure.kind
    assert est.info["converged"]
    assert np.abs(zscores(est, truth)).max() < 3.5
    assert fit_percent(y0, simulate(est, u)) > 99


@pytest.fixture(scope="module")
def paper():
    if not PAPER_MODELS.exists():
        pytest.skip(f"{PAPER_MODELS} not available")
    return load_paper_model("diesel_scania_p320")


@pytest.mark.parametrize("seed", [0, 1])
def test_paper_accuracy_target(paper, seed):
    """Appendix diesel G (near pole-zero cancellations removed so θ is identifiable) with a stable ARMA noise,
    18,000 samples at 0.3 s: simulation fit to the noise-free truth ≥ 99 %, every θ within 3 standard errors."""
    truth = minimal_truth(paper)
    u, y, y0 = paper_data(truth, seed=seed, sigma_e=0.3)
    est = fit_quiet(u, y, truth.structure)
    assert fit_percent(y0, simulate(est, u)) >= 99
    assert np.abs(zscores(est, truth)).max() < 3


def test_paper_orders_converge_stable(paper):
    """The paper's orders (Gw 4/5/3, GT 5/5/0, C and D 11) on data from the full appendix model (printed D
    stabilised): converges to a stable predictor and the simulation fits the noise-free truth ≥ 99 %."""
    truth = true_model(paper)
    u, y, y0 = paper_data(truth, seed=0)
    est = fit_quiet(u, y, paper.structure)
    assert est.info["converged"] and est.info["iterations"] < 100
    for p in [*est.F, est.C, est.D]:
        assert np.abs(np.roots(p)).max() < 1
    assert fit_percent(y0, simulate(est, u)) >= 99


def test_stabilize_reflects_roots():
    p = np.real(np.poly([1.25, 0.5 + 1.2j, 0.5 - 1.2j, 0.3]))
    q = stabilize(p)
    r = np.sort_complex(np.roots(q))
    expected = np.sort_complex(np.array([0.8, 1 / (0.5 - 1.2j), 1 / (0.5 + 1.2j), 0.3]))
    np.testing.assert_allclose(r, expected, atol=1e-9)
    np.testing.assert_array_equal(stabilize([1.0, -0.5]), [1.0, -0.5])


def test_stability_enforced_from_unstable_start():
    """An unstable initial F, C, D (and data from an unstable noise denominator) still give a stable model."""
    truth = PolyModel(A=[1], B=[[0.5, 0.3]], F=[[1, -0.9]], C=[1, 0.5], D=[1, -1.02], Ts=1.0, nk=(0,))
    rng = np.random.default_rng(4)
    u = lfilter([1.0], [1.0, -0.5], rng.normal(size=3000))
    y = simulate(truth, u) + lfilter(truth.C, stabilize(truth.D), 0.1 * rng.normal(size=3000))
    bad = PolyModel(A=[1], B=[[0.4, 0.2]], F=[[1, -1.3]], C=[1, 1.6], D=[1, -1.5], Ts=1.0, nk=(0,))
    est = fit_quiet(u, y, truth.structure, init=bad)
    for p in [*est.F, est.C, est.D]:
        assert np.abs(np.roots(p)).max() < 1
    assert fit_percent(simulate(truth, u), simulate(est, u)) > 98


def test_covariance_matches_monte_carlo():
    truth = PolyModel(A=[1], B=[[0, 0.5, 0.3]], F=[[1, -0.7]], C=[1, 0.4], D=[1, -0.6], Ts=1.0, nk=(1,))
    runs = [fit_quiet(*generate(truth, 1500, seed, sigma=0.5)[:2], truth.structure) for seed in range(60)]
    spread = np.std([r.theta for r in runs], axis=0, ddof=1)
    predicted = np.mean([r.std_errors for r in runs], axis=0)
    assert np.all(np.abs(spread / predicted - 1) < 0.35), spread / predicted


def test_cancellation_warning_and_bad_input():
    truth = PolyModel(A=[1], B=[[0.5]], F=[[1, -0.8]], C=[1], D=[1, -0.5], Ts=1.0, nk=(0,))
    u, y, _ = generate(truth, 2000, 5)
    s = Structure.bj(1, 1, 0, 1, 2)  # one superfluous C/D pair: a zero of C meets a pole of D
    with pytest.warns(UserWarning, match="pole-zero cancellation in C/D"):
        est = pem(u, y, s, 1.0, cancel_tol=0.2)
    assert any("C/D" in w for w in est.info["warnings"])
    with pytest.raises(ValueError, match="samples"):
        pem(u, y[:-1], s, 1.0)
    assert math.isfinite(est.info["loss_V"])
