"""ident.diagnosis.selection: where forward selection stops."""
from fuelid.ident import diagnosis as dg
from fuelid.ident import effects as fx
from fuelid.ident.diagnosis import recommendation, selection
from fuelid.ident.modelrun import run_model
from tests.ident import hidden


def test_forward_selection_stops_once_nothing_a_later_round_could_accept_can_be_recommended():
    """On one trip a bus signal fuelid knows no physics for is never added (recommendation.ONE_TRIP_ONLY). Once the
    search is built on one, whatever a later round finds is found given it and not recommended: it stops — unless a
    candidate that may be added was found in an earlier round given no such signal
    (recommendation.found_given_added)."""
    ds = hidden.make("dpf_regeneration", seed=1)
    run = dg.run_gradients(run_model(hidden.fitted(ds), ds))  # one trip
    generic = {e.id: e for e in fx.generic_effects(ds)}

    def candidate(effect: str, **records) -> dg.Candidate:
        return dg.Candidate(effect, effect, "…", [], [], "…", "…", definition=generic.get(effect), **records)

    signal = candidate("scales:ET1.EngOilTemp1", refit={"verified": True}, verification={"rmse_drop_percent": 5.0})
    twin = candidate("level:ET1.EngOilTemp1", conditional={"found_given": [["engine_map"]]})
    overrun = candidate("overrun_cutoff", conditional={"found_given": [["engine_map"]]})

    def stops(named, pool) -> bool:
        return selection._nothing_left_to_recommend(named, pool, ds, run)

    assert recommendation.why_never_added(signal, ds) == recommendation.ONE_TRIP_ONLY
    assert not stops([], [overrun, twin])  # not built on such a signal: the next round may find one to add
    assert not stops([signal], [overrun, twin])  # found given the map term alone: may be recommended after it
    assert stops([signal], [twin])  # on one trip a generic signal is never added, whatever round found it
    overrun.conditional["found_given"] = [["engine_map", signal.effect]]
    assert stops([signal], [overrun, twin])  # found given the signal only
    signal.refit["verified"] = False  # its refit not verified: the search was not built on it
    assert not stops([signal], [overrun, twin])
    said = selection.why_left_at_the_stop(signal.effect)  # what one found beside it says: not "explained by" it
    assert said.startswith(" — found beside scales:ET1.EngOilTemp1, but forward selection accepted that one and "
                           "stopped")
