"""ident.diagnosis.candidate: what `fuelid identify --effects-from` reads from a saved result, and what a model
carries."""
from fuelid.ident import diagnosis as dg
from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.candidate import Candidate, Status, carried_by_engine_model


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


def test_the_engine_model_carries_the_injection_cut_unless_the_model_has_it_as_its_own_effect():
    cut, own, regen = (Candidate(fx.EFFECTS["overrun_cutoff"]), Candidate(fx.EFFECTS["overrun_cutoff"],
                       Status.ALREADY_IN_MODEL), Candidate(fx.EFFECTS["dpf_regeneration"]))
    assert carried_by_engine_model([cut, own, regen]) == [cut]
    assert (cut.status, cut.explained_by) == (Status.ALREADY_IN_MODEL, "engine_map")
    assert own.explained_by is None and regen.status is Status.NOT_TESTABLE
