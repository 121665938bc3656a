"""The fleet as deployed, with nothing stood in: `fuelid serve` with its Dask LocalCluster, a truck's real
converted recording uploaded, a refit identifying it (PEM, diagnosis, report), and the engineer fetching the
model and loading it into the identifier."""
import json
import subprocess
import sys
import time
import urllib.request

from fuelid.fleet import auth, db
from fuelid.cli import main as fuelid
from fuelid.ident.modelfile import load_model
from fuelid.logger.mcap_log import read_metadata
from tests.fleet.conftest import REPO, free_port


def test_a_truck_uploads_and_the_engineer_fetches_its_identified_model(tmp_path, capsys, monkeypatch):
    log, trip = tmp_path / "trip.log.gz", tmp_path / "trip.mcap"
    assert fuelid(["simulate", "--truth", "diesel_p320", "--cycle", "mixed", "--duration", "900", "--seed", "41",
                   "-o", str(log)]) == 0
    assert fuelid(["convert", str(log), "-o", str(trip)]) == 0
    vin = read_metadata(trip)["fuelid"]["truck"]

    data, port = tmp_path / "fleet", free_port()
    engine = db.open_database(data, None)
    truck_token, engineer_token = auth.create_token(engine, "truck", vin)["token"], auth.create_token(engine, "engineer")["token"]
    engine.dispose()
    server = subprocess.Popen([sys.executable, "-c", "from fuelid.cli import main; raise SystemExit(main())", "serve",
                               "--data-dir", str(data), "--port", str(port), "--workers", "1", "--no-auto-refit",
                               "--log-level", "warning"], cwd=REPO)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                urllib.request.urlopen(url + "/api/v1/health", timeout=1).read()
                break
            except OSError:
                assert server.poll() is None and time.monotonic() < deadline, "fuelid serve did not start"
                time.sleep(0.2)
        monkeypatch.setenv("FUELID_SERVER", url)
        assert fuelid(["upload", str(trip), "--token", truck_token]) == 0
        capsys.readouterr()
        assert fuelid(["refit", vin, "--wait", "600", "--json", "--token", engineer_token]) == 0
        [job] = json.loads(capsys.readouterr().out)
        assert (job["status"], job["model_version"]) == ("done", 1), job
        model_path, report = tmp_path / "model.json", tmp_path / "report.html"
        assert fuelid(["fetch", vin, "-o", str(model_path), "--report", str(report), "--token", engineer_token]) == 0
        model = load_model(model_path)
        assert model.structure.nc == 11 and model.output_unit == "L/h"  # the paper's BJ, in the bus's unit
        assert model.validation["fit_percent"]["simulation"] > 80
        assert "plotly" in report.read_text(encoding="utf-8")
        capsys.readouterr()
        assert fuelid(["trucks", "--json", "--token", engineer_token]) == 0
        [row] = json.loads(capsys.readouterr().out)
        assert (row["truck"], row["files"], row["latest_model_version"]) == (vin, 1, 1)
    finally:
        server.terminate()
        server.wait(30)
