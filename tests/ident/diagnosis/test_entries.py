"""ident.diagnosis.entries: every effect enters the model in one of the known ways."""
from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.entries import ENTRIES
from tests.ident import hidden


def test_every_effect_enters_the_model_one_known_way():
    """Each catalogue effect's entry kind is one of ident.diagnosis.entries.ENTRIES (the one place a new kind goes)."""
    ds = hidden.make(None, n=500)
    assert {e.enters for e in list(fx.EFFECTS.values()) + fx.generic_effects(ds)} <= set(ENTRIES)
    assert fx.EFFECTS["fuel_delay"].enters == "shift" and fx.EFFECTS["engine_fan"].enters == "torque"
