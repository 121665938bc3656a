"""Security and fault probe of `fuelid serve` on loopback: credentials, path and number tricks, size limits,
refused and racing uploads, stalled and half-sent connections, a connection flood under `ulimit -n 1024`,
SIGKILL mid-upload, hostile token names and truck ids, cache headers, file modes.

    .venv/bin/python benchmarks/bench_fleet_probe.py

The server is the real `fuelid serve` (no refits) in a subprocess with its open-file limit set to 1024 and short
deadlines (--header-timeout 2 --body-idle-timeout 2 --request-timeout 6) so the whole run takes well under a
minute. Prints one row per probe (probe, expected, got, ok), then the number of responses with status 500 over
every request the probes made, the files left in `incoming/`, and the modes of the data directory's folders
and files. Exit status 1 when any probe differs from what is expected, a 500 was seen, or a file is left.
"""
import hashlib
import http.client
import json
import resource
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import time
import urllib.parse
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fuelid.fleet import auth, db  # noqa: E402
from fuelid.logger.upload import upload_with_retry  # noqa: E402
from tests.fleet.conftest import free_port, make_mcap  # noqa: E402

HEADER_S, BODY_IDLE_S, REQUEST_S = 2.0, 2.0, 6.0
statuses: list[int] = []  # every status any probe received


class Fleet:
    """`fuelid serve` in a subprocess (open-file limit 1024) on a free loopback port."""

    def __init__(self, data_dir: Path):
        self.data_dir, self.port = data_dir, free_port()
        self.proc = None

    def start(self) -> "Fleet":
        cmd = [sys.executable, "-m", "fuelid.cli", "serve", "--data-dir", str(self.data_dir), "--port",
               str(self.port), "--no-auto-refit", "--max-upload-mb", "4", "--log-level", "critical",
               "--header-timeout", str(HEADER_S), "--body-idle-timeout", str(BODY_IDLE_S),
               "--request-timeout", str(REQUEST_S)]
        hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
        self.proc = subprocess.Popen(cmd, preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_NOFILE, (1024, hard)))
        for _ in range(300):
            try:
                if call("GET", "/api/v1/health", record=False)[0] == 200:
                    return self
            except OSError:
                time.sleep(0.1)
        raise SystemExit("server did not start")

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(20)


fleet: Fleet
URL = ""


def call(method: str, path: str, token: str | None = None, body: bytes | None = None, headers: dict | None = None,
         record: bool = True) -> tuple[int, dict | str, http.client.HTTPMessage]:
    """One request → (status, JSON body or text, headers); the status is recorded."""
    conn = http.client.HTTPConnection("127.0.0.1", fleet.port, timeout=30)
    h = {**({"Authorization": f"Bearer {token}"} if token else {}), **(headers or {})}
    conn.request(method, path, body=body, headers=h)
    r = conn.getresponse()
    raw = r.read()
    conn.close()
    if record:
        statuses.append(r.status)
    try:
        return r.status, json.loads(raw), r.headers
    except ValueError:
        return r.status, raw.decode(errors="replace"), r.headers


def put_headers(token: str, sha: str, size: int, length: int, offset: int = 0) -> http.client.HTTPConnection:
    conn = http.client.HTTPConnection("127.0.0.1", fleet.port, timeout=30)
    conn.putrequest("PUT", f"/api/v1/uploads/{sha}?size={size}&offset={offset}")
    conn.putheader("Authorization", f"Bearer {token}")
    conn.putheader("Content-Length", str(length))
    conn.endheaders()
    return conn


def answer(conn: http.client.HTTPConnection) -> tuple[int, dict]:
    r = conn.getresponse()
    status, body = r.status, json.loads(r.read())
    conn.close()
    statuses.append(status)
    return status, body


def incoming() -> list[str]:
    return sorted(p.name for p in (fleet.data_dir / "incoming").iterdir())


def wait_for(predicate, timeout_s: float = 10.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def mcap(tmp: Path, name: str, truck: str, seed: int, messages: int = 20) -> tuple[Path, bytes, str]:
    path = make_mcap(tmp / name, truck, seed=seed, messages=messages, payload_bytes=256 if messages > 20 else 8)
    data = path.read_bytes()
    return path, data, hashlib.sha256(data).hexdigest()


def probes(tmp: Path, engine) -> list[tuple[str, str, str, bool]]:
    """(probe, expected, got, as expected) for every probe."""
    admin, engineer = auth.create_token(engine, "admin")["token"], auth.create_token(engine, "engineer")["token"]
    truck = auth.create_token(engine, "truck", "T1")["token"]
    revoked = auth.create_token(engine, "engineer")
    auth.revoke_token(engine, revoked["id"])
    rows = []

    def row(probe: str, expected: str, got: str, ok: bool | None = None):
        rows.append((probe, expected, got, got == expected if ok is None else ok))

    # credentials
    for label, token in [("no token", None), ("unknown token", "fuelid_x"), ("revoked token", revoked["token"]),
                         ("not a bearer token", None)]:
        headers = {"Authorization": "Basic YWRtaW46YWRtaW4="} if label == "not a bearer token" else None
        row(f"GET /trucks, {label}", "401", str(call("GET", "/api/v1/trucks", token, headers=headers)[0]))
    row("GET /trucks, truck token", "403", str(call("GET", "/api/v1/trucks", truck)[0]))
    status, body, _ = call("POST", "/api/v1/tokens", engineer, b'{"role": "admin"}',
                           {"Content-Type": "application/json"})
    row("POST /tokens, engineer token", "403 an engineer token may not do this",
        f"{status} {body['detail'].split(' (')[0]}")
    # paths and numbers
    status = call("GET", "/api/v1/trucks/..%2F..%2Ffleet.db/files", engineer)[0]
    row("GET /trucks/..%2F..%2Ffleet.db/files", "404 or 422", str(status), status in (404, 422))
    row("GET /static/../fleet.db", "404", str(call("GET", "/static/../fleet.db")[0]))
    row("GET /uploads/<not hex>", "422", str(call("GET", f"/api/v1/uploads/{'g' * 64}?size=1", truck)[0]))
    row("GET /uploads size of 390 digits", "422", str(call("GET", f"/api/v1/uploads/{'0' * 64}?size={'9' * 390}",
                                                           truck)[0]))
    row("GET /fleet threshold=1e400", "422", str(call("GET", "/api/v1/fleet?threshold=1e400", engineer)[0]))
    points = urllib.parse.quote(f"{'9' * 390}x600Nm")
    row("GET /fleet points of 390 digits", "422", str(call("GET", f"/api/v1/fleet?points={points}", engineer)[0]))
    row("GET /jobs/99999999999", "422", str(call("GET", "/api/v1/jobs/99999999999", engineer)[0]))
    # sizes and refusals: nothing kept
    _, data, sha = mcap(tmp, "a.mcap", "T1", seed=1)
    row("GET /uploads size over the limit", "413", str(call("GET", f"/api/v1/uploads/{sha}?size={8 << 20}",
                                                            truck)[0]))
    row("PUT size=0", "422", str(call("PUT", f"/api/v1/uploads/{sha}?size=0", truck, b"")[0]))
    for _ in range(9):  # one more than the partial uploads an uploader may hold
        status, body, _ = call("PUT", f"/api/v1/uploads/{sha}?size={len(data)}", truck, b"")
    row("9 empty-body PUTs", "202, 0 kept", f"{status}, {len(incoming())} kept")
    conn = put_headers(truck, sha, len(data), len(data) + 10)
    conn.send(data + b"0123456789")
    status, body = answer(conn)
    row("PUT body past its size", "413, 0 kept", f"{status}, {len(incoming())} kept")
    bad = bytes(len(data))
    status, body, _ = call("PUT", f"/api/v1/uploads/{sha}?size={len(data)}", truck, bad)
    row("PUT bytes not matching the sha256", "422, 0 kept", f"{status}, {len(incoming())} kept")
    status, body, _ = call("PUT", f"/api/v1/uploads/{hashlib.sha256(bad).hexdigest()}?size={len(bad)}", truck, bad)
    row("PUT a file that is not MCAP", "422, 0 kept", f"{status}, {len(incoming())} kept")
    _, evil, evil_sha = mcap(tmp, "evil.mcap", "<script>alert(1)</script>", seed=2)
    status, body, _ = call("PUT", f"/api/v1/uploads/{evil_sha}?size={len(evil)}", admin, evil)
    row("PUT a file naming truck <script>", "422, 0 kept", f"{status}, {len(incoming())} kept")
    conn = put_headers(truck, sha, len(data), len(data))
    conn.close()
    time.sleep(0.2)
    row("PUT headers then disconnect", "0 kept", f"{len(incoming())} kept")
    status, body, _ = call("PUT", f"/api/v1/uploads/{sha}?size={len(data)}", truck, data)
    row("PUT the file after the refusals", "201", str(status))
    # races
    path, data, sha = mcap(tmp, "race.mcap", "T1", seed=3, messages=800)
    slow = put_headers(admin, sha, len(data), len(data))
    slow.send(data[:1000])
    wait_for(lambda: len(incoming()) == 1)
    busy = call("PUT", f"/api/v1/uploads/{sha}?size={len(data)}", admin, data)[0]
    row("second PUT while the first streams", "409", str(busy))
    whole = call("PUT", f"/api/v1/uploads/{sha}?size={len(data)}", truck, data)[0]
    slow.send(data[1000:])
    status, body = answer(slow)
    row("truck PUTs whole while admin streams", "201; slow one 200 JSON",
        f"{whole}; slow one {status} {'JSON' if 'status' in body else body}")
    # stalled upload: its lock goes at the body deadline and the client then completes
    path, data, sha = mcap(tmp, "stall.mcap", "T1", seed=4, messages=2000)
    stalled = put_headers(truck, sha, len(data), len(data))
    stalled.send(data[:100_000])
    wait_for(lambda: incoming() != [])
    t0 = time.monotonic()
    reply = upload_with_retry(path, URL, truck, deadline_s=30)
    took = time.monotonic() - t0
    stalled_status, _ = answer(stalled)
    row("upload while another PUT of it stalls", f"stored within {BODY_IDLE_S:g} s + backoff; 408",
        f"{reply['status']} after {took:.1f} s; {stalled_status}",
        reply["status"] == "stored" and took < BODY_IDLE_S + 4 and stalled_status == 408)
    # slow and half-sent connections
    c = socket.create_connection(("127.0.0.1", fleet.port))
    c.sendall(b"GET /api/v1/health HTTP/1.1\r\nHost: x\r\n")
    t0 = time.monotonic()
    c.settimeout(10)
    closed = c.recv(1) == b""
    took = time.monotonic() - t0
    row("headers never finished", f"closed at {HEADER_S:g} s", f"closed at {took:.1f} s",
        closed and took < HEADER_S + 1)
    c.close()
    held = []
    for _ in range(2000):
        s = socket.create_connection(("127.0.0.1", fleet.port), timeout=5)
        s.sendall(b"GET /api/v1/health HTTP/1.1\r\nHost: x\r\n")
        held.append(s)
    worst = 0.0
    for _ in range(5):
        t0 = time.monotonic()
        ok = call("GET", "/api/v1/health")[0] == 200
        worst = max(worst, time.monotonic() - t0 if ok else float("inf"))
    for s in held:
        s.close()
    row("2000 half-sent GETs, ulimit -n 1024: health", "200 within 1 s", f"200 within {worst:.2f} s", worst < 1.0)
    # SIGKILL mid-upload, then resume
    path, data, sha = mcap(tmp, "kill.mcap", "T1", seed=5, messages=2000)
    conn = put_headers(truck, sha, len(data), len(data))
    conn.send(data[: len(data) // 2])
    wait_for(lambda: incoming() != [])
    fleet.kill()
    conn.close()
    fleet.start()
    reply = upload_with_retry(path, URL, truck, deadline_s=30)
    row("server SIGKILLed mid-upload, then resumed", "stored", reply["status"])
    # tokens and headers
    status, body, headers = call("POST", "/api/v1/tokens", admin,
                                 json.dumps({"role": "engineer", "name": "x\x1b[31m\u202e"}).encode(),
                                 {"Content-Type": "application/json"})
    row("token name with ESC and U+202E", "422", str(status))
    status, body, headers = call("POST", "/api/v1/tokens", admin, b'{"role": "engineer"}',
                                 {"Content-Type": "application/json"})
    row("POST /tokens Cache-Control", "201 no-store", f"{status} {headers.get('Cache-Control')}")
    row("GET /docs (Swagger UI from a CDN)", "404", str(call("GET", "/docs")[0]))
    return rows


def modes(data_dir: Path) -> tuple[set[str], set[str]]:
    entries = [data_dir] + [p for p in data_dir.rglob("*") if "jobs" not in p.relative_to(data_dir).parts]
    return ({oct(stat.S_IMODE(p.stat().st_mode)) for p in entries if p.is_dir()},
            {oct(stat.S_IMODE(p.stat().st_mode)) for p in entries if p.is_file()})


def main() -> int:
    global fleet, URL
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, max(soft, 4096)), hard))  # the probe holds 2000 sockets
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        fleet = Fleet(tmp / "data")
        URL = f"http://127.0.0.1:{fleet.port}"
        engine = db.open_database(fleet.data_dir)
        fleet.start()
        try:
            rows = probes(tmp, engine)
        finally:
            fleet.stop()
            engine.dispose()
        left = incoming()
        dir_modes, file_modes = modes(fleet.data_dir)
    width = max(len(r[0]) for r in rows)
    print(f"{'probe':<{width}}  {'expected':<40}  got")
    failed = 0
    for probe, expected, got, ok in rows:
        failed += not ok
        print(f"{probe:<{width}}  {expected:<40}  {got}{'' if ok else '   <-- differs'}")
    fives = sum(s == 500 for s in statuses)
    print(f"\n{len(rows)} probes, {failed} differing; {len(statuses)} responses, {fives} with status 500; "
          f"{len(left)} files left in incoming/; folder modes {sorted(dir_modes)}, file modes {sorted(file_modes)}")
    return 1 if failed or fives or left or dir_modes != {"0o700"} or file_modes != {"0o600"} else 0


if __name__ == "__main__":
    sys.exit(main())
