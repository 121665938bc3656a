"""The fleet server against slow, stalled, racing and hostile clients over loopback (a real uvicorn in a
subprocess, short deadlines): connection floods, header slowloris, a stalled upload's lock, concurrent
completion, refusals that keep nothing, file modes, token names, cache headers."""
import hashlib
import http.client
import json
import resource
import socket
import stat
import threading
import time

import pytest

import fuelid.logger.upload as upload_module
from fuelid.cli import main as fuelid
from fuelid.fleet import auth
from fuelid.fleet.storage import BlobStore
from fuelid.logger.upload import Rejected, request, request_json, upload_file
from tests.fleet.conftest import Server, make_mcap


@pytest.fixture
def quick_server(tmp_path):
    """A server with 1.5 s header and 2 s body-idle deadlines."""
    s = Server(tmp_path / "data", header_timeout=1.5, body_idle_timeout=2.0).start()
    yield s
    s.stop()


def put_headers(s: Server, token: str, sha: str, size: int, offset: int = 0, length: int | None = None,
                truck: str | None = None) -> http.client.HTTPConnection:
    """A PUT whose headers are sent and whose body is left to the caller (conn.send)."""
    conn = http.client.HTTPConnection("127.0.0.1", s.port, timeout=30)
    conn.putrequest("PUT", f"/api/v1/uploads/{sha}?size={size}&offset={offset}" + (f"&truck={truck}" if truck else ""))
    conn.putheader("Authorization", f"Bearer {token}")
    conn.putheader("Content-Length", str(size - offset if length is None else length))
    conn.endheaders()
    return conn


def half_put(s: Server, token: str, data: bytes) -> http.client.HTTPConnection:
    """A PUT of the first half of `data` as a whole request (Content-Length: half)."""
    conn = put_headers(s, token, hashlib.sha256(data).hexdigest(), len(data), length=len(data) // 2)
    conn.send(data[: len(data) // 2])
    return conn


def reply(conn: http.client.HTTPConnection) -> tuple[int, dict]:
    r = conn.getresponse()
    status, body = r.status, json.loads(r.read())
    conn.close()
    return status, body


def leftovers(s: Server) -> list:
    return sorted(p.name for p in (s.data_dir / "incoming").iterdir())


def wait_for(predicate, timeout_s: float = 10.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def test_2000_half_open_connections_under_ulimit_1024_leave_health_answering(tmp_path):
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < 2200:
        pytest.skip(f"this test holds 2,000 sockets: the open-file hard limit is {hard}")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, 2200), hard))
    s = Server(tmp_path / "data", open_files=1024, header_timeout=2.0).start()
    held = []
    try:
        for _ in range(2000):  # headers begun, never finished: each holds a server socket until a deadline
            c = socket.create_connection(("127.0.0.1", s.port), timeout=5)
            c.sendall(b"GET /api/v1/health HTTP/1.1\r\nHost: fleet\r\n")
            held.append(c)
        times = []
        for _ in range(5):
            t0 = time.monotonic()
            assert request_json("GET", s.url + "/api/v1/health", None, timeout_s=1.0)["status"] == "ok"
            times.append(time.monotonic() - t0)
        assert max(times) < 1.0, times
        # and the half-sent requests are closed: none is still open after the header deadline
        time.sleep(2.5)
        for c in held:
            c.settimeout(1.0)
            try:
                assert c.recv(1) == b""
            except ConnectionResetError:
                pass
    finally:
        for c in held:
            c.close()
        s.stop()
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


def test_headers_sent_a_byte_at_a_time_are_cut_at_the_header_deadline(quick_server):
    c = socket.create_connection(("127.0.0.1", quick_server.port), timeout=5)
    t0 = time.monotonic()
    closed_after = None
    try:
        for byte in b"GET /api/v1/health HTTP/1.1\r\nHost: fleet\r\nX-Slow: " + b"a" * 100:
            c.sendall(bytes([byte]))
            time.sleep(0.1)
    except (BrokenPipeError, ConnectionResetError):
        closed_after = time.monotonic() - t0
    if closed_after is None:
        c.settimeout(5)
        assert c.recv(100) == b""
        closed_after = time.monotonic() - t0
    c.close()
    assert 1.4 < closed_after < 3.0


def test_a_stalled_upload_frees_its_file_within_the_body_deadline_and_fuelid_upload_completes(
        quick_server, tmp_path, monkeypatch, capsys):
    s = quick_server
    token = s.token("truck", "T1")
    path = make_mcap(tmp_path / "big.mcap", "T1", seed=2, messages=2000, payload_bytes=256)
    data = path.read_bytes()
    sha = hashlib.sha256(data).hexdigest()
    stalled = put_headers(s, token, sha, len(data))
    stalled.send(data[:100_000])  # then nothing, the socket held open
    assert wait_for(lambda: sum(p.stat().st_size for p in (s.data_dir / "incoming").glob("*.part")) == 100_000)

    puts = []
    real_request = upload_module.request

    def counting(method, url, *a, **kw):
        if method == "PUT":
            puts.append(time.monotonic())
        return real_request(method, url, *a, **kw)

    monkeypatch.setattr(upload_module, "request", counting)
    t0 = time.monotonic()
    assert fuelid(["upload", str(path), "--server", s.url, "--token", token, "--retry-s", "20"]) == 0
    elapsed = time.monotonic() - t0
    assert "stored for truck T1" in capsys.readouterr().out
    assert elapsed < 2.0 + 4.0  # the body deadline (2 s) and the client's next backoff step
    # while the file was busy (409) the client backed off: a handful of PUTs, not a tight loop
    assert len(puts) <= 6, len(puts)
    status, body = reply(stalled)
    assert status == 408 and "no byte of the request body for 2 s" in body["detail"]
    assert leftovers(s) == []


def test_a_whole_put_racing_a_slow_put_of_the_same_file_ends_in_json_never_500(quick_server, tmp_path):
    s = quick_server
    admin, truck = s.token("admin"), s.token("truck", "T1")
    path = make_mcap(tmp_path / "a.mcap", "T1", seed=3, messages=800, payload_bytes=128)
    data = path.read_bytes()
    sha = hashlib.sha256(data).hexdigest()
    slow = put_headers(s, admin, sha, len(data))
    slow.send(data[:1000])
    assert wait_for(lambda: len(list((s.data_dir / "incoming").glob("*.part"))) == 1)
    assert upload_file(path, s.url, truck)["status"] == "stored"  # the truck's own PUT stores it meanwhile
    slow.send(data[1000:])
    status, body = reply(slow)
    assert (status, body["status"], body["sha256"]) == (200, "already stored", sha)
    assert leftovers(s) == []


@pytest.mark.parametrize("case", ["empty body", "body past the declared size", "disconnect before the body"])
def test_refused_or_empty_puts_keep_no_partial_file(quick_server, tmp_path, case):
    s = quick_server
    token = s.token("truck", "T1")
    data = make_mcap(tmp_path / "a.mcap", "T1", seed=4).read_bytes()
    sha = hashlib.sha256(data).hexdigest()
    for _ in range(9):  # more than the 8 partial uploads an uploader may hold
        if case == "empty body":
            status, body = reply(put_headers(s, token, sha, len(data), length=0))
            assert (status, body["offset"]) == (202, 0)
        elif case == "body past the declared size":
            conn = put_headers(s, token, sha, len(data), length=len(data) + 10)
            conn.send(data + b"0123456789")
            status, body = reply(conn)
            assert status == 413 and "past the declared size" in body["detail"]
        else:
            put_headers(s, token, sha, len(data)).close()
            time.sleep(0.05)
        assert leftovers(s) == []
    assert upload_file(tmp_path / "a.mcap", s.url, token)["status"] == "stored"
    assert leftovers(s) == []


def test_data_directory_0700_and_its_files_0600(quick_server, tmp_path):
    s = quick_server
    upload_file(make_mcap(tmp_path / "a.mcap", "T1", seed=5), s.url, s.token("truck", "T1"))
    part = make_mcap(tmp_path / "b.mcap", "T1", seed=6).read_bytes()
    conn = put_headers(s, s.token("truck", "T1"), hashlib.sha256(part).hexdigest(), len(part))
    conn.send(part[:50])  # a partial upload being received
    assert wait_for(lambda: leftovers(s) != [])
    dirs = [s.data_dir] + [p for p in s.data_dir.rglob("*") if p.is_dir() and p.name != "jobs"]
    files = [p for p in s.data_dir.rglob("*") if p.is_file() and "jobs" not in p.parts]
    assert {p.name for p in files} >= {"fleet.db", leftovers(s)[0]} and len(dirs) >= 4
    assert {oct(stat.S_IMODE(p.stat().st_mode)) for p in dirs} == {"0o700"}
    assert {oct(stat.S_IMODE(p.stat().st_mode)) for p in files} == {"0o600"}
    conn.close()


def test_token_names_are_printable_text_and_printed_escaped(quick_server, capsys):
    s = quick_server
    admin = s.token("admin")
    for name in ["\x1b[2J\x1b[31mroot", "cab\x00", "evil\u202etxt.exe", "x" * 201]:
        with pytest.raises(Rejected, match="HTTP 422"):
            request_json("POST", s.url + "/api/v1/tokens", admin, {"role": "engineer", "name": name})
    assert fuelid(["token", "create", "--role", "engineer", "--name", "a\x07b", "--data-dir", str(s.data_dir)]) != 0
    assert "printable" in capsys.readouterr().err
    made = request_json("POST", s.url + "/api/v1/tokens", admin, {"role": "engineer", "name": "Ana Müller, café 7"})
    assert made["name"] == "Ana Müller, café 7"
    # a name stored before the rule (straight into the database) is listed with its escapes visible
    with s.engine.begin() as conn:
        conn.execute(auth.db.tokens.update().where(auth.db.tokens.c.id == made["id"]).values(name="a\x1b[31m\u202eb"))
    assert fuelid(["token", "list", "--server", s.url, "--token", admin]) == 0
    line = [x for x in capsys.readouterr().out.splitlines() if x.split()[0] == str(made["id"])][0]
    assert line.endswith("a\\u001b[31m\\u202eb") and "\x1b" not in line


def test_every_api_reply_is_no_store_and_there_is_no_cdn_docs_page(quick_server):
    s = quick_server
    admin = s.token("admin")
    _, _, headers = request("POST", s.url + "/api/v1/tokens", admin, data=b'{"role": "engineer"}',
                            content_type="application/json")
    assert headers["Cache-Control"] == "no-store"
    for path in ["/api/v1/health", "/api/v1/tokens", "/api/v1/trucks", "/openapi.json"]:
        assert request("GET", s.url + path, admin)[2]["Cache-Control"] == "no-store"
    for path, token in [("/api/v1/trucks", None), ("/api/v1/trucks/NOPE/files", admin), ("/api/v1/nope", admin)]:
        with pytest.raises(Rejected) as refused:
            request("GET", s.url + path, token)
        conn = http.client.HTTPConnection("127.0.0.1", s.port, timeout=5)
        conn.request("GET", path, headers={"Authorization": f"Bearer {token}"} if token else {})
        assert conn.getresponse().getheader("Cache-Control") == "no-store", (path, refused.value)
        conn.close()
    for path in ["/docs", "/redoc"]:
        with pytest.raises(Rejected, match="HTTP 404"):
            request("GET", s.url + path, None)


def test_refusal_wording_names_the_role_with_its_article(quick_server, tmp_path):
    with pytest.raises(Rejected, match="HTTP 403: an engineer token may not do this"):
        upload_file(make_mcap(tmp_path / "a.mcap", "T1"), quick_server.url, quick_server.token("engineer"))
    with pytest.raises(Rejected, match="HTTP 403: a truck token may not do this"):
        request_json("GET", quick_server.url + "/api/v1/trucks", quick_server.token("truck", "T1"))


def test_a_request_body_trickling_past_the_request_deadline_gets_408(tmp_path):
    s = Server(tmp_path / "data", body_idle_timeout=1.0, request_timeout=2.0).start()
    try:
        token = s.token("truck", "T1")
        data = make_mcap(tmp_path / "a.mcap", "T1", seed=7).read_bytes()
        conn = put_headers(s, token, hashlib.sha256(data).hexdigest(), len(data))
        t0 = time.monotonic()
        stop, sock = threading.Event(), conn.sock  # the socket itself: reply() closes conn, which drops conn.sock

        def trickle():  # one byte every 0.5 s: never idle for 1 s, never complete
            for byte in data:
                if stop.wait(0.5):
                    return
                try:
                    sock.sendall(bytes([byte]))
                except OSError:  # the server closed the connection, or reply() did
                    return

        sender = threading.Thread(target=trickle, daemon=True)
        sender.start()
        status, body = reply(conn)
        stop.set()
        sender.join(5)
        assert status == 408 and "not complete within 2 s" in body["detail"]
        assert 1.9 < time.monotonic() - t0 < 4.0
        # what arrived stays for the resume
        assert request_json("GET", f"{s.url}/api/v1/uploads/{hashlib.sha256(data).hexdigest()}?size={len(data)}",
                            token)["offset"] > 0
    finally:
        s.stop()


def test_endless_headers_are_refused_with_431(quick_server):
    c = socket.create_connection(("127.0.0.1", quick_server.port), timeout=5)
    c.sendall(b"GET /api/v1/health HTTP/1.1\r\nHost: fleet\r\n")
    try:
        for k in range(200):  # 200 × 1 kB of headers, fast: the header deadline alone would allow them all
            c.sendall(f"X-Pad-{k}: {'a' * 1000}\r\n".encode())
    except (BrokenPipeError, ConnectionResetError):
        pass
    c.settimeout(5)
    try:
        assert c.recv(100).startswith(b"HTTP/1.1 431")
    except ConnectionResetError:  # the reset raced the reply: the connection is closed all the same
        pass
    c.close()


def test_a_stalled_json_body_gets_408_after_the_idle_deadline(quick_server):
    conn = http.client.HTTPConnection("127.0.0.1", quick_server.port, timeout=10)
    conn.putrequest("POST", "/api/v1/tokens")
    conn.putheader("Authorization", f"Bearer {quick_server.token('admin')}")
    conn.putheader("Content-Type", "application/json")
    conn.putheader("Content-Length", "100")
    conn.endheaders()
    conn.send(b'{"role": ')
    t0 = time.monotonic()
    status, body = reply(conn)
    assert status == 408 and "no byte of the request body for 2 s" in body["detail"]
    assert 1.9 < time.monotonic() - t0 < 3.5


def test_the_client_backs_off_on_429_with_growing_jittered_delays(tmp_path, monkeypatch):
    # one partial upload allowed per uploader, expiring 1.8 s after its last byte
    s = Server(tmp_path / "data", max_partial_uploads=1, partial_expiry_h=0.0005).start()
    try:
        token = s.token("truck", "T1")
        held = make_mcap(tmp_path / "held.mcap", "T1", seed=8).read_bytes()
        status, body = reply(half_put(s, token, held))
        assert (status, body["offset"]) == (202, len(held) // 2)
        puts = []
        real_request = upload_module.request

        def counting(method, url, *a, **kw):
            if method == "PUT":
                puts.append(time.monotonic())
            return real_request(method, url, *a, **kw)

        monkeypatch.setattr(upload_module, "request", counting)
        reply_ = upload_module.upload_with_retry(make_mcap(tmp_path / "next.mcap", "T1", seed=9), s.url, token,
                                                 deadline_s=20)
        assert reply_["status"] == "stored"
        gaps = [b - a for a, b in zip(puts, puts[1:])]
        assert 3 <= len(puts) <= 6, gaps  # 429 until the held partial expired (1.8 s), then stored
        assert gaps[0] >= 0.45 and all(b > 1.5 * a for a, b in zip(gaps, gaps[1:])), gaps
    finally:
        s.stop()


def test_empty_partial_uploads_left_in_the_data_directory_go_at_start(tmp_path):
    data = make_mcap(tmp_path / "a.mcap", "T1", seed=10).read_bytes()
    store = BlobStore(tmp_path / "data")
    for k in range(8):  # eight empty partial uploads of truck T1: its whole partial quota
        store.partial(f"{k:064x}", "T1").touch()
    s = Server(tmp_path / "data", max_partial_uploads=8).start()
    try:
        assert leftovers(s) == []
        assert upload_file(tmp_path / "a.mcap", s.url, s.token("truck", "T1"))["sha256"] == \
            hashlib.sha256(data).hexdigest()
    finally:
        s.stop()
