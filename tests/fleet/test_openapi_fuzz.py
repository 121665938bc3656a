"""A schemathesis pass over the live server's OpenAPI description: its CLI sends generated requests to every
operation (positive and negative data, every phase) with an admin token; no 5xx, and status codes, content
types and JSON bodies as the description declares. Bounded: at most 25 examples per operation, fixed seed.
(The CLI rather than schemathesis' pytest plugin, which does not run under pytest 9.)"""
import subprocess
import sys
from pathlib import Path

from fuelid.logger.upload import upload_file
from tests.fleet.conftest import Server, make_mcap

CHECKS = "not_a_server_error,status_code_conformance,content_type_conformance,response_schema_conformance"


def test_api_conforms_to_its_openapi_description(tmp_path):
    s = Server(tmp_path / "data").start()
    try:
        upload_file(make_mcap(tmp_path / "a.mcap", "T1"), s.url, s.token("truck", "T1"))  # something to list
        cli = Path(sys.executable).parent / "schemathesis"
        run = subprocess.run(
            [str(cli), "run", f"{s.url}/openapi.json", "--checks", CHECKS, "--max-examples", "25", "--seed", "1",
             "--header", f"Authorization: Bearer {s.token('admin')}", "--request-timeout", "20",
             "--report-dir", str(tmp_path / "reports")],
            capture_output=True, text=True, timeout=600, cwd=tmp_path,  # it keeps a cache in its cwd
            env={"NO_COLOR": "1", "PATH": "/usr/bin:/bin"})
        assert run.returncode == 0, run.stdout[-6000:] + run.stderr[-2000:]
        assert "No issues found" in run.stdout or " passed" in run.stdout
    finally:
        s.stop()
