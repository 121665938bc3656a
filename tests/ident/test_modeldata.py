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
