"""ident.orders: delay estimation and the greedy search for the lowest orders passing eqs. 18-19."""
import numpy as np
import pytest
from scipy.signal import lfilter

from fuelid.errors import InputError
from fuelid.ident.orders import estimate_delays, residual_tests, search_orders
from fuelid.ident.polymodel import PolyModel, simulate

TRUTH = PolyModel(A=[1], B=[[0, 0, 0.6, 0.3], [0.4, 0.2]], F=[[1, -0.8], [1, -1.1, 0.5]], C=[1, 0.5],
                  D=[1, -0.9], Ts=0.3, nk=(2, 0))


def data(n=4000, seed=0):
    rng = np.random.default_rng(seed)
    u = lfilter([1.0], [1.0, -0.3], rng.normal(size=(n, 2)), axis=0)
    y = simulate(TRUTH, u) + lfilter(TRUTH.C, TRUTH.D, 0.1 * rng.normal(size=n))
    return u, y


def test_estimate_delays():
    u, y = data()
    assert estimate_delays(u, y) == (2, 0)


def test_search_finds_passing_low_orders():
    u, y = data()
    res = search_orders(u, y, 0.3)
    assert res.passed and res.trials[-1].passed
    s = res.structure
    assert s.nk == (2, 0)
    assert s.nf[1] >= 2 and s.nc >= 1
    assert s.n_params <= TRUTH.structure.n_params + 4  # lowest on the path, not a big over-fit
    assert not any(t.passed for t in res.trials[:-1])
    assert residual_tests(res.model, u, y) == (True, (True, True))


def test_data_too_short_for_the_delay_estimate_are_an_input_error_saying_what_to_do():
    """30 s at 0.3 s: fewer samples than the delays' ARX model needs; the error says to give the orders."""
    u, y = data(n=100)
    with pytest.raises(InputError, match=r"too little data to estimate the delays for --orders auto \(100 samples .* "
                                         r"52 parameters.*give the orders"):
        search_orders(u, y, 0.3)
