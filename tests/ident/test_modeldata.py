"""ident.modeldata: effects as a model's inputs and its (shifted) fuel."""
import numpy as np
import pytest

from fuelid.ident.fueldelay import shift_signal
from fuelid.ident.modeldata import apply_effects
from tests.ident import hidden


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
