"""Fleet test helpers: small MCAP files of named trucks, a live server in a subprocess (killable), tokens,
and the PostgreSQL URL that .ci/postgres-setup provides."""
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from fuelid.fleet import auth, db
from fuelid.logger.mcap_log import RAW_SCHEMA, McapLogWriter

REPO = Path(__file__).resolve().parents[2]
POSTGRES_URL_FILE = Path(os.environ.get("TMPDIR", "/tmp")) / "fuelid-test-postgres-url"


def make_mcap(path: Path, truck: str, seed: int = 0, messages: int = 20, payload_bytes: int = 8) -> Path:
    """A small complete MCAP log of `truck`: `messages` /can/raw frames 10 ms apart (one chunk per second of
    log time, as the daemon writes), content set by `seed` (distinct seeds → distinct files and hashes) from
    t0 = 1_700_000_000 s + seed days; `payload_bytes` > 8 pads each record with random bytes to grow the file."""
    t0 = 1_700_000_000 + 86_400 * seed
    with McapLogWriter(path, metadata={"truck": truck, "source": "test"}, fsync=False) as w:
        w.add_channel("/can/raw", RAW_SCHEMA)
        for k in range(messages):
            w.write("/can/raw", t0 * 10**9 + k * 10**7, {
                "t": t0 + k / 100, "id": 0x0CF00400, "extended": True, "dlc": 8, "error": False, "remote": False,
                "channel": "can0", "data": os.urandom(payload_bytes).hex() if payload_bytes > 8 else f"{seed:016x}"})
    return path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def postgres_url() -> str | None:
    url = os.environ.get("FUELID_TEST_POSTGRES_URL")
    if not url and POSTGRES_URL_FILE.exists():
        url = POSTGRES_URL_FILE.read_text().strip()
    return url or None


class Server:
    """tests/fleet/fake_server.py in a subprocess on a free loopback port; `kill()` is SIGKILL."""

    def __init__(self, data_dir: Path, database_url: str | None = None, **options):
        self.data_dir, self.database_url, self.options = data_dir, database_url, options
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.engine = db.open_database(data_dir, database_url)
        self.proc = None

    def start(self) -> "Server":
        cmd = [sys.executable, "-m", "tests.fleet.fake_server", "--data-dir", str(self.data_dir),
               "--port", str(self.port)]
        if self.database_url:
            cmd += ["--database-url", self.database_url]
        for k, v in self.options.items():
            cmd += [f"--{k.replace('_', '-')}", str(v)]
        self.proc = subprocess.Popen(cmd, cwd=REPO)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                urllib.request.urlopen(self.url + "/api/v1/health", timeout=1).read()
                return self
            except OSError:
                if self.proc.poll() is not None:
                    raise RuntimeError(f"server exited with {self.proc.returncode}")
                time.sleep(0.1)
        self.stop()  # a server that never answered is not left running after the test
        raise RuntimeError("server did not start in 30 s")

    def token(self, role: str, truck: str | None = None) -> str:
        return auth.create_token(self.engine, role, truck)["token"]

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()

    def stop(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.kill()
        self.engine.dispose()


@pytest.fixture(params=["sqlite", "postgresql"])
def database(request, tmp_path):
    """None (SQLite in the data dir) or a fresh PostgreSQL database; skips only when PostgreSQL is absent."""
    if request.param == "sqlite":
        yield None
        return
    base = postgres_url()
    if base is None:
        pytest.skip(f"PostgreSQL not set up: run .ci/postgres-setup (or set FUELID_TEST_POSTGRES_URL); "
                    f"no {POSTGRES_URL_FILE}")
    import sqlalchemy as sa

    name = f"fuelid_test_{os.getpid()}_{abs(hash(str(tmp_path))) % 10**8}"
    admin = sa.create_engine(base, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.exec_driver_sql(f"CREATE DATABASE {name}")
    yield base.rsplit("/", 1)[0] + "/" + name
    with admin.connect() as conn:
        conn.exec_driver_sql(f"DROP DATABASE IF EXISTS {name} WITH (FORCE)")
    admin.dispose()


@pytest.fixture
def server(tmp_path, database):
    s = Server(tmp_path / "data", database).start()
    yield s
    s.stop()


@pytest.fixture
def sqlite_server(tmp_path):
    s = Server(tmp_path / "data").start()
    yield s
    s.stop()
