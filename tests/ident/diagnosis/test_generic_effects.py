"""Effects fuelid's catalogue lacks (the simulator's generic hidden effects, sim.effects.GENERIC_EFFECTS), found
with the engineer's effect file (docs/effects-example.toml) and added: a 20-minute identification trip and
another day's validation trip through the bus and fuelid's decoder (tests.ident.hidden), the paper's orders.
benchmarks/bench_generic_effects.py runs more seeds, and the built-in generic candidates alone beside them."""
from pathlib import Path

import pytest

from fuelid.ident import diagnosis as dg
from fuelid.ident.effectfile import read_effects_file
from fuelid.ident.validation import evaluate
from tests.ident import hidden

EXAMPLE = Path(__file__).resolve().parents[3] / "docs" / "effects-example.toml"


@pytest.mark.parametrize("effect, file_id, signal, spn", [
    ("hot_intake_air", "hot_intake_air", "AMB.EngAirInletTemp", 172),
    ("auxiliary_load", "parasitic_torque", "EEC3.EstEngParasiticLossesPercentTorque", 2978),
])
def test_an_effect_the_engineer_describes_is_found_sized_and_helps_on_another_day(effect, file_id, signal, spn):
    defined = read_effects_file(EXAMPLE)
    ds, truth, summary = hidden.simulated(effect, 5001)
    model = hidden.identify(ds)
    top = dg.diagnose(model, ds, effects=defined).candidates[0]
    assert top.significant and top.effect == file_id and signal in top.signals and spn in top.spns
    assert f"add effect {file_id} (defined in {EXAMPLE})" in top.explanation
    magnitude = summary["config"]["effects"][effect]
    if effect == "hot_intake_air":  # relative fuel change per K above 30 °C
        assert top.size["relative_change_per_unit"] == pytest.approx(magnitude / 10.0, rel=0.35)
    else:  # torque per % of parasitic losses: the reference torque's 1 %, in Nm (measured 11.3 against 16: the
        # linearised refit's one step leaves part of it in the model's own offset and gains)
        ref = summary["engine"]["reference_torque_nm"]
        assert top.size["torque_scale"] == pytest.approx(ref / 100.0, rel=0.4)
    val, _, _ = hidden.simulated(effect, 5051)
    after = hidden.identify(ds, effects=[top.spec], defined=defined)
    before_rmse, after_rmse = (evaluate(m, val)["rmse"]["simulation"] for m in (model, after))
    assert after_rmse < 0.9 * before_rmse


@pytest.mark.parametrize("effect, file_id, signal", [
    ("hot_intake_air", "hot_intake_air", "AMB.EngAirInletTemp"),
    ("auxiliary_load", "parasitic_torque", "EEC3.EstEngParasiticLossesPercentTorque"),
])
def test_without_the_file_the_generic_forms_find_it_and_what_they_recommend_helps_on_another_day(effect, file_id,
                                                                                                 signal):
    """The built-in and generic candidates alone (issue 16, item 1: every bus signal in every form — the intake
    air as a factor scaling the fuel, the parasitic losses as a torque through the torque path): the effect's
    signal is named, and adding what is named lowers the validation trip's RMS error by at least 70 % of what the
    true effect (the example file's) does — never raises it (item 3). Found on one trip, a bus signal fuelid
    knows no physics for is named but not recommended (`--effects-from` does not add it)."""
    ds, _, _ = hidden.simulated(effect, 5001)
    val, _, _ = hidden.simulated(effect, 5051)
    model = hidden.identify(ds)
    candidates = dg.diagnose(model, ds).candidates
    named = [c for c in candidates if c.significant]
    assert any(signal in c.signals for c in named), [c.effect for c in named]
    assert not [c.effect for c in candidates if c.recommended and ":" in c.effect]
    base = evaluate(model, val)["rmse"]["simulation"]
    named = evaluate(hidden.identify(ds, effects=[c.spec for c in named]), val)["rmse"]["simulation"]
    oracle = evaluate(hidden.identify(ds, effects=[file_id], defined=read_effects_file(EXAMPLE)),
                      val)["rmse"]["simulation"]
    assert named < base and base - named >= 0.7 * (base - oracle), (base, named, oracle)


@pytest.mark.parametrize("effect, oracle_id", [
    ("hot_intake_air", "scales:AMB.EngAirInletTemp"),
    ("auxiliary_load", "torque:EEC3.EstEngParasiticLossesPercentTorque"),
])
def test_on_three_days_the_signal_is_recommended_and_helps_on_other_days_as_the_true_effect(effect, oracle_id):
    """What the one-trip advice asks: the route driven on three days (seed 5001 and the next two days' trips,
    diagnosed together). The effect's signal carries over leave-one-trip-out, so a form of it is recommended, the
    only recommendation, and on three other days (seed 5051's) the model `--effects-from` builds with it lowers the
    RMS error by at least 70 % of what the true effect (its signal in the form its physics takes) does: issue 16's
    oracle."""
    ds, _, _ = hidden.simulated(effect, 5001, days=3)
    val, _, _ = hidden.simulated(effect, 5051, days=3)
    model = hidden.identify(ds)
    candidates = dg.diagnose(model, ds).candidates
    recommended = [c for c in candidates if c.recommended]
    signal = oracle_id.split(":")[1]
    assert [list(c.signals) for c in recommended] == [[signal]], [(c.effect, c.explanation) for c in candidates
                                                             if c.significant]
    base = evaluate(model, val)["rmse"]["simulation"]
    added = evaluate(hidden.identify(ds, effects=[c.spec for c in recommended]), val)["rmse"]["simulation"]
    oracle = evaluate(hidden.identify(ds, effects=[oracle_id]), val)["rmse"]["simulation"]
    assert added < base and base - added >= 0.7 * (base - oracle), (base, added, oracle)


def test_a_bus_signal_speed_and_torque_determine_is_named_not_recommended():
    """Nothing hidden on the VECTO map engine (seed 100's trip): a scaling of the fuel by EEC3's desired operating
    speed — the engine speed but in neutral — stands in for what the engine's term leaves of its map, and is
    named. Speed and torque determine that signal, so whatever it explains is the engine's own fuelling: it is
    not recommended, on this trip or on any number of them, and the explanation says why (not "diagnose other
    days' files"); only the engine's term is recommended."""
    ds, _, _ = hidden.simulated(None, 100, truth="map")
    candidates = {c.effect: c for c in dg.diagnose(hidden.identify(ds), ds).candidates}
    desired = candidates["scales:EEC3.EngDesiredOperatingSpeed"]
    assert desired.significant and not desired.recommended
    assert "engine speed and torque determine EEC3.EngDesiredOperatingSpeed (a static map of them leaves" \
           in desired.explanation and "other days' files" not in desired.explanation
    assert [e for e, c in candidates.items() if c.recommended] == ["engine_map"]


def test_with_nothing_hidden_the_generic_forms_name_nothing():
    """A trip on the hot-intake-air route with nothing hidden: no bus signal in any form is named."""
    ds, _, _ = hidden.simulated(None, 500, routes_of="hot_intake_air")
    out = dg.diagnose(hidden.identify(ds), ds)
    assert not [c.effect for c in out.candidates if c.significant], out.verdict


@pytest.mark.parametrize("effect, seed, signals", [
    ("hot_intake_air", 5000, {"ET1.EngOilTemp1", "AMB.EngAirInletTemp"}),
    ("auxiliary_load", 5001, {"EEC3.EstEngParasiticLossesPercentTorque"}),
])
def test_signals_these_data_cannot_tell_apart_are_named_together(effect, seed, signals):
    """In the simulator the oil temperature follows the same smoothed load as the intake air: on seed 5000's trip
    each explains the other away (neither significant and relevant given the other), so the diagnosis names one
    and lists the other as an alternative it cannot tell from it, and says so — the true signal is among them.
    The parasitic losses have no such twin: what cannot be told apart there are forms of the same signal."""
    ds, _, _ = hidden.simulated(effect, seed)
    candidates = {c.effect: c for c in dg.diagnose(hidden.identify(ds), ds).candidates}
    named = [c for c in candidates.values() if c.significant]
    assert len(named) == 1 and named[0].alternatives, [(c.effect, c.alternatives) for c in named]
    told_apart = [named[0], *(candidates[a] for a in named[0].alternatives)]
    assert {s for c in told_apart for s in c.signals} == signals, [c.effect for c in told_apart]
    assert "cannot tell them apart" in named[0].explanation


def test_a_bus_signal_that_does_not_carry_over_once_re_identified_is_named_not_recommended():
    """On the VECTO map engine's three trips in different weather (seed 3000, ambient air hidden), bus signals that
    lead the engine's transient fuelling (EEC1's demand torque, EEC3's desired speed) scale the fuel significantly on
    these data, and one of them lowers their error once re-identified with it, yet nothing that carries over: fitted
    on the other trips, as `--effects-from` adds it (its own dynamics, the model re-identified), it does not lower
    the trips left out's error by the 2 % every candidate's held-out blocks must gain (diagnosis.carryover; the level
    of such a signal passed a check that asked only not to rise and raised another day's error, 0.492 → 0.495 L/h).
    Each is named, none recommended. Which signal gets that far depends on the model's last bits (README: the OE
    start), so every one that does is checked."""
    ds, _, _ = hidden.simulated("ambient", 3000, truth="map")
    out = dg.diagnose(hidden.identify(ds), ds)
    generic = [c for c in out.candidates if c.significant and ":" in c.effect]  # FORM:SIGNAL, no known physics
    assert generic and not any(c.recommended for c in generic)
    left_out = [c for c in generic if "trips" in (c.refit or {})]  # re-identified, then trips left out
    assert left_out, [c.explanation for c in generic]
    for c in left_out:
        carry = c.refit["trips"]
        assert not carry["carries_over"]
        ways = [w for w in ("own_dynamics", "re_identified") if w in carry]  # the cheap way first, to the first miss
        assert [carry[w]["lowered"] for w in ways] == [True] * (len(ways) - 1) + [False]
        assert carry[ways[-1]]["rmse_with"] > 0.98 * carry[ways[-1]]["rmse_without"]
        assert "the trips left out by 2 % (" in c.explanation
        assert "leave-one-trip-out by PEM): not recommended" in c.explanation
    assert {"engine_map", "ambient"} <= {c.effect for c in out.candidates if c.recommended}
