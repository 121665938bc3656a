"""fuelid simulate on a VECTO engine set: by short name, by path, and a one-line error for a broken set."""
import json
import shutil
from pathlib import Path

from fuelid.cli import main
from fuelid.sim import catalog
from fuelid.sim.vecto import engine_file


def test_a_map_engine_trip_by_the_shipped_name(tmp_path, capsys):
    out = tmp_path / "map.log.gz"
    assert main(["simulate", "--engine", "vecto_325kW", "--duration", "60", "--seed", "3", "-o", str(out),
                 "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["truth"] == "map" and result["mean_fuel"] > 0
    summary = json.loads((tmp_path / "map.truth.json").read_text())
    assert summary["config"]["engine"] == "vecto_325kW"
    assert summary["engine"]["reference_torque_nm"] == 2134.0 and summary["fuel_truth"]["name"] == "map"


def test_paper_p320_names_the_paper_model_truth(tmp_path, capsys):
    assert main(["simulate", "--truth", "paper_p320", "--duration", "60", "-o", str(tmp_path / "p.log.gz"),
                 "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["truth"] == "diesel_p320"
    assert "engine" not in json.loads((tmp_path / "p.truth.json").read_text())["config"]


def test_a_broken_engine_set_is_one_line_on_stderr(tmp_path, capsys):
    for f in engine_file("vecto_325kW").parent.iterdir():
        shutil.copy(f, tmp_path / f.name)
    (tmp_path / "325kW.vmap").write_text("engine speed [rpm],torque [Nm],fuel consumption [g/h]\n600,0,x\n")
    veng = tmp_path / "Engine_325kW_12.7l.veng"
    assert main(["simulate", "--engine", str(veng), "-o", str(tmp_path / "t.log.gz")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith("fuelid simulate: error: ") and "325kW.vmap: line 2: not a number" in err
    assert not (tmp_path / "t.log.gz").exists()


def test_an_engine_with_a_paper_truth_is_refused(tmp_path, capsys):
    assert main(["simulate", "--truth", "diesel_p320", "--engine", "vecto_325kW", "-o",
                 str(tmp_path / "t.log.gz")]) == 1
    assert "map truth only" in capsys.readouterr().err


def test_every_shipped_catalog_entry_is_in_replay_logs():
    logs = Path(__file__).resolve().parents[1] / "replay_logs"
    assert all((logs / f"{name}.log.gz").is_file() for name in catalog.SHIPPED)
    made_on_demand = set(catalog.CATALOG) - set(catalog.SHIPPED)
    assert made_on_demand == {f"map_cycle_{k:02d}" for k in range(1, 12)} | {f"map_day_{k}" for k in range(1, 6)} | {
        f"generic_{name}_20min" for name in catalog.GENERIC_EFFECT_TRIPS}
    assert "--truth map" in catalog.command_line("map_cycle_01") and "--engine vecto_325kW" in \
        catalog.command_line("map_cycle_01")


def test_a_catalog_entry_on_another_engine_with_noise(tmp_path, capsys):
    veng = engine_file("vecto_325kW")
    assert main(["simulate", "--catalog", "sample_diesel_1min", "--engine", str(veng), "--noise", "0.5", "--dir",
                 str(tmp_path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["truth"] == "map"
    summary = json.loads((tmp_path / "sample_diesel_1min.truth.json").read_text())
    assert summary["fuel_truth"]["engine"]["file"] == veng.name and summary["config"]["engine"] == str(veng)
    assert summary["fuel_truth"]["noise"]["std"] == 0.5 and 0.2 < summary["noise_floor"]["rms"] < 0.8


def test_an_engine_burning_gas_is_refused_in_one_line(tmp_path, capsys):
    for f in engine_file("vecto_325kW").parent.iterdir():
        shutil.copy(f, tmp_path / f.name)
    veng = tmp_path / "Engine_325kW_12.7l.veng"
    doc = json.loads(veng.read_text())
    doc["Body"]["FuelType"] = "NGPI"
    veng.write_text(json.dumps(doc))
    assert main(["simulate", "--engine", str(veng), "-o", str(tmp_path / "t.log.gz")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "fuel type NGPI is a gas" in err
