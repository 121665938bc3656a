import json

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.interpolate import BSpline

from fuelid.errors import InputError
from fuelid.ident.enginemap import (BLOCK, CUT_TORQUE, CV_FOLDS, DEGREE, SMOOTHING_GRID, EngineMap, _axis, _axis_slope,
                                   cv_smoothing, fit_map, fold_grams, knots, penalised_fit, penalty_gram)


def surface(n, T):
    """A smooth fuel map [L/h], monotone in torque: 2 + 0.03 T + 6 ((T − 600)/1000)² + 2 ((n − 1200)/600)² T/1700."""
    return 2.0 + 0.03 * T + 6.0 * ((T - 600.0) / 1000.0) ** 2 + 2.0 * ((n - 1200.0) / 600.0) ** 2 * (T / 1700.0)


def samples(size=6000, seed=0, noise=0.3):
    rng = np.random.default_rng(seed)
    n, T = rng.uniform(600, 1900, size), rng.uniform(20, 1700, size)
    return n, T, surface(n, T) + rng.normal(0, noise, size)


@given(st.floats(-500.0, 500.0), st.floats(1.0, 3000.0), st.floats(0.0, 1.0))
def test_the_basis_and_its_slope_are_scipys_b_splines_on_the_knots(lo, width, at):
    t = knots(lo, lo + width)
    splines = BSpline(t, np.eye(len(t) - DEGREE - 1), DEGREE)
    x = lo + at * width
    assert np.allclose(_axis(t, [x])[0], splines(x), rtol=0, atol=1e-12)
    assert np.allclose(_axis_slope(t, [x])[0], splines.derivative()(x), rtol=0, atol=1e-12 / width)


@pytest.fixture(scope="module")
def fitted():
    n, T, y = samples()
    return fit_map(n, T, y, (600.0, 112.0), 2.0, ("rpm", "Nm", "L/h"))


def test_a_known_surface_is_recovered_within_a_tenth_of_the_noise(fitted):
    gn, gt = np.meshgrid(np.linspace(650, 1850, 25), np.linspace(50, 1650, 25))
    err = fitted(gn, gt) - surface(gn, gt)
    assert np.sqrt(np.mean(err ** 2)) < 0.1  # noise 0.3 L/h on each of 6000 samples
    assert fitted.covered(gn, gt).all() and not fitted.covered(3000.0, 800.0)


def test_the_map_is_monotone_in_torque_and_never_negative_even_where_the_data_say_otherwise():
    n, T, y = samples(noise=3.0, seed=1)  # noise 3 L/h: an unconstrained fit would wiggle down somewhere
    emap = fit_map(n, T, y, (600.0, 112.0), 2.0, ("rpm", "Nm", "L/h"))
    gn, gt = np.meshgrid(np.linspace(400, 2500, 40), np.linspace(-100, 2500, 200), indexing="ij")
    f = emap(gn, gt)
    assert (np.diff(f, axis=1) >= -1e-9).all()
    assert (f >= 0).all()


def test_a_map_steep_at_its_lowest_torque_is_fitted_without_bending_the_edge_up():
    # 0.5 L/h at 20 Nm rising 0.03 L/h per Nm: one knot interval below the data the plane would be negative
    rng = np.random.default_rng(2)
    n, T = rng.uniform(600, 1900, 6000), rng.uniform(20, 1700, 6000)
    def plane(n, T):
        return 0.5 + 0.03 * (T - 20.0) + 1e-4 * (n - 600.0)
    emap = fit_map(n, T, plane(n, T) + rng.normal(0, 0.05, n.size), (600.0, 112.0), 0.5, ("rpm", "Nm", "L/h"))
    gn, gt = np.meshgrid(np.linspace(620, 1880, 20), np.linspace(20, 300, 20))
    assert np.abs(emap(gn, gt) - plane(gn, gt)).max() < 0.05
    assert (emap.coef[:, 0] < 0).all() and emap(gn, np.full_like(gn, 20.0)).min() > 0


def test_the_smoothing_minimises_the_error_of_each_held_out_fold_of_blocks():
    n, T, y = samples(size=2000, seed=3)
    shell = fit_map(n, T, y, (600.0, 112.0), 2.0, ("rpm", "Nm", "L/h"), smoothing=1.0)
    phi, (kn, kt) = shell.basis(n, T), shell.coef.shape
    fold = np.arange(len(y)) // BLOCK % CV_FOLDS
    def held_out_error(lam):  # refit without each fold, unconstrained, and predict it
        err = 0.0
        for f in range(CV_FOLDS):
            c, *_ = penalised_fit(phi[fold != f], y[fold != f], kn, kt, smoothing=lam * np.trace(phi.T @ phi) /
                                 np.trace(phi[fold != f].T @ phi[fold != f]), monotone=False)
            err += np.sum((y[fold == f] - phi[fold == f] @ c) ** 2)
        return err
    chosen = cv_smoothing(*fold_grams(phi, y), penalty_gram(kn, kt))
    assert held_out_error(chosen) <= min(held_out_error(lam) for lam in SMOOTHING_GRID) * (1 + 1e-9)


def test_with_errors_correlated_in_time_the_map_is_smoothed_rather_than_fitted_to_the_drift():
    # AR(1) errors, 0.98 per sample (a 50-sample memory) and 1 L/h std: a slow drift that samples in time order
    # follow along the operating points they visit; a leave-one-sample-out choice takes the drift for the map
    rng = np.random.default_rng(4)
    size = 6000
    walk = np.cumsum(rng.normal(0, 1, (size, 2)), axis=0)
    n = 600 + 1300 * (np.sin(walk[:, 0] / 20) + 1) / 2
    T = 20 + 1680 * (np.sin(walk[:, 1] / 20) + 1) / 2
    e = np.zeros(size)
    for k in range(1, size):
        e[k] = 0.98 * e[k - 1] + rng.normal(0, 0.2)
    emap = fit_map(n, T, surface(n, T) + e, (600.0, 112.0), 2.0, ("rpm", "Nm", "L/h"))
    rough = fit_map(n, T, surface(n, T) + e, (600.0, 112.0), 2.0, ("rpm", "Nm", "L/h"), smoothing=SMOOTHING_GRID[0])
    gn, gt = np.meshgrid(np.linspace(650, 1850, 25), np.linspace(50, 1650, 25))
    def error(m):
        return np.sqrt(np.mean((m(gn, gt) - surface(gn, gt)) ** 2))
    assert emap.smoothing > SMOOTHING_GRID[0] and error(emap) < error(rough)


def test_outside_its_region_speed_is_clamped_and_torque_continues_linearly_above(fitted):
    (n_lo, n_hi), (t_lo, t_hi) = fitted.speed_range, fitted.torque_range
    T = np.array([300.0, 900.0])
    assert np.allclose(fitted(np.full(2, n_hi + 500), T), fitted(np.full(2, n_hi), T))
    assert np.allclose(fitted(np.full(2, n_lo - 300), T), fitted(np.full(2, n_lo), T))
    above = fitted(np.full(3, 1200.0), t_hi + np.array([100.0, 200.0, 300.0]))
    slope = np.diff(above) / 100.0
    assert np.allclose(slope[0], slope[1]) and slope[0] > 0
    assert np.isclose(fitted(1200.0, t_lo / 2), fitted(1200.0, t_lo))  # clamped between the cut and T_lo


def test_at_or_below_zero_torque_the_fuel_is_cut(fitted):
    assert np.all(fitted(np.full(3, 1200.0), np.array([CUT_TORQUE, -50.0, -500.0])) == 0.0)
    assert fitted(1200.0, 50.0) > 0
    assert np.all(fitted.basis([1200.0, 1300.0], [-10.0, np.nan]) == 0.0)


def test_the_torque_slope_is_the_maps_derivative_and_zero_where_the_map_is_flat_or_cut(fitted):
    """∂s/∂T: the map's own derivative (the surface's within a few % over the data), the extrapolation's slope above
    the knot box, 0 between the cut and T_lo (the map is clamped there) and at or below the cut."""
    n = np.array([700.0, 1300.0, 1800.0, 1300.0])
    T = np.array([200.0, 800.0, 1500.0, fitted.torque_range[1] + 200.0])
    h = 1e-3
    slope = fitted.torque_slope(n, T)
    assert np.allclose(slope, (fitted(n, T + h) - fitted(n, T - h)) / (2 * h), rtol=1e-6)
    truth = 0.03 + 12.0 * (T[:3] - 600.0) / 1e6 + 2.0 * ((n[:3] - 1200.0) / 600.0) ** 2 / 1700.0
    assert np.allclose(slope[:3], truth, rtol=0.1)
    below = np.array([fitted.torque_range[0] / 2, CUT_TORQUE, -100.0, np.nan])
    assert np.all(fitted.torque_slope(np.full(4, 1300.0), below) == 0.0)


def test_the_map_beyond_its_plane_has_no_slope_over_its_data_and_its_level_above_the_operating_fuel(fitted):
    n, T, _ = samples()
    m = fitted.beyond_plane(n, T)
    P = np.column_stack([np.ones_like(n), n, T])
    coef = np.linalg.lstsq(P, m, rcond=None)[0]
    assert np.abs(coef[1:] * [n.std(), T.std()]).max() < 1e-6 * m.std()
    assert np.allclose(fitted(n, T) - m, fitted.plane_at(n, T)) and fitted.plane_at(600.0, 112.0) == 2.0


def test_to_dict_and_back_gives_the_same_map_with_its_units(fitted):
    d = json.loads(json.dumps(fitted.to_dict()))
    assert d["units"] == {"speed": "rpm", "torque": "Nm", "fuel": "L/h"}
    again = EngineMap.from_dict(d)
    n, T, _ = samples(size=100, seed=5)
    assert np.array_equal(again(n, T), fitted(n, T)) and np.array_equal(again.covered(n, T), fitted.covered(n, T))
    with pytest.raises(InputError, match="malformed engine map"):
        EngineMap.from_dict({"speed_knots": [1, 2]})


def test_too_few_fuelled_samples_is_an_input_error():
    with pytest.raises(InputError, match="at least"):
        fit_map(np.full(50, 1000.0), np.linspace(1, 100, 50), np.ones(50), (600.0, 0.0), 1.0)


def test_a_plane_s_coefficients_reproduce_the_plane_over_the_knot_box():
    from fuelid.ident.enginemap import EngineMap, knots

    tn, tt = knots(600.0, 2000.0), knots(0.0, 1500.0)
    shell = EngineMap(tn, tt, np.zeros(81), (0, 0, 0), (700.0, 100.0), 1.0, 0.0, np.zeros((12, 12)), "rpm", "Nm")
    plane = shell.with_coefficients(shell.plane_coefficients(3.0, 0.01, 0.02), (3.0, 0.01, 0.02))
    n, T = np.meshgrid(np.linspace(600, 2000, 7), np.linspace(1, 1500, 7))
    assert np.allclose(plane(n, T), plane.plane_at(n, T)) and np.allclose(plane.beyond_plane(n, T), 0.0, atol=1e-9)


@pytest.mark.parametrize("rho", [0.0, 0.9])
def test_the_coefficients_covariance_predicts_the_spread_of_the_map_over_repeated_noisy_data(rho):
    """Over 40 draws of the data (noise white, or AR(1) with ρ = 0.9 as a simulation error is), the spread of s at
    three points is the one φᵀ Cov(ĉ) φ predicts (within the Monte-Carlo error of 40 draws and the estimator's own)."""
    rng = np.random.default_rng(7)
    n, T = rng.uniform(600, 1900, 3000), rng.uniform(200, 1700, 3000)
    points = (np.array([900.0, 1200.0, 1600.0]), np.array([500.0, 1000.0, 1400.0]))
    values, predicted = [], []
    for _ in range(40):
        e = rng.normal(0.0, 0.5, n.size)
        noise = np.empty_like(e)
        noise[0] = e[0]
        for k in range(1, e.size):  # AR(1), unit-variance scaled
            noise[k] = rho * noise[k - 1] + np.sqrt(1 - rho ** 2) * e[k]
        emap = fit_map(n, T, surface(n, T) + noise, (600.0, 112.0), 2.0, ("rpm", "Nm", "L/h"), smoothing=1e-3)
        phi = emap.basis(*points)
        values.append(emap(*points))
        predicted.append(np.sqrt(np.einsum("pk,kl,pl->p", phi, emap.covariance, phi)))
    ratio = np.std(values, axis=0, ddof=1) / np.mean(predicted, axis=0)
    assert ((ratio > 0.6) & (ratio < 1.5)).all(), ratio


def test_the_covariance_travels_with_the_map(fitted):
    again = EngineMap.from_dict(json.loads(json.dumps(fitted.to_dict())))
    assert again.covariance.shape == (fitted.coef.size, fitted.coef.size)
    assert np.allclose(again.covariance, fitted.covariance)
