"""Reliability over loopback: 50 trucks × 5 files uploading at once, and the server SIGKILLed mid-upload."""
import hashlib
import http.client
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import sqlalchemy as sa

from fuelid.fleet import db
from fuelid.logger.upload import request_json, upload_file, upload_with_retry
from tests.fleet.conftest import Server, make_mcap


def assert_consistent(s: Server, expected: dict[str, str]) -> None:
    """Database rows and blobs match `expected` (sha256 → truck) exactly; no partial upload left over."""
    with s.engine.connect() as conn:
        rows = dict(conn.execute(sa.select(db.files.c.sha256, db.files.c.truck)).all())
    assert rows == expected
    blobs = {p.name: p for p in (s.data_dir / "blobs").glob("*/*")}
    assert set(blobs) == set(expected)
    for sha, p in blobs.items():
        assert hashlib.sha256(p.read_bytes()).hexdigest() == sha
    assert list((s.data_dir / "incoming").iterdir()) == []


def test_50_trucks_5_files_each_concurrently(server, tmp_path):
    trucks = [f"TRUCK{i:02d}" for i in range(50)]
    tokens = {t: server.token("truck", t) for t in trucks}
    files = {t: [make_mcap(tmp_path / f"{t}-{k}.mcap", t, seed=100 * i + k, messages=5) for k in range(5)]
             for i, t in enumerate(trucks)}

    def truck_uploads(truck):
        # every file twice: the second time must be "already stored", never a second row
        return [upload_with_retry(p, server.url, tokens[truck], deadline_s=60)
                for p in files[truck] + files[truck][:1]]

    with ThreadPoolExecutor(50) as pool:
        replies = dict(zip(trucks, pool.map(truck_uploads, trucks)))
    for t in trucks:
        assert [r["status"] for r in replies[t]] == ["stored"] * 5 + ["already stored"]
    expected = {r["sha256"]: t for t in trucks for r in replies[t]}
    assert len(expected) == 250
    assert_consistent(server, expected)
    listing = request_json("GET", server.url + "/api/v1/trucks", server.token("engineer"))
    assert [(t["truck"], t["files"]) for t in listing] == [(t, 5) for t in trucks]


def test_server_killed_mid_upload_then_the_client_resumes(server, tmp_path):
    token = server.token("truck", "T1")
    done = upload_file(make_mcap(tmp_path / "done.mcap", "T1", seed=1), server.url, token)
    path = make_mcap(tmp_path / "big.mcap", "T1", seed=2, messages=4000, payload_bytes=256)
    data = path.read_bytes()
    sha = hashlib.sha256(data).hexdigest()

    # A PUT announcing the whole file but sending only its first half, then the server dies.
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
    conn.putrequest("PUT", f"/api/v1/uploads/{sha}?size={len(data)}&offset=0")
    conn.putheader("Authorization", f"Bearer {token}")
    conn.putheader("Content-Length", str(len(data)))
    conn.endheaders()
    half = len(data) // 2
    conn.send(data[:half])
    part = None
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        parts = list((server.data_dir / "incoming").glob("*.part"))
        if parts and parts[0].stat().st_size == half:
            part = parts[0]
            break
        time.sleep(0.02)
    assert part is not None, "the server did not receive the first half"
    server.kill()
    conn.close()

    # The client retries while the server is down and finishes once it is back, sending only the rest.
    result = {}
    uploader = threading.Thread(target=lambda: result.update(
        upload_with_retry(path, server.url, token, deadline_s=60)))
    uploader.start()
    time.sleep(1.0)
    server.start()
    state = request_json("GET", f"{server.url}/api/v1/uploads/{sha}?size={len(data)}", token)
    uploader.join(60)
    assert state["offset"] in (half, len(data)) or state["stored"]
    assert result["status"] == "stored" and result["sha256"] == sha
    assert_consistent(server, {done["sha256"]: "T1", sha: "T1"})
