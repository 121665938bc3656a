"""The README's first command, step by step, on the shipped map-engine trip with a DPF regeneration: convert,
identify (the default keeps the engine model: the engine's map under the paper's dynamics), diagnose it, identify
again with what the diagnosis recommends, compare — and the recommendation checked on a trip it was not chosen on
(the 40-minute validation trip, another day, no regeneration): it must not make the model worse there."""
import json
from pathlib import Path

import pytest

from fuelid.cli import main
from tests.conftest import run_json

LOGS = Path(__file__).resolve().parents[1] / "replay_logs"


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    out = tmp_path_factory.mktemp("front_door")
    for trip in ("map_effect_dpf_regeneration_20min", "map_valid_40min"):
        assert main(["convert", str(LOGS / f"{trip}.log.gz"), "-o", str(out / f"{trip}.mcap"), "--json"]) == 0
    return out


def test_the_front_door_keeps_the_engine_model_names_the_regeneration_and_the_error_falls_on_both_trips(loop, capsys):
    trip, valid = loop / "map_effect_dpf_regeneration_20min.mcap", loop / "map_valid_40min.mcap"
    before, after, diagnosis = loop / "before.json", loop / "after.json", loop / "diagnosis.json"
    identified = run_json(capsys, "identify", trip, "-o", before)
    choice = identified["model_choice"]
    assert choice["chosen"] == "engine" and identified["effects"] == ["engine_map"], choice
    assert choice["held_out"]["improvement_mean"] > 2 * choice["held_out"]["improvement_se"]
    result = run_json(capsys, "diagnose", before, trip)
    diagnosis.write_text(json.dumps(result))
    # the engine's curvature is the model's own: what is missing is the regeneration first; the bus signals that speed
    # and torque determine (EEC2's relative load, EEC1's demand torque) are named but never recommended
    assert result["missing_effects"][0] == "dpf_regeneration", result["verdict"]
    recommended = [c["effect"] for c in result["candidates"] if c.get("recommended")]
    assert recommended[0] == "dpf_regeneration", result["verdict"]
    # the held-out error reported is the base's the first candidate was held to (one base, built as identify builds)
    assert result["candidates"][0]["held_out"]["rmse_without"] == pytest.approx(result["held_out"]["rmse"], rel=0.02)
    regen = result["candidates"][0]["size"]  # the simulator hides +10 % while the filter regenerates
    assert regen["form"] == "state" and 6 < regen["percent"] < 14 and regen["unit"] == "L/h"
    determined = [c for c in result["candidates"] if c.get("reason") == "determined_by_inputs"]
    assert {"level:EEC2.EngPercentLoadAtCurrentSpeed", "level:EEC1.EngDemandPercentTorque"} <= \
        {c["effect"] for c in determined} and not any(c.get("recommended") for c in determined)
    assert result["model"]["engine_map"]["covered_share"] > 0.2
    assert run_json(capsys, "identify", trip, "--effects-from", diagnosis, "-o", after)["effects"] == \
        ["engine_map", *recommended]
    on_trip = run_json(capsys, "compare", before, after, trip)
    on_valid = run_json(capsys, "compare", before, after, valid)
    for compared, fall in ((on_trip, 0.5), (on_valid, 0.5)):
        rmse = [m["rmse"]["simulation"] for m in compared["models"]]
        assert rmse[1] < (1 - fall) * rmse[0], rmse
    assert on_valid["models"][1]["rmse"]["simulation"] < 1.5  # L/h (0.80 measured)
    if len(recommended) > 1:  # what is recommended after the regeneration must not stand in for it on this trip only
        first = loop / "first.json"
        run_json(capsys, "identify", trip, "--fuel-lag", str(identified["training"]["fuel_lag_s"]),
                 "--effect", "dpf_regeneration", "-o", first)
        rmse = [m["rmse"]["simulation"] for m in run_json(capsys, "compare", first, after, valid)["models"]]
        assert rmse[1] < 1.01 * rmse[0], rmse
