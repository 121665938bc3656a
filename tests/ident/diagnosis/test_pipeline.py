"""ident.diagnosis end to end on small synthetic trips (tests.ident.hidden.make: a known Box-Jenkins truth with
effects hidden in it): what is hidden is recommended, nothing is on clean trips — at the rate the procedure states —
and the statuses, the JSON and `confirmed_effects` say the same."""
import dataclasses
import json
import multiprocessing
import os
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import lfilter
from scipy.stats import binom

from fuelid.ident import diagnosis as dg
from fuelid.ident import effects as fx
from fuelid.ident.diagnosis import MapStatus, Status
from fuelid.ident.effectfile import effect_from_table, read_effects_file
from fuelid.output import json_safe
from fuelid.parallel import jobs
from tests.ident import engine_data, hidden
from tests.ident.diagnosis.trips import joined

EXAMPLE = Path(__file__).resolve().parents[3] / "docs" / "effects-example.toml"


def diagnosed(effect, seed, n=4000, **kwargs):
    ds = hidden.make(effect, n=n, seed=seed)
    return ds, dg.diagnose(hidden.fitted(ds), ds, **kwargs)


def recommended(d) -> list[str]:
    return [c.effect for c in d.candidates if c.recommended]


@pytest.mark.parametrize("effect, expected", [
    ("dpf_regeneration", "dpf_regeneration"),  # scales the fuel while a state is on
    ("cold_engine", "cold_engine"),  # extra fuel while the coolant warms up
    ("unlisted", "state:XX.UnknownState"),  # a generic form on a decoded signal nobody listed
])
def test_a_hidden_effect_is_recommended_first_and_lowers_the_held_out_error(effect, expected):
    _, d = diagnosed(effect, 11)
    top = d.candidates[0]
    assert recommended(d)[:1] == [expected] and top.status is Status.RECOMMENDED and top.alternatives == ()
    assert top.held_out.passes and top.held_out.drop_percent > 10
    out = d.to_json()
    assert dg.confirmed_effects(out["candidates"]) == recommended(d) == out["missing_effects"]
    assert out["candidates"][0]["id"] == expected and f"add {expected} (" in out["verdict"]


def test_progress_is_told_the_base_then_each_model_built_round_by_round():
    steps = []
    _, d = diagnosed("dpf_regeneration", 11, progress=steps.append)
    assert steps[0] == dg.Progress(0) and str(steps[0]) == "the base model"
    assert [s.round for s in steps] == sorted(s.round for s in steps) and steps[1].round == 1
    assert dg.Progress(1, ("dpf_regeneration",)) in steps and recommended(d)[:1] == ["dpf_regeneration"]
    assert str(dg.Progress(2, ("fan", "gear_shift"), placebo=True)) == "round 2: fan + gear_shift (placebo)"


def test_two_hidden_effects_are_both_recommended_by_forward_selection():
    _, d = diagnosed(("dpf_regeneration", "cold_engine"), 12, n=5000)
    assert set(recommended(d)[:2]) == {"dpf_regeneration", "cold_engine"}
    assert [c.round for c in d.candidates[:2]] == [1, 2]


def _state_effect(id_: str, signal: str, sign: int):
    return effect_from_table({"id": id_, "name": id_, "enters": "additive", "unit": "1", "sign": sign,
                              "x": {"state": signal, "on": [1]}, "explanation": "{size:+.2f} {unit} ({signals})"})


def masking_trip(seed: int):
    """A clean synthetic trip with two engineer-defined effects that cancel where they overlap: a PTO pump (+3 L/h
    while CCVS1.PTOGovernorState is 1) and an exhaust brake (-3 L/h while ERC1.RetarderTorqueMode is 1), on together
    in most of their stretches, each alone in a few. Alone, each one's fit is a fraction of its size and wrong
    wherever the other is on."""
    ds = hidden.make(None, n=4000, seed=seed)
    rng = np.random.default_rng(seed + 1)
    pto, brake = np.zeros(ds.t.size), np.zeros(ds.t.size)
    k = 0
    while k < ds.t.size:  # stretches of 30-90 s, 30-120 s apart
        n, gap, r = int(rng.uniform(30, 90) / ds.Ts), int(rng.uniform(30, 120) / ds.Ts), rng.uniform()
        pto[k:k + n], brake[k:k + n] = r < 0.8, r < 0.6 or r >= 0.8
        k += n + gap
    extra = {**ds.extra, "CCVS1.PTOGovernorState": pto, "ERC1.RetarderTorqueMode": brake}
    return dataclasses.replace(ds, y=ds.y + 3.0 * pto - 3.0 * brake, extra=extra)


def test_two_effects_that_mask_each_other_are_both_recommended_and_sized_in_the_model_with_both():
    """Both are found, together (neither passes alone; seeds 5 and 7) or one after the other (the first passes alone
    against its placebo, fitted at a fraction of its size; the second on the model with it); either way each one's
    size is the one in the model with both."""
    effects = [_state_effect("pto_pump", "CCVS1.PTOGovernorState", 1),
               _state_effect("exhaust_brake", "ERC1.RetarderTorqueMode", -1)]
    found = together = 0
    for seed in range(5, 10):
        ds = masking_trip(seed)
        d = dg.diagnose(hidden.fitted(ds), ds, effects=effects, candidates=effects)
        rec = {c.effect: c for c in d.candidates if c.recommended}
        if set(rec) == {"pto_pump", "exhaust_brake"}:
            found += 1
            assert rec["pto_pump"].size.value == pytest.approx(3.0, abs=0.5)
            assert rec["exhaust_brake"].size.value == pytest.approx(-3.0, abs=0.5)
            assert "add pto_pump (" in d.verdict and "add exhaust_brake (" in d.verdict
            if rec["pto_pump"].together_with is not None:
                together += 1
                assert rec["exhaust_brake"].together_with == "pto_pump" and "with exhaust_brake beside it" in d.verdict
                assert {c["id"]: c["together_with"] for c in d.to_json()["candidates"] if c["recommended"]} == \
                    {"pto_pump": "exhaust_brake", "exhaust_brake": "pto_pump"}
    assert found >= 4 and together >= 1  # both on 8 of seeds 5-12, together on 2


def _pump_and_lamp(flipped: float, seed: int = 31):
    """A PTO pump (+3 L/h while CCVS1.PTOGovernorState is 1, a minute in three) and a lamp (ERC1.RetarderTorqueMode)
    that follows the PTO switch but for a share `flipped` of the samples, diagnosed with both as candidates."""
    ds = hidden.make(None, n=4000, seed=seed)
    pto = (np.floor(np.arange(ds.t.size) * ds.Ts / 60.0) % 3 == 0).astype(float)
    lamp = np.where(np.random.default_rng(seed).uniform(size=pto.size) < flipped, 1.0 - pto, pto)
    ds = dataclasses.replace(ds, y=ds.y + 3.0 * pto, extra={**ds.extra, "CCVS1.PTOGovernorState": pto,
                                                          "ERC1.RetarderTorqueMode": lamp})
    effects = [_state_effect("pto_pump", "CCVS1.PTOGovernorState", 1),
               _state_effect("pto_lamp", "ERC1.RetarderTorqueMode", 1)]
    return dg.diagnose(hidden.fitted(ds), ds, effects=effects, candidates=effects)


def test_two_candidates_the_data_cannot_tell_apart_are_named_as_alternatives():
    """The lamp wrong on one sample in a thousand: either model simulates the trip as well, so the one recommended
    names the other as its alternative. Wrong on one in two hundred, the pump's model is better beyond the margin:
    no alternative (both on seeds 31-34)."""
    d = _pump_and_lamp(0.001)
    assert recommended(d) == ["pto_pump"] and d.candidates[0].alternatives == ("pto_lamp",)
    assert "these data do not tell it apart from pto_lamp" in d.verdict
    assert {c["id"]: c["alternatives"] for c in d.to_json()["candidates"]}["pto_pump"] == ["pto_lamp"]
    told_apart = _pump_and_lamp(0.005)
    assert recommended(told_apart) == ["pto_pump"] and told_apart.candidates[0].alternatives == ()
    assert "tell it apart" not in told_apart.verdict


def test_an_effect_the_engineer_defines_is_recommended():
    defined = read_effects_file(EXAMPLE)
    regen = next(e for e in defined if e.id == "regen_from_file")
    ds = hidden.make("dpf_regeneration", n=4000, seed=13)
    d = dg.diagnose(hidden.fitted(ds), ds, effects=defined, candidates=[regen, fx.EFFECTS["cold_engine"]])
    assert recommended(d) == ["regen_from_file"]


def test_with_several_trips_each_trip_is_held_out_in_turn():
    ds = joined(*(hidden.make("dpf_regeneration", n=2500, seed=s) for s in (14, 15)))
    d = dg.diagnose(hidden.fitted(ds), ds)
    assert recommended(d)[:1] == ["dpf_regeneration"] and d.candidates[0].held_out.folds == "trips"


def test_an_effect_in_the_model_is_not_a_candidate_again():
    ds = hidden.make("dpf_regeneration", n=3000, seed=16)
    model = hidden.identify(ds, hidden.STRUCTURE, ["dpf_regeneration"])
    d = dg.diagnose(model, ds, candidates=[fx.EFFECTS["dpf_regeneration"], fx.EFFECTS["cold_engine"]])
    assert {c.effect: c.status for c in d.candidates}["dpf_regeneration"] is Status.ALREADY_IN_MODEL
    assert recommended(d) == []


def test_the_engine_map_is_never_a_candidate_and_is_in_the_model_when_the_model_has_it():
    ds = hidden.make(None, n=3000, seed=17)
    d = dg.diagnose(hidden.fitted(ds), ds)
    assert not {"engine_map", "power_nonlinearity"} & {c.effect for c in d.candidates}
    assert {c.effect: c.status for c in d.candidates}["overrun_cutoff"] is not Status.ALREADY_IN_MODEL
    cut = fx.EFFECTS["overrun_cutoff"]
    with_map = dg.diagnose(hidden.identify(ds, hidden.STRUCTURE, ["engine_map"]), ds, candidates=(cut,))
    assert with_map.engine_map.status is MapStatus.IN_MODEL and with_map.to_json()["engine_map"]["status"] == "in the model"
    # the engine model's map cuts the injection at zero torque: the overrun cut-off is part of it
    (row,) = with_map.to_json()["candidates"]
    assert row["status"] == "already in the model" and "cuts the injection" in row["explanation"]
    # a linear model with the cut-off as its own effect has it, not through a map
    with_cut = dg.diagnose(hidden.identify(ds, hidden.STRUCTURE, ["overrun_cutoff"]), ds, candidates=(cut,))
    (row,) = with_cut.to_json()["candidates"]
    assert row["status"] == "already in the model" and row["explanation"] == "already in the model"


def test_once_the_engine_map_is_advised_the_overrun_cut_off_is_in_it():
    ds = hidden.make(None, n=4000, seed=18)
    n, T = ds.u[:, 0], ds.u[:, 1]  # a curved engine: the map beyond the linear truth, through the map's dynamics
    ds = dataclasses.replace(ds, y=ds.y + lfilter(engine_data.B_MAP, engine_data.F_MAP,
                                                  engine_data.curve(n, np.maximum(T, 0.0))))
    d = dg.diagnose(hidden.fitted(ds), ds, candidates=(fx.EFFECTS["overrun_cutoff"],))
    assert d.engine_map.status is MapStatus.ADVISED
    assert [(c.effect, c.status) for c in d.candidates] == [("overrun_cutoff", Status.ALREADY_IN_MODEL)]


ALPHA = 0.05
CLEAN_TRIPS = 40


def test_on_clean_trips_anything_is_recommended_no_more_often_than_alpha():
    """The stated family-wise error rate: on trips with nothing hidden, the share with any recommendation is at most
    alpha — checked as: the count is not above what Binomial(CLEAN_TRIPS, alpha) reaches with probability 0.99."""
    hits = sum(bool(recommended(diagnosed(None, 1000 + s, n=2500)[1])) for s in range(CLEAN_TRIPS))
    assert hits <= binom.ppf(0.99, CLEAN_TRIPS, ALPHA)


def _children() -> list[int]:
    """Process ids whose parent is this process, but multiprocessing's resource tracker (started with the first
    spawned worker, it lives as long as this process and exits with it)."""
    me, out = os.getpid(), []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
            tracker = b"resource_tracker" in Path(f"/proc/{pid}/cmdline").read_bytes()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == me and not tracker:
            out.append(int(pid))
    return out


@pytest.mark.parametrize("workers", [1, 2])
def test_no_child_process_is_left_after_the_diagnosis_ends_or_is_interrupted(monkeypatch, workers):
    before = set(_children())
    with jobs(workers):
        diagnosed("dpf_regeneration", 18, n=2500)
    assert set(_children()) <= before and not multiprocessing.active_children()

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("fuelid.ident.diagnosis.selection.compare", interrupted)
    with pytest.raises(KeyboardInterrupt), jobs(workers):
        diagnosed("dpf_regeneration", 18, n=2500)
    assert set(_children()) <= before and not multiprocessing.active_children()


@pytest.mark.parametrize("effects", [[], ["engine_map"]])
def test_with_its_builds_side_by_side_in_workers_the_diagnosis_is_the_same(effects):
    """fuelid.parallel: the builds and fold refits in a worker are the fits made here, bit for bit (a pure
    computation moved, not a new one), on a linear and an engine-model base."""
    ds = hidden.make(("dpf_regeneration", "cold_engine"), n=3000, seed=20)
    model = hidden.identify(ds, hidden.STRUCTURE, effects)
    here = json.dumps(json_safe(dg.diagnose(model, ds).to_json()), sort_keys=True)
    with jobs(2):
        side_by_side = json.dumps(json_safe(dg.diagnose(model, ds).to_json()), sort_keys=True)
    assert side_by_side == here and '"recommended": true' in here


def test_the_json_keeps_the_fields_its_readers_use():
    ds, d = diagnosed("dpf_regeneration", 19, n=2500)
    out = d.to_json()
    assert {"model", "data", "compare", "held_out", "where_it_fails", "test", "engine_map", "candidates",
            "verdict"} <= set(out)
    assert out["held_out"]["rmse"] > 0 and np.isfinite(out["held_out"]["cycle_fuel_error_percent"]["rms"])
    for c in out["candidates"]:
        assert {"id", "effect", "spec", "recommended", "significant", "status", "explanation", "testable"} <= set(c)
        assert c["recommended"] is (c["status"] == "recommended")


def test_a_fuel_delay_is_estimated_from_its_screening_and_recommended_with_its_value():
    ds = hidden.make("fuel_delay", n=4000, seed=3, delay_s=0.4)
    d = dg.diagnose(hidden.fitted(ds), ds, candidates=[fx.EFFECTS["fuel_delay"], fx.EFFECTS["cold_engine"]])
    delay = d.candidates[0]
    assert delay.recommended and delay.spec.startswith("fuel_delay=")
    assert float(delay.spec.split("=")[1]) == pytest.approx(0.4, abs=0.15)
    assert dg.confirmed_effects(d.to_json()["candidates"]) == [delay.spec]


def test_an_effect_fitted_against_its_physics_is_named_but_not_recommended():
    ds = hidden.make("dpf_regeneration", n=4000, seed=11, size=-0.11)  # less fuel while it regenerates: not a DPF
    d = dg.diagnose(hidden.fitted(ds), ds)
    regen = next(c for c in d.candidates if c.effect == "dpf_regeneration")
    assert regen.held_out.passes and regen.size.value < 0 and regen.size.percent == pytest.approx(-11, abs=3)
    assert (regen.status, regen.reason) == (Status.NAMED_NOT_RECOMMENDED, dg.Reason.AGAINST_ITS_PHYSICS)
    assert "dpf_regeneration" not in dg.confirmed_effects(d.to_json()["candidates"])
    assert "dpf_regeneration is named by the screening but not recommended: the model built with it lowers" in d.verdict
