import numpy as np
import pytest

from fuelid.errors import FuelidError
from fuelid.ident.baseline import (EngineMap, engine_map, fuel_shift_sweep, inertia_sweep, lwr, outside_share, seed2_baselines,
                            static_inputs, static_model, steady_points)
from fuelid.ident.dataset import VEHICLE_SPEED, Dataset

TS = 0.3


def make_ds(n, T, y, v=None):
    N = len(n)
    extra = {} if v is None else {VEHICLE_SPEED: np.asarray(v, float)}
    return Dataset(Ts=TS, t=np.arange(N) * TS, u=np.column_stack([n, T]), y=np.asarray(y, float),
                   input_names=("EEC1.EngSpeed", "EngTorque"), input_units=("rpm", "Nm"),
                   output_name="LFE1.EngFuelRate", output_unit="L/h", u0=np.array([600.0, 50.0]), y0=2.0,
                   valid=np.isfinite(y), cycle=np.zeros(N, int), extra=extra)


def true_map(n, T):
    return 1.0 + 0.004 * n + 0.02 * T + 1e-5 * T * n / 10


def piecewise_drive(seed=0, blocks=300):
    """Alternating 6 s steady blocks (constant v, random n, T) and 3 s ramps (v changing, fuel off-map)."""
    rng = np.random.default_rng(seed)
    n, T, v, y = [], [], [], []
    vv = 50.0
    for _ in range(blocks):
        nn, TT = rng.uniform(700, 1900), rng.uniform(0, 2000)
        vv = (vv + 15 + rng.uniform(3, 60)) % 100     # never within 3 km/h of the last ramp value
        n += [nn] * 20
        T += [TT] * 20
        v += [vv] * 20
        y += [true_map(nn, TT)] * 20
        n += list(rng.uniform(700, 1900, 10))
        T += list(rng.uniform(0, 2000, 10))
        v += list(vv + np.linspace(3, 15, 10))          # accelerating: not steady
        y += list(rng.uniform(0, 100, 10))               # garbage fuel in transients
    return make_ds(np.array(n), np.array(T), np.array(y), np.array(v))


def test_steady_points_only_from_constant_speed():
    ds = piecewise_drive()
    X, f = steady_points(ds)
    assert len(X) == 300 * 2  # two 3-s windows per 6-s block
    assert np.allclose(f, true_map(X[:, 0], X[:, 1]))


def test_engine_map_recovers_static_map():
    ds = piecewise_drive()
    m = engine_map(ds)
    rng = np.random.default_rng(5)
    q = np.column_stack([rng.uniform(900, 1700, 200), rng.uniform(300, 1700, 200)])
    assert np.max(np.abs(m(q) - true_map(q[:, 0], q[:, 1]))) < 0.02 * true_map(q[:, 0], q[:, 1]).max()
    far = m(np.array([[3000.0, 3000.0], [np.nan, 1.0]]))   # outside the hull: nearest; NaN in, NaN out
    assert np.isfinite(far[0]) and np.isnan(far[1])


def test_engine_map_errors():
    ds = make_ds(np.full(50, 800.0), np.full(50, 100.0), np.full(50, 3.0))
    with pytest.raises(FuelidError, match="vehicle speed"):
        engine_map(ds)
    with pytest.raises(FuelidError, match="steady"):
        EngineMap(np.empty((0, 2)), np.empty(0))
    one = EngineMap(np.array([[800.0, 100.0]]), np.array([3.0]))
    assert one(np.array([[900.0, 50.0]]))[0] == 3.0


def test_lwr_recovers_smooth_function():
    rng = np.random.default_rng(1)
    X = rng.uniform([0, -1], [3, 1], size=(3000, 2))
    f = lambda X: np.sin(X[:, 0]) + X[:, 1] ** 2
    y = f(X) + 0.05 * rng.standard_normal(3000)
    Xq = rng.uniform([0.3, -0.8], [2.7, 0.8], size=(300, 2))
    yq = lwr(X, y, Xq, span=0.03)
    assert np.sqrt(np.mean((yq - f(Xq)) ** 2)) < 0.03
    assert np.isnan(lwr(X, y, np.array([[np.nan, 0.0]]))[0])


def sweep_drive(shift_samples=0, J=0.0, N=3000, seed=2):
    rng = np.random.default_rng(seed)
    t = np.arange(N) * TS
    n = 1200 + 400 * np.sin(2 * np.pi * t / 37) + 150 * np.sin(2 * np.pi * t / 5.3)
    T = 900 + 600 * np.sin(2 * np.pi * t / 23 + 1) + 100 * rng.standard_normal(N)
    dw = np.gradient(n * 2 * np.pi / 60, TS)
    Te = T + J * dw
    f = 2 + 0.01 * n * Te / 1000 + 0.002 * n
    y = np.full(N, np.nan)
    y[shift_samples:] = f[: N - shift_samples] if shift_samples else f
    y[:3] = np.nan
    return make_ds(n, T, y, v=np.full(N, 50.0))


def test_fuel_shift_sweep_finds_the_delay():
    ds = sweep_drive(shift_samples=2)      # fuel lags the inputs by 0.6 s
    res = fuel_shift_sweep(ds, "EB", span=0.02)
    assert res["shift_s"][int(np.argmin(res["rmse"]))] == pytest.approx(-0.6)
    assert res["r2"][int(np.argmin(res["rmse"]))] > 0.99
    assert min(res["shift_s"]) == pytest.approx(-0.9) and max(res["shift_s"]) == pytest.approx(0.9)


def test_inertia_sweep_finds_J1():
    ds = sweep_drive(J=2.0)
    res = inertia_sweep(ds, J1_values=np.arange(0, 4.01, 0.5), span=0.02)
    assert res["J1"][int(np.argmin(res["rmse"]))] == pytest.approx(2.0)


def test_vb_inputs():
    ds = sweep_drive()
    ds.extra[VEHICLE_SPEED] = np.arange(len(ds)) * 0.3 * 3.6   # 1 m/s² in km/h
    X = static_inputs(ds, "VB")
    assert np.allclose(X[1:-1, 1], 1.0)


def test_lwr_on_a_grid_is_close_to_exact():
    rng = np.random.default_rng(3)
    X = rng.uniform([0, -1], [3, 1], size=(3000, 2))
    y = np.sin(X[:, 0]) + X[:, 1] ** 2 + 0.05 * rng.standard_normal(3000)
    Xq = np.vstack([rng.uniform([0.3, -0.8], [2.7, 0.8], size=(500, 2)), [[np.nan, 0.0]]])
    exact, gridded = lwr(X, y, Xq, span=0.03), lwr(X, y, Xq, span=0.03, grid=40)
    assert np.sqrt(np.nanmean((gridded - exact) ** 2)) < 0.01 and np.isnan(gridded[-1])


def test_seed2_baselines_pick_the_shift_and_predict_the_measured_fuel():
    """Fuel lagging the inputs by 0.6 s: the sweep picks a 0.6 s advance, and the prediction, shifted back,
    follows the fuel as measured (not the advanced one)."""
    ds = sweep_drive(shift_samples=2)
    res = seed2_baselines(ds, ds, ["EB", "EB*", "VB"], span=0.02, grid=None, J1_values=[0.0, 1.0],
                          sweep_points=1500)
    assert res["fuel_shift"]["best_shift_s"] == pytest.approx(-0.6) and not res["fuel_shift"]["best_at_edge"]
    assert res["J1"]["best_J1"] == 0.0 and res["J1"]["best_at_edge"]
    assert res["errors"] == {}
    yhat = res["predictions"]["EB"]
    ok = np.isfinite(yhat) & np.isfinite(ds.y)
    assert ok.sum() > 2900 and np.sqrt(np.mean((yhat[ok] - ds.y[ok]) ** 2)) < 0.05 * ds.y[ok].std()


def test_seed2_vb_without_vehicle_speed_is_an_error():
    ds = sweep_drive()
    del ds.extra[VEHICLE_SPEED]
    res = seed2_baselines(ds, ds, ["VB", "EB"], span=0.02, grid=None, J1_values=[0.0], sweep_points=500)
    assert "vehicle speed" in res["errors"]["VB"] and "EB" in res["predictions"]


def test_static_model_holds_its_edge_outside_the_calibration_range():
    """A local linear fit would extrapolate without bound; like a lookup table, the model holds the value at
    the edge of the calibration data, and the share of samples that needed it is reported."""
    train = sweep_drive()
    test = sweep_drive(seed=5)
    test.u[:, 0] = test.u[:, 0] * 2.0  # engine speeds up to twice the calibrated ones
    assert outside_share(train, test, "EB") > 0.3
    edge = train.u[train.valid, 0].max()
    held = static_model(train, test, "EB", span=0.02)
    clamped = make_ds(np.minimum(test.u[:, 0], edge), test.u[:, 1], test.y, v=np.full(len(test), 50.0))
    at_edge = static_model(train, clamped, "EB", span=0.02)
    np.testing.assert_allclose(held[test.valid], at_edge[test.valid])
