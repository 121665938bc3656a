"""ident.modelfile: model.json round trip (bit for bit), malformed files, the paper's appendix models."""
import dataclasses
import json
import os
import stat
import threading
import warnings

import numpy as np
import pytest

from fuelid.errors import FuelidError
from fuelid.ident.modelfile import PAPER_MODELS, load_model, load_paper_model, save_model
from fuelid.ident.pem import pem
from fuelid.ident.polymodel import PolyModel, Structure, simulate


@pytest.fixture(scope="module")
def fitted():
    rng = np.random.default_rng(3)
    u = rng.normal(size=(1500, 2)) * [100.0, 10.0] + [600.0, 0.0]
    truth = PolyModel(A=[1], B=[[0, 0.0013, 0.0007], [0.08]], F=[[1, -0.6], [1, -0.3]], C=[1, 0.3], D=[1, -0.8],
                      Ts=0.3, nk=(1, 0), u0=(600.0, 0.0), y0=2.0)
    y = simulate(truth, u) + 0.02 * rng.normal(size=1500)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = pem(u, y, truth.structure, 0.3, u0=(600.0, 0.0), y0=2.0)
    m.input_names, m.input_units = ("engine_speed", "engine_torque"), ("rpm", "Nm")
    m.output_name, m.output_unit = "fuel_flow", "L/h"
    m.effects = ("fuel_shift",)
    m.training = {"samples": 1500, "files": ["a.mcap"]}
    m.validation = {"fit_percent": {"simulation": 91.2}}
    return m


def test_saving_to_a_pipe_writes_into_it_and_leaves_it_a_pipe(fitted, tmp_path):
    """`identify -o /dev/null` (or a named pipe): the atomic rename would replace the device with a file."""
    fifo = tmp_path / "out.fifo"
    os.mkfifo(fifo)
    got = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_bytes()))
    reader.start()
    save_model(fitted, fifo)
    reader.join(timeout=10)
    assert stat.S_ISFIFO(fifo.stat().st_mode) and json.loads(got[0])["format"] == "fuelid-model"
    assert not (tmp_path / "out.fifo.tmp").exists()


def test_figures_that_could_not_be_computed_are_saved_as_null(fitted, tmp_path):
    """Data shorter than a drive cycle have no cycle fuel error (NaN): the file is strict JSON with null there."""
    p = tmp_path / "m.json"
    save_model(dataclasses.replace(fitted, validation={"cycle_fuel_error_percent": {"mean": np.nan, "rms": np.inf}}), p)

    def refuse(constant):
        raise ValueError(f"{constant} in the file")

    assert json.loads(p.read_text(), parse_constant=refuse)["validation"]["cycle_fuel_error_percent"] == \
        {"mean": None, "rms": None}
    assert load_model(p).validation["cycle_fuel_error_percent"]["mean"] is None


def test_round_trip_bit_for_bit(fitted, tmp_path):
    p = tmp_path / "m.json"
    save_model(fitted, p)
    back = load_model(p)
    for a, b in zip([back.A, *back.B, *back.F, back.C, back.D, back.covariance],
                    [fitted.A, *fitted.B, *fitted.F, fitted.C, fitted.D, fitted.covariance]):
        assert a.tobytes() == b.tobytes()
    assert back.structure == fitted.structure and back.Ts == fitted.Ts
    assert (back.u0, back.y0, back.input_names, back.input_units) == (fitted.u0, fitted.y0, fitted.input_names, fitted.input_units)
    assert (back.effects, back.training, back.validation) == (fitted.effects, fitted.training, fitted.validation)
    assert back.info["loss_V"] == fitted.info["loss_V"]
    p2 = tmp_path / "m2.json"
    save_model(back, p2)
    assert p2.read_bytes() == p.read_bytes()
    doc = json.loads(p.read_text())
    assert doc["format"] == "fuelid-model" and doc["version"] == 3
    assert doc["inputs"][0]["nk"] == 1 and doc["inputs"][0]["B"][0] == 0
    assert len(doc["parameters"]["names"]) == len(doc["parameters"]["std_errors"]) == fitted.structure.n_params


@pytest.mark.parametrize("content, message", [
    ("{not json", "not valid JSON"),
    ("[1, 2]", "not a JSON object"),
    ('{"format": "other"}', "not a fuelid-model"),
    ('{"format": "fuelid-model", "version": 99}', "unsupported version"),
    ('{"format": "fuelid-model", "version": 3}', "missing field"),
    ('{"format": "fuelid-model", "version": 2, "effects": ["engine_map", "engine_fan"]}', "identify it again"),
    ('{"format": "fuelid-model", "version": 2, "effects": ["engine_map", "torque:X.Y"]}', "identify it again"),
    ('{"format": "fuelid-model", "version": 1, "effects": ["engine_map", "dpf_regeneration"]}', "identify it again"),
])
def test_malformed_models(tmp_path, content, message):
    p = tmp_path / "bad.json"
    p.write_text(content)
    with pytest.raises(FuelidError, match=message) as err:
        load_model(p)
    assert "\n" not in str(err.value)


def test_a_version_1_model_without_an_engine_map_and_effects_is_read(fitted, tmp_path):
    """Version 2 only changed the columns of a fuel scaling on an engine model: every other version-1 file reads."""
    p = tmp_path / "m.json"
    save_model(fitted, p)
    doc = json.loads(p.read_text())
    doc["version"] = 1
    p.write_text(json.dumps(doc))
    assert np.array_equal(load_model(p).theta, fitted.theta)


def test_inconsistent_model(fitted, tmp_path):
    p = tmp_path / "m.json"
    save_model(fitted, p)
    doc = json.loads(p.read_text())
    doc["C"] = [2.0, 0.1]
    p.write_text(json.dumps(doc))
    with pytest.raises(FuelidError, match="monic"):
        load_model(p)
    with pytest.raises(FuelidError, match="cannot read"):
        load_model(tmp_path / "missing.json")


def test_paper_models():
    if not PAPER_MODELS.exists():
        pytest.skip(f"{PAPER_MODELS} not available")
    d = load_paper_model("diesel_scania_p320")
    assert d.structure == Structure.bj((4, 5), (5, 5), (3, 0), 11, 11) and d.Ts == 0.3
    assert d.B[0][3] == 0.001171 and d.F[1][-1] == 0.03823 and d.output_unit == "L/h"
    g = load_paper_model("gas_scania_p340", PAPER_MODELS)
    assert g.structure.nc == 10 and g.output_unit == "kg/h"
    with pytest.raises(FuelidError, match="no 'nope'"):
        load_paper_model("nope")
    with pytest.raises(FuelidError, match="cannot read"):
        load_paper_model("diesel_scania_p320", "/nonexistent/paper_models.json")
