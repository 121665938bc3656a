"""ident.diagnosis.statistics on arrays with known answers: the score tests, the AR whitener, Holm and the nuisance
bases."""
import numpy as np
import pytest
from scipy.linalg import block_diag, solve_toeplitz
from scipy.signal import lfilter
from scipy.stats import chi2

from fuelid.ident.diagnosis import statistics as st


def test_score_test_is_n_r2_for_white_noise_and_holm_is_step_down():
    rng = np.random.default_rng(0)
    e, X = rng.normal(size=5000), rng.normal(size=(5000, 2))
    e2 = e + 0.1 * X[:, 0]
    res = st.score_test(e2, X, hac_lags=0)
    r2 = 1 - np.sum((e2 - X @ np.linalg.lstsq(X, e2, rcond=None)[0]) ** 2) / np.sum(e2**2)
    assert res.df == 2 and res.statistic == pytest.approx(5000 * r2, rel=0.05)
    assert res.p_value == pytest.approx(chi2.sf(res.statistic, 2))
    adj, rej = st.holm([0.01, 0.04, 0.03, 0.5], 0.05)
    assert np.allclose(adj, [0.04, 0.09, 0.09, 0.5]) and rej.tolist() == [True, False, False, False]
    assert st.score_test(e, X[:, :1], Q=st.nuisance_basis(X[:, :1])).df == 0  # nothing left to test


def test_level_test_whitens_coloured_noise_under_the_alternative():
    """A level shift in strongly coloured noise (AR pole 0.98) is found by the simulation-error test; with no
    shift a regressor as slow as the noise (the hardest case: a spurious regression without whitening) is
    flagged at 5 % in at most 12 % of 100 trials (measured 9 % over 200)."""
    n, p_null = 6000, []
    Q = st.nuisance_basis(np.ones((n, 1)))
    for seed in range(100):
        noise = lfilter([1.0], [1.0, -0.98], np.random.default_rng(seed).normal(size=n))
        x = lfilter([1.0], [1.0, -0.98], np.random.default_rng(1000 + seed).normal(size=n))[:, None]
        p_null.append(st.level_test(noise - noise.mean(), x - x.mean(), [n], Q)[0].p_value)
    assert np.mean(np.array(p_null) < 0.05) <= 0.12
    step = (np.arange(n) > n // 2).astype(float)[:, None]
    shifted = lfilter([1.0], [1.0, -0.98], np.random.default_rng(1).normal(size=n)) + 6.0 * step[:, 0]
    found, left = st.level_test(shifted - shifted.mean(), step - step.mean(), [n], Q)  # noise std 5
    assert found.p_value < 1e-6 and left < 0.9


def test_nuisance_basis_keeps_each_segments_initial_states_on_its_own_rows():
    """Segments' free-response columns are zero outside their segment: the basis projects out exactly what the
    dense QR of [Z, blockdiag(IC_1 … IC_S)] does, and stores N·(p_Z + p_s) numbers however many segments there
    are."""
    rng = np.random.default_rng(5)
    lens = [300, 200, 250, 250]
    ICs = [lfilter([1.0], [1.0, -0.95], np.eye(n, 2), axis=0) for n in lens]  # two free responses per segment
    Z = rng.normal(size=(sum(lens), 3))
    X = rng.normal(size=(sum(lens), 2))
    basis = st.nuisance_basis(Z, ICs)
    dense = np.linalg.qr(np.column_stack([Z, block_diag(*ICs)]))[0]
    assert np.allclose(basis.project_out(X), X - dense @ (dense.T @ X))
    assert basis.dense.shape == (sum(lens), 3) and [b.shape for b in basis.blocks] == [(n, 2) for n in lens]
    wider = basis.extended(X)
    assert np.allclose(wider.project_out(X), 0.0, atol=1e-10) and wider.dense.shape[1] == 5


def test_a_nuisance_column_already_in_the_span_adds_nothing():
    """An offset next to the trips' levels (an exact dependence) adds no direction: a plain QR would add one made
    of rounding errors, and project it out of everything."""
    levels = np.zeros((400, 2))
    levels[:250, 0], levels[250:, 1] = 1.0, 1.0
    basis = st.nuisance_basis(np.column_stack([levels, np.ones(400)]))
    assert basis.dense.shape[1] == 2
    assert basis.extended(levels @ [2.0, -1.0]) is basis


def test_well_independent_columns_get_the_pivoted_qrs_span_by_cholesky_qr_twice():
    """Columns as ill-conditioned as a model's gradient (two of them apart by 1e-7 of their norm) are independent far
    beyond RANK_TOL: Cholesky QR twice gives an orthonormal basis of the span a pivoted QR gives, to rounding. Two
    columns apart by less than WELL_INDEPENDENT · RANK_TOL are left to the pivoted QR's rank decision: kept 5e-10
    apart, one dropped 1e-12 apart."""
    rng = np.random.default_rng(6)
    X, Y = rng.normal(size=(5000, 12)), rng.normal(size=(5000, 3))
    for gap, kept in ((1e-7, 12), (5e-10, 12), (1e-12, 11)):
        X[:, 5] = X[:, 4] + gap * np.linalg.norm(X[:, 4]) * rng.normal(size=5000) / np.sqrt(5000)
        norms = np.linalg.norm(X, axis=0)
        Q = st._orthonormal_columns(X, norms, st.RANK_TOL)
        pivoted = st.pivoted_qr_columns(X / norms, st.RANK_TOL)
        assert Q.shape[1] == pivoted.shape[1] == kept and np.allclose(Q.T @ Q, np.eye(kept), atol=1e-14)
        assert np.allclose(Q @ (Q.T @ Y), pivoted @ (pivoted.T @ Y), atol=1e-8)
        assert (st._cholesky_qr2(X / norms) is not None) == (gap == 1e-7)


def test_free_responses_span_any_initial_state():
    """A filter started from zero state differs from one started anywhere else by a combination of the columns."""
    F = np.array([1.0, -1.5, 0.7])
    x = np.random.default_rng(4).normal(size=300)
    started = lfilter([1.0], F, x, zi=[0.8, -0.3])[0]
    diff = started - lfilter([1.0], F, x)
    cols = st.free_responses([F], 300)
    assert cols.shape == (300, 2)
    assert np.allclose(cols @ np.linalg.lstsq(cols, diff, rcond=None)[0], diff)


@pytest.mark.parametrize("n", [2989, 11989])  # 2n − 1 and 2n with a large prime factor (11989 = 19 · 631)
def test_the_whitener_is_yule_walker_on_the_linear_autocovariances(n):
    """ar_whitener's FFT autocovariances are the biased linear ones (no circular wrap-around), so its a(q) is the
    Yule–Walker AR fit: for an AR(2) series it recovers the coefficients and whitens the series."""
    rng = np.random.default_rng(n)
    v = lfilter([1.0], [1.0, -1.2, 0.5], rng.standard_normal(n))
    order = 100
    d = v - v.mean()
    acov = np.array([d[: n - k] @ d[k:] for k in range(order + 1)]) / n
    a = st.ar_whitener(v, order)
    np.testing.assert_allclose(a, np.r_[1.0, -solve_toeplitz(acov[:order], acov[1:])], rtol=0, atol=1e-9)
    np.testing.assert_allclose(a[1:3], [-1.2, 0.5], atol=0.06)
