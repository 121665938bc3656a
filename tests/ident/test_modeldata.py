"""ident.modeldata: effects as a model's inputs and its (shifted) fuel."""
import numpy as np
import pytest

from fuelid.ident.fueldelay import shift_signal
from fuelid.ident.enginemap import EngineMap
from fuelid.ident.identify import identify_model
from fuelid.ident.modeldata import apply_effects
from fuelid.ident.validation import evaluate
from tests.ident import engine_data, hidden


def test_apply_effects_gives_inputs_orders_and_structure():
    ds = hidden.make(None, n=2000)
    out = apply_effects(ds, ["inertia", "dpf_regeneration", "fuel_delay=0.3"])
    assert out.u.shape == (2000, 4) and out.effects == ("inertia", "dpf_regeneration", "fuel_delay")
    assert out.parameters == {"fuel_delay": 0.3}
    s = out.extend(hidden.STRUCTURE)
    assert s.n_inputs == 6 and s.nb[2:] == (2, 1, 1, 1)
    assert np.allclose(out.y[5:-5], shift_signal(ds.y, 1.0)[5:-5])
    with pytest.raises(ValueError, match="unknown effect"):
        apply_effects(ds, ["warp_drive"])
    with pytest.raises(ValueError, match="fuel_delay needs"):
        apply_effects(ds, ["fuel_delay"])


def test_a_fuel_scaling_on_an_engine_model_scales_the_map_too():
    """On an engine model an effect that scales the fuel, y (1 + m x), gets one column more than on the linear
    model: x times the map beyond its plane (with x, x·ñ, x·T̃: x times the whole map), in either order of the ids."""
    ds = hidden.make(None, n=2000)
    linear = apply_effects(ds, ["dpf_regeneration"])
    for ids in (["engine_map", "dpf_regeneration"], ["dpf_regeneration", "engine_map"]):
        out = apply_effects(ds, ids)
        regen = [i for i, n in enumerate(out.names) if n.startswith("dpf_regeneration")]
        beyond = out.u[:, out.names.index("engine_map: map beyond the plane")]
        assert len(regen) == linear.u.shape[1] + 1
        assert np.allclose(out.u[:, regen[:-1]], linear.u)
        assert np.allclose(out.u[:, regen[-1]], linear.u[:, 0] * beyond)
        assert out.names[regen[-1]].endswith("x map beyond the plane") and np.ptp(out.u[:, regen[-1]]) > 0


def test_a_hidden_torque_on_an_engine_model_burns_at_the_maps_marginal_fuel():
    """On an engine model a torque x the bus does not report (the fan's) gets one column more than on the linear
    model: x times the map's torque slope beyond its plane, ∂m/∂T (with x through the torque path's gain: x ∂f/∂T)."""
    ds = engine_data.trip(fan_kw=15.0, n=3000)
    linear = apply_effects(ds, ["engine_fan"])
    out = apply_effects(ds, ["engine_map", "engine_fan"])
    fan = [i for i, n in enumerate(out.names) if n.startswith("engine_fan")]
    emap = EngineMap.from_dict(out.parameters["engine_map"])
    slope = emap.torque_slope(ds.u[:, 0], ds.u[:, 1]) - emap.plane[2]
    assert len(fan) == 2 and np.allclose(out.u[:, fan[0]], linear.u[:, 0])
    assert np.allclose(out.u[:, fan[1]], linear.u[:, 0] * slope) and np.ptp(out.u[:, fan[1]]) > 0
    assert out.units[fan[1]] == "Nm/kW.L/h/Nm"


def test_an_engine_model_with_a_hidden_torque_simulates_another_day_at_the_noise_floor():
    """A fan of 15 kW at full speed on a curved map: the fuel of its torque follows the map's marginal fuel
    (0.02–0.04 L/h per Nm here), so the engine model with engine_fan simulates another day's trip within 12 % of the
    noise floor; with x through the torque path's one gain alone, 19–24 % above it (seeds 2 and 4)."""
    model = identify_model(engine_data.trip(fan_kw=15.0, seed=2), hidden.STRUCTURE, ["engine_map", "engine_fan"])
    other = engine_data.trip(fan_kw=15.0, seed=3)
    assert evaluate(model, other)["rmse"]["simulation"] < 1.12 * engine_data.noise_floor()
