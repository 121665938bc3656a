"""Issue 7's acceptance tests on the truck simulator: a 20-minute diesel trip with one hidden physical effect (three,
a winter lowland, a summer mountain and a spring hill one, identified together, for ambient air:
sim.catalog.EFFECT_TRIPS), through the bus and fuelid's decoder, identified with the paper's orders and diagnosed.

For each effect the simulator can hide (two seeds each here; `python benchmarks/bench_diagnose.py
--acceptance` runs three more per effect, 20 trips and 10 pairs of trips with nothing hidden) the top significant
candidate names it (or its signal's SPN), and adding it lowers the held-out RMS simulation error (the linearised
refit scored on 1-minute blocks left out of the fit, ident.diagnosis.verify) by ≥ 25 % or to the noise floor —
the RMS of the simulator's noise H e (truth.npz `noise`), +5 % — and the cycle fuel error falls. With nothing
hidden no candidate is significant. Simulated data and diagnoses are cached per session (tests.ident.hidden).
"""
import functools
import warnings

import numpy as np
import pytest

from fuelid.ident import diagnosis as dg
from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.entries import ENTRIES
from fuelid.ident.diagnosis.verification import MIN_IDENTIFIABILITY, identifiability
from fuelid.ident.fueldelay import DELAY_REFERENCE
from fuelid.ident.identify import FitMemo, estimate_fuel_delay, identify_model
from fuelid.ident.modelrun import run_model
from fuelid.ident.validation import evaluate
from tests.ident import hidden

FLOOR_TOLERANCE = 1.05


@functools.cache
def diagnosed(effect, seed, routes_of=None, truth="diesel_p320"):
    ds, arrays, summary = hidden.simulated(effect, seed, routes_of=routes_of, truth=truth)
    return dg.diagnose(hidden.identify(ds), ds).to_json(), arrays, summary  # as `fuelid diagnose --json` prints it


def names(row, effect, summary) -> bool:
    """The candidate names the hidden effect: its id, or one of the SPNs the simulator shows it on."""
    spns = {p for e in summary["effects"] for p in e["spns"]}
    return row["effect"] == effect or bool(spns & set(row["spns"]) - {190, 513})  # not just speed / torque


@pytest.mark.parametrize("effect, seed", [
    (effect, seed) for effect in ("dpf_regeneration", "inertia", "engine_fan", "cold_engine", "gear_shift",
                                  "power_nonlinearity", "ambient", "fuel_delay", "overrun_cutoff")
    for seed in (2004, 3004)
])
def test_hidden_effect_is_named_and_adding_it_lowers_the_error(effect, seed):
    out, truth, summary = diagnosed(effect, seed)
    top = out["candidates"][0]
    assert top["significant"], out["verdict"]
    # the paper engine is linear: no map term of its own, but a hidden speed × torque product is the first term of
    # a map, named as the engine's term — by the product alone, or as the full map when the model identify builds
    # with the map simulates the data better by the relevance bar (verdict._map_beats_product; seed 2004: 1.65
    # against 1.82 L/h, and on another day's trip 1.75 against 1.98)
    if effect == "power_nonlinearity" and top["effect"] == "engine_map":
        built = top["verification"]["built"]
        assert built["rmse_with_map"] < 0.98 * built["rmse_with_product"], built
    else:
        assert names(top, effect, summary), top["effect"]
    assert out["engine_map"] == (top["effect"] if effect == "power_nonlinearity" else None), out["verdict"]
    v = top["verification"]
    floor = float(np.sqrt(np.mean(truth["noise"] ** 2)))
    assert v["rmse_drop_percent"] >= 25 or v["rmse_with"] <= FLOOR_TOLERANCE * floor, (v, floor)
    assert abs(v["cycle_fuel_error_percent_with"]["rms"]) <= abs(v["cycle_fuel_error_percent_without"]["rms"]) + 0.1


@pytest.mark.parametrize("seed, routes_of", [(11, None), (12, None), (13, None), (11, "ambient")])
def test_with_nothing_hidden_no_candidate_is_significant(seed, routes_of):
    """One trip, or the ambient effect's three trips in different weather identified together."""
    out, _, _ = diagnosed(None, seed, routes_of)
    assert not any(r["significant"] for r in out["candidates"]), out["verdict"]
    assert out["verdict"].startswith("No significant candidate")


def test_on_the_map_engine_the_curvature_is_the_engines_map_term_not_a_missing_effect():
    """The VECTO 325 kW map engine with nothing hidden: the paper's LTI model is a plane through a curved map. The
    diagnosis names the curvature as the engine's own map term (tested first), with by far the largest held-out
    drop of all it names, and not as a missing effect: the speed × torque product is explained by the map term
    (README, On a real engine map)."""
    out, _, _ = diagnosed(None, 11, truth="map")
    term = out["candidates"][0]
    assert out["engine_map"] == "engine_map" and term["role"] == "engine map" and term["recommended"], out["verdict"]
    assert term["rmse_drop_percent"] >= 50.0, term
    named = [c for c in out["candidates"] if c["significant"]]
    assert term["rmse_drop_percent"] == max(c["rmse_drop_percent"] or 0.0 for c in named), out["verdict"]
    assert "power_nonlinearity" not in out["missing_effects"]
    product = next(c for c in out["candidates"] if c["effect"] == "power_nonlinearity")
    assert product["explained_by"].startswith("engine_map"), product["explanation"]


def test_without_verification_the_tests_alone_name_and_nothing_is_recommended():
    """n_verify = 0 (`fuelid report --verify 0`): on the map engine the forward selection goes on from the map
    term with the candidates its tests alone accept, unverified, so none is recommended."""
    ds, _, _ = hidden.simulated(None, 11, truth="map")
    out = dg.diagnose(hidden.identify(ds), ds, n_verify=0)
    assert out.engine_map is not None and out.missing_effects, out.verdict
    assert not [c.effect for c in out.candidates if c.recommended]
    assert all(c.verification is None for c in out.missing_effects)


def test_on_the_map_engine_a_hidden_dpf_regeneration_is_found_on_top_of_the_map_term():
    """A DPF regeneration hidden on the map engine: the map term first (the engine's), then the regeneration as
    the first missing effect, found on the model with the map term and lowering its held-out error a lot."""
    out, _, _ = diagnosed("dpf_regeneration", 3000, truth="map")
    assert out["engine_map"] == "engine_map", out["verdict"]
    assert out["missing_effects"][:1] == ["dpf_regeneration"], out["verdict"]
    dpf = next(c for c in out["candidates"] if c["effect"] == "dpf_regeneration")
    assert dpf["recommended"] and dpf["conditional"]["given"] == ["engine_map"]
    assert dpf["conditional"]["rmse_drop_percent"] >= 25.0, dpf["conditional"]


def test_on_the_map_engine_building_ahead_in_a_worker_gives_the_same_diagnosis():
    """`fuelid diagnose --workers 1` (ident.diagnosis.builds): the models `fuelid identify` would build — with the
    map term, with it and the regeneration, without either — on which what is recommended is checked, built ahead in
    a worker process: the same diagnosis, to the bit, as with each built when needed."""
    ds, _, _ = hidden.simulated("dpf_regeneration", 3000, truth="map")
    out, _, _ = diagnosed("dpf_regeneration", 3000, truth="map")
    assert dg.diagnose(hidden.identify(ds), ds, workers=1).to_json() == out


def built_rmse(ds, val, memo: FitMemo, effects) -> float:
    """RMS simulation error [L/h] on the trip val of the model `fuelid identify` builds on ds with `effects`; memo
    shared by one test's calls, whose sets of effects nest (each fit made once)."""
    return evaluate(identify_model(ds, hidden.PAPER, tuple(effects), memo=memo), val)["rmse"]["simulation"]


def assert_each_lowers_another_days_error(case, recommended: list[str]) -> None:
    """The models `fuelid identify` builds on the map engine's trip(s) of seed 4000 hiding `case`, scored on another
    day's (seed 4050): the one with every effect recommended simulates them better than the one without effects,
    and each effect recommended lowers the error given the others."""
    ds, _, _ = hidden.simulated(case, 4000, truth="map")
    val, _, _ = hidden.simulated(case, 4050, truth="map")
    rmse = functools.partial(built_rmse, ds, val, FitMemo())
    with_all = rmse(recommended)
    assert with_all < evaluate(hidden.identify(ds), val)["rmse"]["simulation"]
    for e in recommended:
        assert rmse([o for o in recommended if o != e]) > with_all, e


def test_on_the_map_engine_no_effect_recommended_raises_another_days_error():
    """A fan and a fuel delay hidden at once on the map engine (seed 4000, one trip): bus signals fuelid has no
    physics for are named on one trip, never recommended, and each effect recommended was verified on a model made
    of effects recommended — the model `fuelid identify --effects-from` builds. Added as it does
    (ident.identify.identify_model), no effect recommended raises the RMS error on another day's trip given the
    others (the fan, accepted given the EEC1 demand-torque scaling and recommended without it, raised it by half).
    The engine's term is its map: a scaling by the oil temperature lowers the held-out error more, but a generic
    bus signal's drop is discounted there as in forward selection (without that, no map term, and the product
    term and the delay were recommended: another day 1.40 L/h against 0.59 with the map term)."""
    case = ("engine_fan", "fuel_delay")
    out, _, _ = diagnosed(case, 4000, truth="map")
    assert out["engine_map"] == "engine_map", out["verdict"]
    recommended = [c["effect"] for c in out["candidates"] if c.get("recommended")]
    generic = [c for c in out["candidates"] if c["significant"] and ":" in c["effect"]]
    assert generic and not any(c.get("recommended") for c in generic), out["verdict"]
    for c in out["candidates"]:
        if c.get("recommended") and c.get("conditional"):  # the round it was accepted in, or an earlier one
            rounds = [c["conditional"]["given"]] + c["conditional"]["found_given"]
            assert any(set(g) <= set(recommended) for g in rounds), (c["effect"], rounds)
    assert_each_lowers_another_days_error(case, recommended)


def test_on_the_map_engine_what_is_recommended_is_verified_on_the_model_identify_builds():
    """Ambient air hidden on the map engine, three trips in different weather (seed 4000): forward selection's
    warm-started refits can stay far from the model `fuelid identify` builds of the same effects, so each effect
    recommended was checked on that model too (refit.built: built with it and the effects recommended before it, it
    simulates these trips no worse than without it). Each lowers the error of the model built with it on another
    day's trips (seed 4050) too, given the others, and together they lower it against the model without them."""
    out, _, _ = diagnosed("ambient", 4000, truth="map")
    recommended = dg.confirmed_effects(out["candidates"])
    assert recommended[:2] == ["engine_map", "ambient"], out["verdict"]
    for c in out["candidates"]:
        if c.get("recommended") and c.get("refit"):
            assert c["refit"]["built"]["rmse_with"] <= c["refit"]["built"]["rmse_without"], c["refit"]
    assert_each_lowers_another_days_error("ambient", recommended)


def test_hidden_inertia_is_found_within_20_percent_of_its_J():
    """The J of the fitted inertia effect (diagnose's refit) against the J the simulator's bus nets out (the
    effect's magnitude in truth.json)."""
    out, _, summary = diagnosed("inertia", 2004)
    row = next(r for r in out["candidates"] if r["effect"] == "inertia")
    J = summary["config"]["effects"]["inertia"]
    assert abs(row["size"]["inertia_kgm2"] - J) <= 0.2 * J, (row["size"], J)


def test_on_the_map_engine_a_fuel_delay_leaves_the_engine_its_map_and_is_checked_on_the_model_built_with_it():
    """A 0.4 s fuel delay hidden on the map engine (seed 4000). The linearised refit prefers the speed × torque product
    to the full map term (it steps once from the model as it is); the models `fuelid identify` builds decide
    instead, and with the full map — whose FIR taps absorb most of the delay — the model simulates the data far
    better, so the engine's term is the map. The delay is named (0.45 s, from the reference model); the model
    identify builds with the map and the delay simulates the data worse than with the map alone (0.05 s off), so it
    is not recommended. Another day's error with what is recommended is a third of what the product term and the delay gave
    (1.38 L/h)."""
    out, _, _ = diagnosed("fuel_delay", 4000, truth="map")
    assert out["engine_map"] == "engine_map", out["verdict"]
    term = out["candidates"][0]
    assert term["verification"]["built"]["rmse_with_map"] < 0.5 * term["verification"]["built"]["rmse_with_product"]
    assert "the model with the full map term simulates these data" in term["explanation"]
    delay = next(c for c in out["candidates"] if c["effect"] == "fuel_delay")
    assert delay["significant"] and abs(delay["size"]["delay_s"] - 0.4) <= 0.1, delay["explanation"]
    b = delay["verification"]["built"]
    assert b["effects"] == ["engine_map"] and b["rmse_with"] > b["rmse_without"], b
    assert not delay["recommended"] and "builds with it, after engine_map" in delay["explanation"], b
    ds, _, _ = hidden.simulated("fuel_delay", 4000, truth="map")
    val, _, _ = hidden.simulated("fuel_delay", 4050, truth="map")
    rmse = functools.partial(built_rmse, ds, val, FitMemo())
    assert rmse(dg.confirmed_effects(out["candidates"])) < 0.55


def test_on_the_map_engine_an_effect_verified_before_a_one_trip_signal_was_accepted_is_recommended():
    """Inertia hidden on the map engine (seed 3000): forward selection accepts bus signals fuelid has no physics for
    first (scalings by EEC3's desired speed and EEC1's demand torque: larger held-out drops on this one trip, never
    added) and the inertia after them. Its first round, on the model with the map term alone, had found and verified
    it already — on a model `fuelid identify --effects-from` builds — so it is recommended, and another day's error
    falls with it. The overrun cut-off on the cold-engine trip, which only a round given such signals would find, is
    not: forward selection stops once built on one (nothing a later round found could be recommended), and its
    explanation names what its last re-test was given."""
    out, _, _ = diagnosed("inertia", 3000, truth="map")
    recommended = dg.confirmed_effects(out["candidates"])
    inertia = next(c for c in out["candidates"] if c["effect"] == "inertia")
    assert inertia["recommended"] and ["engine_map"] in inertia["conditional"]["found_given"], inertia["explanation"]
    assert not set(inertia["conditional"]["given"]) <= set(recommended), inertia["conditional"]["given"]
    assert "found and verified before that given engine_map alone" in inertia["explanation"]
    ds, _, _ = hidden.simulated("inertia", 3000, truth="map")
    val, _, _ = hidden.simulated("inertia", 3050, truth="map")
    rmse = functools.partial(built_rmse, ds, val, FitMemo())
    assert rmse(recommended) < rmse([e for e in recommended if e != "inertia"])

    cold, _, _ = diagnosed("cold_engine", 3000, truth="map")
    overrun = next(c for c in cold["candidates"] if c["effect"] == "overrun_cutoff")
    added = set(dg.confirmed_effects(cold["candidates"]))
    assert not overrun["recommended"], overrun["explanation"]
    assert not any(set(g) <= added for g in overrun["conditional"]["found_given"]), overrun["conditional"]
    assert f"explained by {', '.join(overrun['conditional']['given'])} (not significant" in overrun["explanation"]


def test_on_the_map_engine_the_search_continues_from_the_model_identify_builds_with_the_map_term():
    """A fan and a fuel delay hidden at once on the map engine (seed 3000, one trip). Forward selection's
    warm-started refit with the map term (REFIT_MAX_ITER iterations from the linear model) stops far from the model
    `fuelid identify` builds with it, so the search for hidden effects continues from the built one
    (`refit.searched_on`), and each effect recommended after the map term lowers another day's error given the
    others. (On the warm-started refit the fan was not even named; on the built one it is found or lost to a
    scaling by the oil temperature, which moves with its duty, by a few % of the generic signal's discount — with
    the fuel's last bits: README, the OE start. The benchmark's acceptance set counts that pair over both.)"""
    case = ("engine_fan", "fuel_delay")
    out, _, _ = diagnosed(case, 3000, truth="map")
    term = out["candidates"][0]
    searched = term["refit"]["searched_on"]
    assert term["effect"] == "engine_map" and searched["model"] == "built", searched
    assert searched["rmse_built"] < 0.9 * searched["rmse_warm"], searched
    recommended = dg.confirmed_effects(out["candidates"])
    assert recommended[0] == "engine_map", out["verdict"]
    ds, _, _ = hidden.simulated(case, 3000, truth="map")
    val, _, _ = hidden.simulated(case, 3050, truth="map")
    rmse = functools.partial(built_rmse, ds, val, FitMemo())
    for effect in recommended[1:]:
        assert rmse(recommended) < rmse([e for e in recommended if e != effect]), effect


def test_hidden_fuel_delay_is_found_within_a_tenth_of_a_second():
    """Seed 2's sweep (±1 s, parabola through the best three) with its low-order model refitted at each shift: on
    its own, and in the diagnosis (scored on held-out blocks), which says what to add."""
    ds, _, summary = hidden.simulated("fuel_delay", 2004)
    delay = summary["config"]["effects"]["fuel_delay"]
    sweep = estimate_fuel_delay(ds, ds.u, DELAY_REFERENCE)
    assert abs(sweep["best_s"] - delay) <= 0.1, sweep
    top = diagnosed("fuel_delay", 2004)[0]["candidates"][0]
    assert abs(top["size"]["delay_s"] - delay) <= 0.1, top["size"]
    assert top["spec"] == f"fuel_delay={top['size']['delay_s']:.2f}"


@pytest.mark.parametrize("name", ["systemscyber_truck_drive_normal.log", "systemscyber_truck_drive_tsc1.log"])
def test_fuel_signal_lag_on_real_driving_logs(name, real_log, tmp_path):
    """The lag of LFE1's fuel rate (SPN 183) behind speed and torque on 30 s of real driving: the same sweep on
    a 0.1 s grid finds 0.19–0.20 s (an independent analysis: 0.16–0.18 s, ../shared/real_logs/SOURCES.md)."""
    from fuelid.cli import main
    from fuelid.ident.dataset import build_dataset

    mcap = tmp_path / "real.mcap"
    assert main(["convert", str(real_log(name)), "-o", str(mcap), "--json"]) == 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # no idle stretch in 30 s of driving: the operating point is the default
        ds = build_dataset([mcap], Ts=0.1)
    lag = estimate_fuel_delay(ds, ds.u, DELAY_REFERENCE)["best_s"]
    print(f"{name}: fuel-signal lag {lag:.2f} s")
    assert 0.0 < lag < 3.0


@pytest.mark.parametrize("first, recommended", [("gear_shift", True), ("cold_engine", True),
                                                ("overrun_cutoff", False)])
def test_two_hidden_effects_are_both_named(first, recommended):
    """A DPF regeneration hidden with a weaker effect on the weaker one's route: forward selection re-tests every
    candidate on the model re-identified with the regeneration and names the second too (on the model as it is,
    the second lowers the held-out error by only 1.1–1.2 %, short of the 2 % needed, and was not named before; the
    cold engine, 1.4–1.8 % on the model linearised around the one without the regeneration, was not named given
    it either: a demand-torque scaling was, in its place). After both, bus signals fuelid has no physics for may be
    named too, found on one trip: evidence, never recommended. The overrun cut-off is named but not recommended: the
    model re-identified with it simulates this trip worse (RMS 1.901 → 1.919 L/h; and another day's trip, seed
    3050, no better: 2.016 → 2.017 L/h)."""
    pair = (first, "dpf_regeneration")
    out, _, _ = diagnosed(pair, 3000)
    found = [r for r in out["candidates"] if r["significant"]]
    assert [r["effect"] for r in found][:2] == ["dpf_regeneration", first], out["verdict"]
    assert all(":" in r["effect"] and not r["recommended"] for r in found[2:]), out["verdict"]
    assert found[0]["recommended"] and found[0]["refit"]["verified"]
    assert found[1]["recommended"] == found[1]["refit"]["verified"] == recommended, found[1]["refit"]
    second = found[1]["conditional"]
    assert second["given"] == ["dpf_regeneration"] and second["rmse_drop_percent"] >= 2.0, second
    assert out["verdict"].startswith("Missing effects (")
    assert all((f"add effect {e}" in out["verdict"]) == (e == "dpf_regeneration" or recommended) for e in pair)


def test_ambient_air_is_recommended_only_where_it_carries_over_to_another_trip():
    """Three trips in different weather: ambient air found, and fitted on any two it lowers the third's error
    (leave-one-trip-out). Two of them: each fit has one trip, whose air density hardly varies, so a fit hardly
    determines the effect beside the model's own gains: what it does not determine is left at 0, not extrapolated
    to the other trip (which moved its error by hundreds of % either way), so the check changes neither trip's error
    by more than a trace: it cannot show that the effect carries over. The first trip alone: its scaling of the
    fuel is barely told apart from the model's own gains and is not recommended."""
    out, _, _ = diagnosed("ambient", 2004)
    top = out["candidates"][0]
    assert top["effect"] == "ambient" and top["recommended"], out["verdict"]
    trips = top["verification"]["trips"]
    assert len(trips["rmse_with"]) == 3 and min(trips["rmse_drop_percent"]) > 0 and all(trips["determined"]), trips
    assert top["verification"]["identifiable"]

    ds, _, _ = hidden.simulated("ambient", 2004)
    two = hidden.first_trips(ds, 2)
    out_two = dg.diagnose(hidden.identify(two), two).to_json()
    trips = next(r for r in out_two["candidates"] if r["effect"] == "ambient")["verification"]["trips"]
    assert max(abs(d) for d in trips["rmse_drop_percent"]) < 0.1, trips

    one = hidden.first_trips(ds)
    model = hidden.identify(one)
    alone = dg.diagnose(model, one)
    row = next(r for r in alone.candidates if r.effect == "ambient")
    assert not row.recommended and not row.significant
    share = {}
    for name, d in (("one", one), ("three", ds)):
        m = hidden.identify(d)
        run = dg.run_gradients(run_model(m, d))
        c = dg.rank_candidates(m, d, run, [fx.EFFECTS["ambient"]])[0]
        share[name] = identifiability(run, *ENTRIES["scales_fuel"].varying_column(c, run))
    print(share)
    assert share["one"] < MIN_IDENTIFIABILITY <= share["three"], share
