"""ident.export: the MATLAB script and the .mat file give back polynomials that simulate exactly as fuelid does."""
import re
import warnings

import numpy as np
import pytest
from scipy.io import loadmat
from scipy.signal import lfilter

from fuelid.ident.export import matlab_script, write_mat
from fuelid.ident.modelfile import PAPER_MODELS, load_paper_model
from fuelid.ident.pem import pem
from fuelid.ident.polymodel import PolyModel, simulate

@pytest.fixture(scope="module")
def fitted():
    """A PEM model (covariance and noise variance known) with input delays 2 and 0 and an awkward name."""
    rng = np.random.default_rng(5)
    u = rng.normal(size=(1200, 2)) * [100.0, 300.0] + [600.0, 0.0]
    truth = PolyModel(A=[1], B=[[0, 0, 0.0013, 0.0007], [0.002]], F=[[1, -0.6], [1, -0.3]], C=[1, 0.3],
                      D=[1, -0.8], Ts=0.3, nk=(2, 0), u0=(600.0, 0.0), y0=2.0)
    y = simulate(truth, u) + 0.02 * rng.normal(size=1200)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = pem(u, y, truth.structure, 0.3, u0=(600.0, 0.0), y0=2.0)
    m.input_names, m.input_units = ("engine_speed", "torque 'net'"), ("rpm", "Nm")
    m.output_name, m.output_unit = "fuel_flow", "L/h"
    return m


def models(fitted):
    yield fitted
    if PAPER_MODELS.exists():  # the seed paper's diesel model, as shipped beside the repository
        yield load_paper_model("diesel_scania_p320")


def exported_simulation(A, B, F, u0, y0, u):
    """y = y0 + 1/A Σ B_i/F_i (u_i − u0_i), the idpoly's noise-free response, by scipy's lfilter alone."""
    x = sum(lfilter(np.ravel(b), np.ravel(f), u[:, i] - np.ravel(u0)[i]) for i, (b, f) in enumerate(zip(B, F)))
    return float(np.ravel(y0)[0]) + lfilter([1.0], np.ravel(A), x)


def test_mat_file_reproduces_the_simulation(fitted, tmp_path):
    u = np.random.default_rng(1).normal(size=(500, 2)) * [200.0, 400.0] + [900.0, 500.0]
    for model in models(fitted):
        write_mat(model, tmp_path / "m.mat")
        v = loadmat(tmp_path / "m.mat")
        B, F = [v["B"][0, i] for i in range(len(model.B))], [v["F"][0, i] for i in range(len(model.F))]
        np.testing.assert_array_equal(exported_simulation(v["A"], B, F, v["u0"], v["y0"], u), simulate(model, u))
        assert v["Ts"][0, 0] == model.Ts and list(v["nk"].ravel()) == list(model.nk)
        assert v["fuel_lag_s"][0, 0] == model.fuel_lag_s == 0.0  # the fuel as logged
        assert [str(s[0]) for s in v["InputUnit"].ravel()] == list(model.input_units)
        if model.covariance is not None:
            np.testing.assert_array_equal(v["P"], model.covariance)
            assert v["NoiseVariance"][0, 0] == model.info["noise_variance"]


def parse_m(text: str) -> dict:
    """The numeric row vectors of the script: NAME = [..]; and NAME = {[..], [..]};"""
    out = {}
    for name, body in re.findall(r"^(\w+) = (\{.*?\}|\[[^\]\n]*\]|[-0-9.e]+);", text, re.M):
        rows = re.findall(r"\[([^\]]*)\]", body) if body[0] in "[{" else [body]
        arrays = [np.array([float(x) for x in r.split()]) for r in rows]
        out[name] = arrays if body[0] == "{" else arrays[0]
    return out


def test_matlab_script_reproduces_the_simulation(fitted):
    u = np.random.default_rng(2).normal(size=(500, 2)) * [200.0, 400.0] + [900.0, 500.0]
    for model in models(fitted):
        text = matlab_script(model, source="model.json")
        v = parse_m(text)
        np.testing.assert_array_equal(exported_simulation(v["A"], v["B"], v["F"], v["u0"], v["y0"], u),
                                      simulate(model, u))
        # delays live in B's leading zeros only; every B row keeps them
        assert all(b[:k].tolist() == [0.0] * k for b, k in zip(v["B"], model.nk)) and "'InputDelay'" not in text
        assert f"'InputName', {{'{model.input_names[0]}'" in text
    assert "'torque ''net'''" in matlab_script(fitted)
    assert f"NoiseVariance = {fitted.info['noise_variance']!r};" in matlab_script(fitted)


def test_an_engine_model_exports_its_map_as_a_hammerstein_block(tmp_path):
    """The engine model's map in the script (B-spline knots and coefficients for spmak, values on a grid for
    griddedInterpolant, coverage, plane, the input columns as a function of n and T) and in the .mat file."""
    from fuelid.ident.export import MAP_GRID, map_grid
    from fuelid.ident.hammerstein import engine_map_of
    from fuelid.ident.identify import identify_model
    from tests.ident import engine_data
    from tests.ident.hidden import STRUCTURE

    model = identify_model(engine_data.trip(k=1.0, n=4000), STRUCTURE, ["engine_map"])
    text = matlab_script(model)
    for name in ("map_speed_knots", "map_coefficients", "map_fuel", "map_covered", "map_plane", "griddedInterpolant",
                 "engine_inputs = @(n, T)"):
        assert name in text, name
    g = map_grid(model)
    emap = engine_map_of(model)
    gn, gt = np.meshgrid(g["map_speed"], g["map_torque"], indexing="ij")
    assert g["map_fuel"].shape == (MAP_GRID, MAP_GRID) and np.allclose(g["map_fuel"], emap(gn, gt))
    write_mat(model, tmp_path / "m.mat")
    mat = loadmat(tmp_path / "m.mat")
    assert np.allclose(mat["map_fuel"], g["map_fuel"]) and mat["map_coefficients"].shape == emap.coef.shape
    assert map_grid(identify_model(engine_data.trip(k=0.0, n=4000), STRUCTURE)) is None
