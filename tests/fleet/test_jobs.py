"""fleet.jobs: one truck's identification job, and fleet refits on a Dask LocalCluster, on simulated trips."""
import json
from pathlib import Path

import numpy as np
import pytest

from fuelid.fleet.effectlist import ENGINE_PROPERTIES
from fuelid.fleet.jobs import JobError, JobRunner, cycles_sample, files_sample, identify_truck, readable
from fuelid.ident.dataset import Dataset
from fuelid.cli import main
from fuelid.ident.modelfile import load_model
from fuelid.logger.mcap_log import McapLogWriter
from tests.fleet.test_drift import fuel_measured_near

SMALL = "nb=2,2;nf=1,1;nk=3,0;nc=1;nd=1"  # a cheap structure for the cluster test: its subject is the plumbing


def simulated_mcap(folder, seed: int, duration_s: float = 900.0):
    """A diesel truck's trip of duration_s [s] from the simulator, converted to MCAP as `fuelid convert` does."""
    from fuelid.sim.trip import TripConfig, simulate, write

    log = folder / f"truck{seed}.log.gz"
    write(simulate(TripConfig(duration_s=duration_s, seed=seed)), log)
    mcap = folder / f"truck{seed}.mcap"
    assert main(["convert", str(log), "-o", str(mcap), "--json"]) == 0
    return mcap


@pytest.fixture(scope="module")
def trip(tmp_path_factory):
    return simulated_mcap(tmp_path_factory.mktemp("trips"), seed=5)


@pytest.fixture(scope="module")
def no_fuel(tmp_path_factory):
    """Engine speed and torque but no fuel signal."""
    path = tmp_path_factory.mktemp("nofuel") / "nofuel.mcap"
    with McapLogWriter(path, metadata={"truck": "nofuel"}, fsync=False) as w:
        w.add_channel("/j1939/EEC1", {"type": "object"})
        for k in range(600):
            w.write("/j1939/EEC1", k * 10**8, {"t": k / 10, "sa": 0, "EngSpeed": 600.0 + k,
                                               "ActualEngPercentTorque": 20.0})
    return path


def test_identify_truck_writes_model_diagnosis_and_returns_metrics(trip, tmp_path):
    res = identify_truck("truck5", [str(trip)], str(tmp_path / "job"))
    assert res["truck"] == "truck5"
    model = load_model(res["model_path"])
    # the simulator's fuel truth is the paper's BJ model: the paper's orders fit it as `fuelid identify` does
    assert model.structure.nb == (4, 5) and model.training["files"] == [str(trip)]
    assert res["metrics"]["fit_percent"]["simulation"] > 85
    assert res["metrics"]["fit_percent"] == model.validation["fit_percent"]
    assert res["metrics"]["unit"] == "L/h"
    # refits on interleaved halves scored on the other half: about the in-sample error, not a multiple
    held_out = res["metrics"]["held_out"]
    assert 0.9 * res["metrics"]["rmse"]["simulation"] < held_out["rmse_simulation"] < \
        2 * res["metrics"]["rmse"]["simulation"]
    assert abs(held_out["cycle_fuel_error_percent"]["mean"]) < 5
    assert res["n_samples"] == pytest.approx(900 / 0.3, rel=0.02)
    assert res["duration_s"] == pytest.approx(900, rel=0.02)
    diagnosis = json.loads(open(res["diagnosis_path"]).read())
    assert diagnosis["data"]["files"] == [str(trip)] and diagnosis["candidates"]
    assert res["top_effect"] in {None} | {c["effect"] for c in diagnosis["candidates"] if c.get("recommended")} - ENGINE_PROPERTIES
    assert set(load_model(res["model_path"]).info["steady_reference"]) <= {"EEC2.EngPercentLoadAtCurrentSpeed"}
    assert "<html" in open(res["report_path"], encoding="utf-8").read(2000).lower()
    assert res["wall_s"] > 0 and set(res["phases_s"]) == {"dataset", "identify", "diagnose", "identify with effects", "write"}
    json.dumps(res, allow_nan=False)  # the server stores it as it is

    # a refit from the previous version starts PEM there and says how the old model does on the same data
    again = identify_truck("truck5", [str(trip)], str(tmp_path / "job2"), previous_model=res["model_path"])
    assert load_model(again["model_path"]).info["initialisation"] == "given model"
    assert again["previous_metrics"]["fit_percent"] == res["metrics"]["fit_percent"]
    assert again["metrics"]["fit_percent"]["simulation"] == pytest.approx(res["metrics"]["fit_percent"]["simulation"],
                                                                          abs=0.5)


def test_unusable_data_raises_job_error_with_one_line(no_fuel, trip, tmp_path):
    with pytest.raises(JobError, match=r"^nofuel: no fuel flow .* in the data: a gas truck's engine may not send "):
        identify_truck("nofuel", [str(no_fuel)], str(tmp_path / "a"))
    with pytest.raises(JobError, match="no such recording"):
        identify_truck("ghost", [str(tmp_path / "missing.mcap")], str(tmp_path / "b"))
    with pytest.raises(JobError, match="no recordings"):
        identify_truck("empty", [], str(tmp_path / "c"))
    with pytest.raises(JobError, match="--orders"):
        identify_truck("truck5", [str(trip)], str(tmp_path / "d"), orders="nb=4;zz=1")
    assert not (tmp_path / "a" / "model.json").exists()


def test_runner_refits_several_trucks_and_reports_a_failing_one(trip, no_fuel, tmp_path):
    second = simulated_mcap(tmp_path, seed=6, duration_s=600.0)
    tasks = [
        {"truck": "truck5", "mcap_paths": [str(trip)], "out_dir": str(tmp_path / "t5"), "orders": SMALL},
        {"truck": "nofuel", "mcap_paths": [str(no_fuel)], "out_dir": str(tmp_path / "nf"), "orders": SMALL},
        {"truck": "truck6", "mcap_paths": [str(second)], "out_dir": str(tmp_path / "t6"), "orders": SMALL},
    ]
    with JobRunner(n_workers=2) as runner:
        assert len(runner.client.scheduler_info()["workers"]) == 2
        results = runner.refit_all(tasks)
        # the server's way: a future per truck
        future = runner.submit("truck6", [str(second)], str(tmp_path / "t6b"), orders=SMALL)
        assert future.result()["metrics"] == results[2]["metrics"]  # same data, same model
    assert [r["truck"] for r in results] == ["truck5", "nofuel", "truck6"]
    assert results[1]["truck"] == "nofuel" and results[1]["error"].startswith(
        "nofuel: no fuel flow (LFE1.EngFuelRate) in the data: ")
    for r in (results[0], results[2]):
        assert "error" not in r and load_model(r["model_path"]).structure.nb == (2, 2)
        assert r["metrics"]["fit_percent"]["simulation"] > 80
    assert results[0]["metrics"] != results[2]["metrics"]


def test_a_refit_stores_the_model_with_the_effects_its_diagnosis_confirmed(tmp_path):
    """A truck regenerating its particulate filter: the job's model includes the effect the diagnosis named (as
    `identify --effects-from` would add it), with the figures of the model without it beside, and the files are
    named as uploaded, not by their blob paths."""
    from fuelid.sim.trip import TripConfig, simulate, write

    log = tmp_path / "dpf.log.gz"
    write(simulate(TripConfig(duration_s=1200, seed=2004, effects=(("dpf_regeneration", 0.1),))), log)
    blob = tmp_path / ("ab" * 32)  # the store names a file by its sha256
    assert main(["convert", str(log), "-o", str(blob), "--json"]) == 0
    res = identify_truck("dpf", [str(blob)], str(tmp_path / "job"), names=["2024-06-01-trip.mcap"])
    model = load_model(res["model_path"])
    assert res["top_effect"] == "dpf_regeneration" and res["effects_added"] == ["dpf_regeneration"]
    assert model.effects == ("dpf_regeneration",) and model.training["files"] == ["2024-06-01-trip.mcap"]
    assert res["metrics"]["rmse"]["simulation"] < 0.85 * res["without_effects"]["rmse"]["simulation"]
    diagnosis = json.loads(open(res["diagnosis_path"]).read())
    assert diagnosis["data"]["files"] == ["2024-06-01-trip.mcap"]
    page = open(res["report_path"]).read()
    assert "2024-06-01-trip.mcap" in page and str(blob) not in page and "with dpf_regeneration" in page


def test_a_linear_model_whose_diagnosis_advises_the_engine_map_is_refitted_as_the_engine_model(trip, tmp_path,
                                                                                                  monkeypatch):
    """The diagnosis of a linear model can advise the engine map: the job then stores the engine model, as
    `identify --effects-from` builds it, instead of failing on a linear model asked for the map."""
    import fuelid.fleet.jobs as jobs

    monkeypatch.setattr(jobs, "effects_to_add", lambda diagnosis: ["engine_map"])
    res = identify_truck("truck5", [str(trip)], str(tmp_path / "job"))
    assert load_model(res["model_path"]).effects[0] == "engine_map"


def test_the_samples_of_a_job_are_whole_cycles_evenly_spaced_and_bounded():
    """A 10-hour truck: the job diagnoses at most DIAGNOSIS_HOURS of it, whole 30-min drive cycles spread over the
    whole time; a short truck is diagnosed on all of its data."""
    ts, n = 0.3, int(10 * 3600 / 0.3)
    t = np.arange(n) * ts
    cycle = (t // 1800).astype(int)
    ds = Dataset(Ts=ts, t=t, u=np.column_stack([t, t]), y=t.copy(), input_names=("n", "T"), input_units=("rpm", "Nm"),
                 output_name="fuel", output_unit="L/h", u0=np.zeros(2), y0=0.0, valid=np.ones(n, bool), cycle=cycle,
                 extra={"ET1.EngCoolantTemp": t.copy()})
    sample = cycles_sample(ds, hours=3.0)
    kept = np.unique(sample.cycle)
    assert len(kept) == 6 and kept[0] == 0 and kept[-1] == 19 and np.all(np.diff(kept) >= 3)
    assert len(sample.t) == 6 * 6000 and np.array_equal(sample.extra["ET1.EngCoolantTemp"], sample.t)
    assert len(sample.segments()) == 6  # the gaps between the cycles split the data
    assert cycles_sample(ds, hours=12.0) is ds


def test_a_job_reads_whole_files_evenly_spaced_in_time_within_its_hours(tmp_path):
    """Ten 2-hour files given in any order: a job reads at most IDENTIFY_HOURS of them by their summaries, spread
    over the whole time with the newest among them; all of them when they fit, or when a file's span is unknown."""
    from mcap.writer import Writer

    paths = []
    for day in [3, 0, 9, 1, 4, 7, 2, 8, 5, 6]:  # not in time order
        paths.append(str(tmp_path / f"day{day}.mcap"))
        with open(paths[-1], "wb") as f:
            w = Writer(f)
            w.start()
            channel = w.register_channel("t", "json", w.register_schema("s", "jsonschema", b"{}"))
            for t_s in (day * 86400.0, day * 86400.0 + 7200.0):
                w.add_message(channel, log_time=int(t_s * 1e9), data=b"{}", publish_time=int(t_s * 1e9))
            w.finish()
    read = [int(Path(paths[i]).stem[3:]) for i in files_sample(paths, hours=6.0)]
    assert sorted(read) == [0, 4, 9]
    assert files_sample(paths, hours=24.0) == list(range(10))
    Path(paths[0]).write_bytes(Path(paths[0]).read_bytes()[:-100])  # cut before its footer: its span is unknown
    assert files_sample(paths, hours=6.0) == list(range(10))


def test_a_truck_with_a_curved_map_gets_the_engine_model_and_its_steady_fuel_is_the_measured_one(tmp_path):
    """A truck with a VECTO engine map: the job builds the model `fuelid identify` builds by default, the engine
    model with the fuel binned one report period earlier (its held-out choices), and the fleet's steady-state fuel at the default reference points (fleet.drift)
    is within 15 % of the fuel measured near each (the mean of the nearest samples) and within 10 % on their mean."""
    from fuelid.fleet.drift import DEFAULT_POINTS, steady_fuel
    from fuelid.ident.dataset import build_dataset
    from fuelid.sim.trip import TripConfig, simulate, write

    log, mcap = tmp_path / "map.log.gz", tmp_path / "map.mcap"
    write(simulate(TripConfig(truth="map", duration_s=1800, seed=1)), log)
    assert main(["convert", str(log), "-o", str(mcap), "--json"]) == 0
    res = identify_truck("map", [str(mcap)], str(tmp_path / "job"))
    model = load_model(res["model_path"])
    assert model.effects[0] == "engine_map" and model.info["model_choice"]["chosen"] == "engine"
    # the simulated ECU reports the mean fuel of its last 100 ms: the job, as `fuelid identify`, bins it so
    assert model.info["fuel_lag_choice"]["lag_s"] == pytest.approx(0.1) == model.fuel_lag_s
    ds = build_dataset([str(mcap)])
    steady = steady_fuel(model, DEFAULT_POINTS)
    measured = [fuel_measured_near(ds, point) for point in DEFAULT_POINTS]
    assert np.allclose(steady.per_point, measured, rtol=0.15), (steady.per_point, measured)
    assert steady.mean == pytest.approx(np.mean(measured), rel=0.10)


def test_a_previous_model_this_fuelid_cannot_read_is_no_previous_model(tmp_path):
    """The previous model only warm-starts a refit: one of an older file format (or damaged) is left out, so the
    truck's refits go on."""
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"format": "fuelid-model", "version": 1, "effects": ["engine_map", "cold_engine"]}))
    assert readable(None) is None and readable(str(old)) is None
