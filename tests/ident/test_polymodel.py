"""ident.polymodel: structures, simulation, residuals and k-step prediction against direct filtering."""
import math

import numpy as np
import pytest
from scipy.signal import lfilter

from fuelid.ident.polymodel import (PolyModel, Structure, from_theta, parameter_names, polynomials, predict, residuals,
                                    simulate)


def model(**kw):
    base = dict(A=[1.0, -0.5], B=[[0, 0.5, 0.2], [0.3]], F=[[1.0, -0.7], [1.0]], C=[1.0, 0.4], D=[1.0, -0.9],
                Ts=0.3, nk=(1, 0))
    return PolyModel(**{**base, **kw})


def data(m, n=500, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 2))
    e = rng.normal(size=n)
    x = sum(lfilter(m.B[i], m.F[i], u[:, i]) for i in range(2))
    y = lfilter([1.0], m.A, x + lfilter(m.C, m.D, e))
    return u, y, e


def test_named_structures():
    assert Structure.arx(2, (3, 1), (1, 0)).kind == "arx"
    assert Structure.armax(2, 3, 1, 1).kind == "armax"
    assert Structure.oe((4, 5), (5, 5), (3, 0)).kind == "oe"
    s = Structure.bj((4, 5), (5, 5), (3, 0), 11, 11)
    assert s.kind == "bj" and s.n_params == 41 and s.n_start == 11
    assert parameter_names(Structure.bj(2, 1, 3, 1, 0)) == ["b1_3", "b1_4", "f1_1", "c1"]
    with pytest.raises(ValueError):
        Structure(nb=(1, 2), nf=(1,), nk=(0, 0))


def test_theta_round_trip_and_structure():
    m = model()
    assert m.structure == Structure(nb=(2, 1), nf=(1, 0), nk=(1, 0), nc=1, nd=1, na=1)
    back = from_theta(m.theta, m.structure, m.Ts)
    for a, b in zip([back.A, *back.B, *back.F, back.C, back.D], [m.A, *m.B, *m.F, m.C, m.D]):
        np.testing.assert_array_equal(a, b)


def test_polynomials_of_theta_in_the_order_of_parameter_names():
    s = Structure(nb=(2, 1), nf=(1, 0), nk=(2, 0), nc=1, nd=0, na=1)
    p = polynomials(np.arange(1.0, s.n_params + 1), s)  # a1 b1_2 b1_3 b2_0 f1_1 c1
    for got, want in zip([p.A, *p.B, *p.F, p.C, p.D], [[1, 1], [0, 0, 2, 3], [4], [1, 5], [1], [1, 6], [1]]):
        np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="needs 6"):
        polynomials(np.zeros(5), s)


def test_invalid_polynomials_rejected():
    with pytest.raises(ValueError, match="monic"):
        model(C=[2.0, 0.1])
    with pytest.raises(ValueError, match="nk"):
        model(B=[[0.1, 0.5], [0.3]])


def test_simulate_residuals_predict():
    m = model()
    u, y, e = data(m)
    x = sum(lfilter(m.B[i], m.F[i], u[:, i]) for i in range(2))
    np.testing.assert_allclose(simulate(m, u), lfilter([1.0], m.A, x))
    np.testing.assert_allclose(residuals(m, u, y), e, atol=1e-10)  # the true model whitens exactly
    np.testing.assert_allclose(predict(m, u, y, 1), y - e, atol=1e-10)
    np.testing.assert_array_equal(predict(m, u, y, math.inf), simulate(m, u))
    # H = C/(A D) has poles 0.5 and 0.9: after 400 steps the predictor is the simulation
    np.testing.assert_allclose(predict(m, u, y, 400), simulate(m, u), atol=1e-8)
    with pytest.raises(ValueError):
        predict(m, u, y, 0)


def test_operating_point():
    m = model()
    u, y, _ = data(m)
    shifted = model(u0=(600.0, 5.0), y0=2.5)
    np.testing.assert_allclose(simulate(shifted, u + [600.0, 5.0]), simulate(m, u) + 2.5)
    np.testing.assert_allclose(residuals(shifted, u + [600.0, 5.0], y + 2.5), residuals(m, u, y), atol=1e-10)
