from types import SimpleNamespace

import numpy as np
import pytest

from fuelid.ident.hammerstein import MAP_COLUMN, engine_map_of, static_gain, steady_state_map
from fuelid.ident.identify import identify_model, kept_fit
from fuelid.ident.modelfile import from_dict, to_dict
from fuelid.ident.validation import evaluate
from tests.ident import engine_data
from tests.ident.hidden import STRUCTURE


@pytest.fixture(scope="module")
def engine():
    ds = engine_data.trip(k=1.0)
    return ds, identify_model(ds, STRUCTURE, ["engine_map"]), identify_model(ds, STRUCTURE)


def test_the_joint_identification_recovers_a_hammerstein_engines_steady_state_map(engine):
    """Known dynamics and a curved map: the model's steady state (plane of the linear paths + the map beyond it) is the
    true map within 0.15 L/h RMS over the data's region (the curvature spans 3.5 L/h), the map's transfer function has
    unit static gain (set after each map step; the last PEM step moves it by little), and V fell over the joint
    rounds."""
    ds, model, _ = engine
    emap = engine_map_of(model)
    gn, gt = np.meshgrid(np.linspace(700, 1800, 12), np.linspace(100, 1600, 12))
    inside = emap.covered(gn, gt)
    err = steady_state_map(model, gn, gt) - engine_data.steady_state(gn, gt)
    assert inside.mean() > 0.8 and np.sqrt(np.mean(err[inside] ** 2)) < 0.15
    j = model.input_names.index(MAP_COLUMN)
    assert static_gain(model.B[j], model.F[j]) == pytest.approx(1.0, abs=1e-9)
    history = model.info["joint"]["loss_V"]
    assert history[-1] < history[0]


def test_the_joint_fit_starts_from_the_linear_dynamics_and_from_the_static_map_and_keeps_the_lower_loss(engine):
    """Both starts of step (a) are recorded; the rounds go on from the one identify's rule keeps (the lower V unless
    the other simulates grossly better), and end no higher than it."""
    _, model, _ = engine
    starts = model.info["joint"]["starts"]
    assert list(starts) == ["given", "static map"]
    fits = [SimpleNamespace(info={"loss_V": v["loss_V"]}) for v in starts.values()]
    kept = list(starts.values())[kept_fit(fits, [v["simulation_rmse"] for v in starts.values()])]
    assert model.info["joint"]["loss_V"][0] == pytest.approx(kept["loss_V"], rel=1e-12)
    assert min(model.info["joint"]["loss_V"]) <= kept["loss_V"]


def test_a_model_refitted_from_itself_goes_on_from_its_own_map(engine):
    """identify_model with init = an engine model: the map inputs are the model's (not a fresh static fit) and the
    joint fit has no static start, so a refit on the same data starts at the model's own loss."""
    ds, model, _ = engine
    again = identify_model(ds, STRUCTURE, ["engine_map"], init=model)
    assert set(again.info["joint"]["starts"]) == {"given"}
    assert again.info["joint"]["loss_V"][0] <= 1.01 * model.info["loss_V"]


def test_the_model_s_steady_state_is_its_fitted_map(engine):
    """The map the model file carries is the model's steady state over the knot box (the plane of the paths' static
    gains, the map beyond it): what the report draws and a fleet compares is what the model simulates at rest."""
    ds, model, _ = engine
    emap = engine_map_of(model)
    (n_lo, n_hi), (t_lo, t_hi) = emap.speed_range, emap.torque_range
    gn, gt = np.meshgrid(np.linspace(n_lo, n_hi, 9), np.linspace(t_lo + 1.0, 1.5 * t_hi, 9))
    f, s = steady_state_map(model, gn, gt), emap(gn, gt)
    assert np.abs(f - s).max() < 1e-6 * np.abs(s).max()


def test_renormalising_the_map_to_the_steady_state_keeps_the_model_s_simulation(engine):
    """as_steady_state moves the paths' plane and the map block's gain into the map: the simulation is unchanged up
    to the transient column's share of the plane's change (here under 1 % of the fuel's RMS)."""
    import dataclasses

    from fuelid.ident.hammerstein import MAP_EFFECT, as_steady_state
    from fuelid.ident.polymodel import simulate
    from fuelid.ident.modeldata import model_data

    ds, model, _ = engine
    j = model.input_names.index(MAP_COLUMN)
    moved = dataclasses.replace(model, B=[b * (1.3 if i in (0, j) else 1.0) for i, b in enumerate(model.B)])
    again = as_steady_state(moved)
    assert static_gain(again.B[j], again.F[j]) == pytest.approx(1.0)
    gn, gt = np.meshgrid(np.linspace(800, 1700, 5), np.linspace(200, 1500, 5))
    assert np.allclose(steady_state_map(again, gn, gt), engine_map_of(again)(gn, gt))
    assert np.allclose(steady_state_map(again, gn, gt), steady_state_map(moved, gn, gt))
    seg = ds.segments()[0]
    y1, y2 = (simulate(m, model_data(m, ds)[0][seg]) for m in (moved, again))
    assert np.sqrt(np.mean((y1 - y2) ** 2)) < 0.01 * np.sqrt(np.mean(y1 ** 2))
    assert again.effects == moved.effects and MAP_EFFECT in again.info["effect_parameters"]


def test_the_engine_model_simulates_another_day_near_the_noise_and_the_linear_one_does_not(engine):
    ds, model, linear = engine
    other_day = engine_data.trip(k=1.0, seed=7)
    rmse = {name: evaluate(m, other_day)["rmse"]["simulation"] for name, m in (("engine", model), ("linear", linear))}
    floor = engine_data.noise_floor()
    assert rmse["engine"] < 1.1 * floor and rmse["linear"] > 3 * floor, (rmse, floor)


def test_the_model_file_carries_the_map_and_rebuilds_its_input(engine):
    ds, model, _ = engine
    again = from_dict(to_dict(model))
    assert engine_map_of(again).to_dict() == engine_map_of(model).to_dict()
    assert evaluate(again, ds)["rmse"] == model.validation["rmse"]


def test_a_linear_model_s_steady_state_is_its_plane():
    linear = identify_model(engine_data.trip(k=0.0, n=6000), STRUCTURE)
    gn, gt = np.meshgrid(np.linspace(700, 1800, 5), np.linspace(100, 1600, 5))
    f = steady_state_map(linear, gn, gt)
    assert np.abs(f - engine_data.steady_state(gn, gt, k=0.0)).max() < 0.3


def test_the_map_summary_says_its_region_coverage_and_fuel(engine):
    from fuelid.ident.hammerstein import map_summary

    ds, model, linear = engine
    s = map_summary(model)
    assert s["units"] == {"speed": "rpm", "torque": "Nm", "fuel": "L/h"} and 0.5 < s["covered_share"] <= 1.0
    assert s["speed_range"][0] == pytest.approx(ds.u[:, 0].min(), rel=1e-3) and s["steady_state_range"][1] > s["steady_state_range"][0]
    assert map_summary(linear) is None
