import numpy as np
import pytest
from scipy.signal import lfilter
from threadpoolctl import threadpool_limits

from fuelid.ident.validation import autocorr_test, crosscorr_test, cycle_fuel_error, error_table, fit_percent, rmse


def test_autocorr_accepts_white_noise_at_roughly_the_nominal_rate():
    rng = np.random.default_rng(0)
    passed = [autocorr_test(rng.standard_normal(2000), max_lag=25).passed for _ in range(200)]
    # 25 lags at 1 % each: P(pass) ≈ 0.99**25 ≈ 0.78
    assert 0.65 < np.mean(passed) < 0.9


def test_autocorr_rejects_ar1():
    rng = np.random.default_rng(1)
    e = lfilter([1.0], [1.0, -0.3], rng.standard_normal(2000))
    res = autocorr_test(e, max_lag=25)
    assert not res.passed
    assert 1 in res.outside()
    assert res.r[0] == pytest.approx(1.0)
    assert res.bound == pytest.approx(2.5758 / np.sqrt(2000), rel=1e-4)


def test_crosscorr_detects_dependence_and_feedback_option():
    rng = np.random.default_rng(2)
    u = rng.standard_normal(3000)
    white = rng.standard_normal(3000)
    assert crosscorr_test(white, u).passed
    e = white + 0.5 * np.roll(u, 2)          # e(k) depends on u(k-2): lag +2
    res = crosscorr_test(e, u)
    assert not res.passed and 2 in res.outside()
    e_fb = white + 0.5 * np.roll(u, -2)      # u(k) depends on e(k-2): only negative lag
    assert crosscorr_test(e_fb, u, feedback=True).passed
    assert not crosscorr_test(e_fb, u, feedback=False).passed
    both = crosscorr_test(white, np.column_stack([u, u]))
    assert len(both) == 2 and both[0].lags[0] == -25


def test_crosscorr_bound_grows_with_coloured_signals():
    rng = np.random.default_rng(3)
    e = lfilter([1], [1, -0.8], rng.standard_normal(4000))
    u = lfilter([1], [1, -0.8], rng.standard_normal(4000))
    assert crosscorr_test(e, u).bound > 2.58 / np.sqrt(4000) * 1.5


def test_nan_samples_left_out():
    rng = np.random.default_rng(4)
    e = rng.standard_normal(1000)
    e[100:200] = np.nan
    res = autocorr_test(e)
    assert res.bound == pytest.approx(2.5758 / np.sqrt(900), rel=1e-4)


def test_fit_percent_by_hand():
    y = np.array([1.0, 2.0, 3.0, 4.0])
    yhat = np.array([1.0, 2.0, 3.0, 5.0])
    # ‖y−ŷ‖ = 1, ‖y−ȳ‖ = sqrt(2.25+0.25+0.25+2.25) = sqrt(5)
    assert fit_percent(y, yhat) == pytest.approx(100 * (1 - 1 / np.sqrt(5)))
    assert fit_percent(y, y) == 100.0
    assert fit_percent(y, np.full(4, 2.5)) == pytest.approx(0.0)
    assert rmse(y, yhat) == pytest.approx(0.5)


def test_cycle_fuel_error_known_case():
    Ts = 0.5
    y = np.full(8, 10.0)
    yhat = np.r_[np.full(4, 11.0), np.full(4, 9.5)]
    cycle = np.r_[np.zeros(4, int), np.ones(4, int)]
    err = cycle_fuel_error(y, yhat, cycle, Ts)
    assert err == pytest.approx({0: 10.0, 1: -5.0})
    tab = error_table(err)
    assert tab["mean"] == pytest.approx(2.5)
    assert tab["rms"] == pytest.approx(np.sqrt((100 + 25) / 2))


def test_the_metrics_agree_on_any_number_of_blas_threads():
    """On 18,000 samples OpenBLAS may share the dot products out over two threads and sum them in another order:
    the figures of `fuelid identify` and `fuelid compare` then agree to rounding."""
    rng = np.random.default_rng(0)
    e, u, y = rng.standard_normal(18000), rng.standard_normal((18000, 2)), rng.standard_normal(18000)
    figures = []
    for threads in (1, 2):
        with threadpool_limits(limits=threads, user_api="blas"):
            figures.append((autocorr_test(e).r, crosscorr_test(e, u)[1].r, fit_percent(y, y + e)))
    for one, two in zip(*figures):
        np.testing.assert_allclose(one, two, rtol=1e-12, atol=1e-15)
