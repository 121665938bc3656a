"""The MCAP files fuelid writes, read by the TypeScript reference reader (@mcap/core) as Foxglove reads them.

Needs `node` and the npm packages @mcap/core and fzstd (zstd in JavaScript): from FUELID_MCAP_TS_MODULES (a
directory holding node_modules/), else a cache under ~/.cache/fuelid/mcap-ts that the first run fills with
`npm install` (a few seconds, 30 s at most). Skips, saying why, when either is unavailable.
"""
import gzip
import itertools
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from fuelid.cli import main
from fuelid.logger.readers import read_frames
from fuelid.logger.recorder import Recorder, open_writer

HERE = Path(__file__).resolve().parent
SAMPLE = HERE.parents[1] / "replay_logs" / "sample_diesel_1min.log.gz"
PACKAGES = ["@mcap/core@2.2.2", "fzstd@0.1.1"]
NPM_TIMEOUT_S = 30


@pytest.fixture(scope="module")
def node_modules() -> Path:
    if shutil.which("node") is None:
        pytest.skip("node is not installed")
    home = Path(os.environ.get("FUELID_MCAP_TS_MODULES")
                or Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "fuelid" / "mcap-ts")
    modules = home / "node_modules"
    if not all((modules / p.rsplit("@", 1)[0]).is_dir() for p in PACKAGES):
        if shutil.which("npm") is None:
            pytest.skip(f"@mcap/core is not in {modules} and npm is not installed")
        home.mkdir(parents=True, exist_ok=True)
        try:
            subprocess.run(["npm", "install", "--prefix", str(home), "--no-audit", "--no-fund", *PACKAGES],
                           check=True, capture_output=True, timeout=NPM_TIMEOUT_S)
        except (subprocess.SubprocessError, OSError) as exc:
            pytest.skip(f"npm install {' '.join(PACKAGES)} into {home} failed: {type(exc).__name__}")
    return modules


def ts_read(node_modules: Path, path: Path) -> dict:
    """{"reader": "indexed" or "stream", "messages", "statistics"}, or {"error"} from @mcap/core."""
    done = subprocess.run(["node", str(HERE / "mcap_ts_read.cjs"), str(path)], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "NODE_PATH": str(node_modules)})
    return json.loads(done.stdout)


@pytest.fixture(scope="module")
def first_lines(tmp_path_factory) -> Path:
    src = tmp_path_factory.mktemp("ts") / "first.log"
    with gzip.open(SAMPLE, "rt") as f:
        src.write_text("".join(itertools.islice(f, 800)))
    return src


def test_a_converted_file_reads_whole_as_foxglove_reads_it(node_modules, first_lines, tmp_path):
    """No chunk index: Foxglove's choice falls to the stream reader, which reads every message."""
    out = tmp_path / "converted.mcap"
    assert main(["convert", str(first_lines), "-o", str(out)]) == 0
    assert ts_read(node_modules, out) == {"reader": "stream", "messages": 1591, "statistics": 1591}


def test_a_daemon_file_reads_whole_through_the_index(node_modules, first_lines, tmp_path):
    out = tmp_path / "live.mcap"
    writer = open_writer(out)
    recorder = Recorder(writer)
    for msg in read_frames(first_lines):
        recorder.on_message_received(msg)
    writer.close()
    assert ts_read(node_modules, out) == {"reader": "indexed", "messages": 1591, "statistics": 1591}


def test_the_previous_conversion_is_what_the_indexed_reader_refused(node_modules):
    """Why convert writes no chunk index: one without message indexes stops @mcap/core's indexed reader
    (fuelid still reads these files: tests/test_cli_convert.py)."""
    result = ts_read(node_modules, HERE / "data" / "convert_chunk_index_only.mcap")
    assert "chunk index without message indexes" in result["error"]
