"""ident.diagnosis.selection: where forward selection stops, and which rivals it checks the data tell apart."""
from fuelid.ident import diagnosis as dg
from fuelid.ident import effects as fx
from fuelid.ident.diagnosis import recommendation, selection
from fuelid.ident.modelrun import run_model
from tests.ident import hidden


def candidate(effect: str, definitions: dict, **records) -> dg.Candidate:
    """A candidate with its effect's definition (None when `definitions` has none) and the given records."""
    return dg.Candidate(effect, effect, "…", [], [], "…", "…", definition=definitions.get(effect), **records)


def test_forward_selection_stops_once_nothing_a_later_round_could_accept_can_be_recommended():
    """On one trip a bus signal fuelid knows no physics for is never added (recommendation.ONE_TRIP_ONLY). Once the
    search is built on one, whatever a later round finds is found given it and not recommended: it stops — unless a
    candidate that may be added was found in an earlier round given no such signal
    (recommendation.found_given_added)."""
    ds = hidden.make("dpf_regeneration", seed=1)
    run = dg.run_gradients(run_model(hidden.fitted(ds), ds))  # one trip
    generic = {e.id: e for e in fx.generic_effects(ds)}
    signal = candidate("scales:ET1.EngOilTemp1", generic, refit={"verified": True},
                       verification={"rmse_drop_percent": 5.0})
    twin = candidate("level:ET1.EngOilTemp1", generic, conditional={"found_given": [["engine_map"]]})
    overrun = candidate("overrun_cutoff", generic, conditional={"found_given": [["engine_map"]]})

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


def test_two_signals_speed_and_torque_determine_are_not_told_apart():
    """Forms of a signal engine speed and torque determine (here EEC1's demand torque, a curved function of them) are
    never added, on any data: forward selection does not refit one to see whether the data tell it from the other
    (`_indistinguishable`, the "— or …" of the explanation). A rival that might be added is still checked beside
    such a signal, every rival of any other signal is, and a rival explaining less than half as much never is."""
    ds = hidden.make(None, n=4000)
    speed, torque = ds.u[:, 0], ds.u[:, 1]
    ds.extra["EEC1.EngDemandPercentTorque"] = 100.0 * (torque / 2000.0) ** 2 + 1e-3 * speed
    effects = {e.id: e for e in fx.generic_effects(ds)} | fx.EFFECTS

    def found(effect: str, drop: float) -> dg.Candidate:  # found in a round of forward selection, drop [%]
        return candidate(effect, effects, conditional={"rmse_drop_percent": drop})

    level, scales = found("level:EEC1.EngDemandPercentTorque", 4.0), found("scales:EEC1.EngDemandPercentTorque", 3.0)
    oil, fan, weak = found("scales:ET1.EngOilTemp1", 3.0), found("engine_fan", 2.5), found("friction", 1.5)
    assert recommendation.inputs_determine(level, ds) and not recommendation.inputs_determine(oil, ds)
    assert not recommendation.inputs_determine(fan, ds)  # known physics: not a generic signal
    assert selection._rivals(level, [scales, oil, fan, weak], ds) == [oil, fan]
    assert selection._rivals(oil, [level, scales, fan], ds) == [level, scales, fan]
