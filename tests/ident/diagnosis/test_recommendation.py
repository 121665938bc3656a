"""ident.diagnosis.recommendation: what is confirmed and recommended, and the sentence saying why not."""
from fuelid.ident import diagnosis as dg
from fuelid.ident.diagnosis import recommendation
from tests.ident import hidden


def test_an_effect_named_by_its_tests_alone_is_not_recommended_and_says_why():
    """With no verification budget (`fuelid diagnose --verify 0`) the delay is still named by its tests, but what
    was never verified is no advice to add it."""
    ds = hidden.make("fuel_delay", seed=1, delay_s=0.4)
    top = dg.diagnose(hidden.fitted(ds), ds, n_verify=0).candidates[0]
    assert top.effect == "fuel_delay" and top.significant and top.verification is None
    assert not top.recommended and "add effect" not in top.explanation
    assert top.explanation.endswith(" — not verified (`fuelid diagnose --verify 0`): not recommended")


def test_a_candidate_fitted_against_its_physics_is_not_confirmed():
    """Fuel 11 % lower while SPN 3700 says 'regenerating' is something, but not a DPF regeneration."""
    ds = hidden.make("dpf_regeneration", seed=1, size=-0.11)
    out = dg.diagnose(hidden.fitted(ds), ds)
    row = next(r for r in out.candidates if r.effect == "dpf_regeneration")
    assert row.test_significant and row.verification["rmse_drop_percent"] > 5
    assert row.verification["direction"] == -1 and not row.significant
    assert "the other way" in row.explanation


def test_an_effect_accepted_given_a_signal_not_added_is_recommended_only_if_verified_given_those_added_before_it():
    """Forward selection accepted the overrun cut-off given two bus signals that are not added; its first round had
    found and verified it given the map term alone. With the regeneration recommended before it, that round did
    not verify it on the model `fuelid identify --effects-from` builds (map term and regeneration): not recommended
    (on the map engine's DPF trip, seed 3000, with the fuel × (1 + 1e-13), it raised another day's error); with the
    map term alone recommended before it, that round did."""
    c = dg.Candidate("overrun_cutoff", "overrun fuel cut-off", "state", [], [], "…", "…")
    signals = ["scales:EEC3.EngDesiredOperatingSpeed", "level:EEC1.EngDemandPercentTorque"]
    c.conditional = {"given": ["engine_map", "dpf_regeneration", *signals],
                     "found_given": [["engine_map"], ["engine_map", "dpf_regeneration", *signals]]}
    assert recommendation.found_given_added(c, {"engine_map", "dpf_regeneration"}) is None
    assert recommendation.given_not_added(c, {"engine_map", "dpf_regeneration"}) == signals
    c.conditional["given"] = ["engine_map", *signals]
    c.conditional["found_given"] = [["engine_map"], ["engine_map", *signals]]
    assert recommendation.found_given_added(c, {"engine_map"}) == ["engine_map"]
    assert recommendation.given_not_added(c, {"engine_map"}) == []
