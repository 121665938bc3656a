"""ident.diagnosis.candidate: what `fuelid identify --effects-from` reads from a saved result, and what a model
carries."""
from fuelid.ident import diagnosis as dg
from fuelid.ident.diagnosis.candidate import effects_carried


def test_confirmed_effects_are_exactly_the_recommended_ones_in_order():
    rows = [{"id": "a", "effect": "a", "spec": "a", "recommended": True},
            {"id": "fuel_delay", "effect": "fuel_delay", "spec": "fuel_delay=0.40", "recommended": True},
            {"id": "b", "effect": "b", "spec": "b", "recommended": False, "significant": True},
            {"effect": "old"}]
    assert dg.confirmed_effects(rows) == ["a", "fuel_delay=0.40"]
    assert dg.effects_to_add({"candidates": rows, "engine_map": {"status": "advised"}}) == \
        ["engine_map", "a", "fuel_delay=0.40"]
    assert dg.effects_to_add({"candidates": rows, "engine_map": {"status": "not needed"}}) == ["a", "fuel_delay=0.40"]
    assert dg.effects_to_add({"candidates": rows, "engine_map": "engine_map"}) == ["a", "fuel_delay=0.40"]


def test_the_engine_model_carries_the_injection_cut_the_linear_model_does_not():
    assert effects_carried(["engine_map", "fuel_delay=0.10"]) == {"engine_map", "fuel_delay", "overrun_cutoff"}
    assert effects_carried(["dpf_regeneration"]) == {"dpf_regeneration"}
