"""fuelid online end to end on a converted simulated trip: from scratch, from a prior, Kalman, bad input."""
import contextlib
import io
import json

import pytest

from fuelid.cli import main
from fuelid.ident.modelfile import load_model


@pytest.fixture(scope="module")
def trip(tmp_path_factory):
    """A simulated 10-minute urban trip of the diesel truck, converted to MCAP."""
    d = tmp_path_factory.mktemp("online")
    log = d / "trip.log.gz"
    assert main(["simulate", "--truth", "diesel_p320", "--cycle", "urban", "--duration", "600", "--seed", "3",
                 "-o", str(log)]) == 0
    assert main(["convert", str(log), "-o", str(d / "trip.mcap")]) == 0
    return d / "trip.mcap"


def _online(capsys, *args) -> dict:
    capsys.readouterr()
    assert main(["online", *map(str, args), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.fixture(scope="module")
def scratch(trip, tmp_path_factory):
    """The model identified from scratch (paper orders) and the --json result."""
    out = tmp_path_factory.mktemp("scratch") / "model.json"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["online", str(trip), "-o", str(out), "--json"]) == 0
    return out, json.loads(buf.getvalue())


def test_from_scratch(scratch, trip):
    out, r = scratch
    assert r["model"] == str(out) and r["method"] == "rpem" and r["restarts"] == 0
    assert r["structure"]["nb"] == [4, 5] and r["samples"] > 1900 and r["updates"] > 0.95 * r["samples"]
    assert r["update_rate_samples_per_s"] > 5000 and r["final_lambda"] < 1.0  # λ still growing towards 1
    # 600 s: all in the output-error phase (C = D = 1), so the prediction is the simulation
    assert r["fit_percent"]["simulation"] > 75.0 and r["fit_percent"]["prediction"] >= r["fit_percent"]["simulation"]
    assert set(r["running_fit_percent"]) == {"prediction", "simulation"}
    model = load_model(out)  # loads back, with the data's names and units and the run's report
    assert model.structure.n_params == 41 and model.input_units == ("rpm", "Nm") and model.output_unit == "L/h"
    assert model.info["updates"] == r["updates"] and model.validation["fit_percent"] == r["fit_percent"]


def test_from_prior_rpem_and_kalman(scratch, trip, tmp_path, capsys):
    prior, first = scratch
    r = _online(capsys, trip, "--prior", prior, "--forgetting", "0.9995", "--adapt", "all", "-o", tmp_path / "rpem.json")
    assert r["final_lambda"] == 0.9995
    assert r["fit_percent"]["simulation"] > first["fit_percent"]["simulation"] - 2.0  # a second pass keeps it
    k = _online(capsys, trip, "--prior", prior, "--method", "kalman", "--adapt", "all", "-o", tmp_path / "kalman.json")
    assert k["method"] == "kalman" and load_model(tmp_path / "kalman.json").info["method"].startswith("Kalman")
    assert k["fit_percent"]["simulation"] > first["fit_percent"]["simulation"] - 2.0
    assert r["fuel_change_percent"] is None and k["fuel_change_percent"] is None  # every parameter adapts


def test_from_prior_tracks_the_fuel_gain(trip, tmp_path, capsys):
    prior = tmp_path / "offline.json"  # the offline PEM model of this truck, then the same data again:
    assert main(["identify", str(trip), "-o", str(prior)]) == 0  # no drift, and the 95 % interval says so
    fit = load_model(prior).validation["fit_percent"]["simulation"]
    for method in ("rpem", "kalman"):
        g = _online(capsys, trip, "--prior", prior, "--method", method, "--forgetting", "0.9995",
                    "-o", tmp_path / f"{method}.json")
        change = g["fuel_change_percent"]
        assert g["adapt"] == "gain" and abs(change["change"]) <= max(change["ci95"], 1.0) and change["ci95"] < 5.0
        assert load_model(tmp_path / f"{method}.json").info["method"].startswith("fuel-gain tracking")
        assert g["fit_percent"]["simulation"] > fit - 1.0


def test_text_output(scratch, trip, tmp_path, capsys):
    capsys.readouterr()
    assert main(["online", str(trip), "--prior", str(scratch[0]), "-o", str(tmp_path / "m.json")]) == 0
    out = capsys.readouterr().out
    assert "final model fit: simulation" in out and "samples/s" in out and "fuel change since the prior" in out


@pytest.mark.parametrize("args, says", [
    (["missing.mcap"], "missing.mcap"),
    (["@trip", "--forgetting", "1.5"], "--forgetting must be in (0, 1]"),
    (["@trip", "--method", "kalman"], "needs --prior"),
    (["@trip", "--orders", "nb=2,2;nf=1,1;nk=1,0", "--prior", "@prior"], "differ from the prior"),
    (["@trip", "--prior", "@trip"], "not valid JSON"),
])
def test_bad_input_is_one_line(args, says, trip, scratch, tmp_path, capsys):
    args = [str(trip) if a == "@trip" else str(scratch[0]) if a == "@prior" else a for a in args]
    capsys.readouterr()
    assert main(["online", *args, "-o", str(tmp_path / "m.json")]) != 0
    err = capsys.readouterr().err
    assert says in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "m.json").exists()


def test_an_engine_model_runs_online_over_recorded_files_its_map_fixed(trip, tmp_path, capsys):
    """The engine model (its map an input like speed and torque, computed from them) as a prior: RPEM tracking the
    fuel gain and Kalman adapting every parameter run over the trip and keep its fit; the model written keeps the
    map."""
    prior = tmp_path / "engine.json"
    assert main(["identify", str(trip), "--model", "engine", "-o", str(prior)]) == 0
    fit = load_model(prior).validation["fit_percent"]["simulation"]
    for method, adapt in (("rpem", "gain"), ("kalman", "all")):
        r = _online(capsys, trip, "--prior", prior, "--method", method, "--adapt", adapt, "-o", tmp_path / "o.json")
        assert r["fit_percent"]["simulation"] > fit - 2.0, (method, r["fit_percent"], fit)
        online = load_model(tmp_path / "o.json")
        assert online.effects == ("engine_map",)
        assert online.info["effect_parameters"]["engine_map"] == load_model(prior).info["effect_parameters"]["engine_map"]
