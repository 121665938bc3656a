"""The fleet server over loopback (a real uvicorn in a subprocess): uploads, refusals, tokens, registry, jobs,
and the `fuelid` client commands."""
import gzip
import itertools
import json
import os
import time
from pathlib import Path

import pytest
import sqlalchemy as sa
from mcap.writer import Writer

from fuelid.fleet import db
from fuelid.cli import main as fuelid
from fuelid.logger.upload import Rejected, UploadError, request, request_json, upload_file
from tests.fleet.conftest import Server, make_mcap

REPO = Path(__file__).resolve().parents[2]


def stored_state(s: Server) -> tuple[int, list, list]:
    """(file rows, blob files, partial uploads) of a server's data."""
    with s.engine.connect() as conn:
        rows = conn.execute(sa.select(sa.func.count()).select_from(db.files)).scalar()
    blobs = list((s.data_dir / "blobs").glob("*/*"))
    return rows, blobs, list((s.data_dir / "incoming").glob("*"))


def test_upload_is_content_addressed_idempotent_and_listed(server, tmp_path):
    token = server.token("truck", "TRUCK1")
    paths = [make_mcap(tmp_path / f"f{i}.mcap", "TRUCK1", seed=i) for i in range(2)]
    first = upload_file(paths[0], server.url, token)
    assert first["status"] == "stored" and first["truck"] == "TRUCK1"
    assert first["start_ns"] == 1_700_000_000 * 10**9 and first["messages"] == 20
    again = upload_file(paths[0], server.url, token)
    assert again["status"] == "already stored" and again["sha256"] == first["sha256"]
    second = upload_file(paths[1], server.url, token)
    rows, blobs, partial = stored_state(server)
    assert rows == 2 and sorted(b.name for b in blobs) == sorted([first["sha256"], second["sha256"]])
    assert partial == []
    assert (server.data_dir / "blobs" / first["sha256"][:2] / first["sha256"]).read_bytes() == paths[0].read_bytes()

    engineer = server.token("engineer")
    [truck] = request_json("GET", server.url + "/api/v1/trucks", engineer)
    assert truck == {"truck": "TRUCK1", "files": 2, "size_bytes": sum(p.stat().st_size for p in paths),
                     "start_ns": 1_700_000_000 * 10**9, "end_ns": 1_700_086_400 * 10**9 + 19 * 10**7,
                     "latest_model_version": None}
    files = request_json("GET", server.url + "/api/v1/trucks/TRUCK1/files", engineer)
    assert [(f["sha256"], f["size_bytes"]) for f in files] == [
        (first["sha256"], paths[0].stat().st_size), (second["sha256"], paths[1].stat().st_size)]


def test_tokens_and_roles(sqlite_server, tmp_path):
    s = sqlite_server
    admin, engineer, truck = s.token("admin"), s.token("engineer"), s.token("truck", "T1")
    f = make_mcap(tmp_path / "a.mcap", "T1")

    def status(method, path, token, payload=None):
        try:
            request_json(method, s.url + path, token, payload)
            return 200
        except Rejected as exc:
            return exc.status

    assert status("GET", "/api/v1/trucks", None) == 401
    assert status("GET", "/api/v1/trucks", "fuelid_wrong") == 401
    assert status("GET", "/api/v1/trucks", truck) == 403  # trucks upload, they do not read the registry
    assert status("POST", "/api/v1/tokens", engineer, {"role": "admin"}) == 403
    assert status("POST", "/api/v1/tokens", admin, {"role": "truck"}) == 422  # a truck token needs its truck
    with pytest.raises(Rejected, match="HTTP 403"):
        upload_file(f, s.url, engineer)
    with pytest.raises(Rejected, match="HTTP 403: this token uploads for truck T1 only"):
        upload_file(f, s.url, truck, truck="T2")
    new = request_json("POST", s.url + "/api/v1/tokens", admin, {"role": "truck", "truck": "T1", "name": "cab 7"})
    assert upload_file(f, s.url, new["token"])["status"] == "stored"
    assert request_json("DELETE", f"{s.url}/api/v1/tokens/{new['id']}", admin)["revoked_unix_s"] > 0
    assert status("GET", f"/api/v1/uploads/{'0' * 64}?size=1", new["token"]) == 401
    listed = request_json("GET", s.url + "/api/v1/tokens", admin)
    assert all("token" not in t and "token_sha256" not in t for t in listed)
    with s.engine.connect() as conn:  # only hashes are stored
        assert new["token"] not in str(conn.execute(sa.select(db.tokens)).all())


def _truncated(path):
    make_mcap(path, "T1", messages=200)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])


@pytest.mark.parametrize("case, status, message", [
    ("not_mcap", 422, "not an MCAP file"),
    ("truncated", 422, "truncated MCAP file"),
    ("oversized", 413, "exceeds the server's limit"),
    ("wrong_truck", 403, "the file is from truck T2, not T1"),
    ("no_truck", 422, "names no truck"),
    ("unchunked", 422, "messages but no chunk index"),
])
def test_bad_uploads_are_refused_and_nothing_is_stored(tmp_path, case, status, message):
    s = Server(tmp_path / "data", max_upload_mb=0.5).start()
    try:
        path = tmp_path / "x.mcap"
        if case == "not_mcap":
            path.write_bytes(os.urandom(5000))
        elif case == "truncated":
            _truncated(path)
        elif case == "oversized":
            make_mcap(path, "T1", messages=2000, payload_bytes=400)
            assert path.stat().st_size > 0.5 * 2**20
        elif case == "no_truck":
            make_mcap(path, "", messages=5)
        elif case == "unchunked":  # messages outside chunks: readable only by a sequential scan
            with open(path, "wb") as f:
                w = Writer(f, use_chunking=False)
                w.start()
                w.add_metadata("fuelid", {"truck": "T1"})
                w.add_message(w.register_channel("/can/raw", "json", 0), 1, b"{}", 1)
                w.finish()
        else:
            make_mcap(path, "T2")
        with pytest.raises(Rejected) as err:
            upload_file(path, s.url, s.token("truck", "T1"), chunk_bytes=1500)
        assert err.value.status == status and message in str(err.value)
        assert stored_state(s) == (0, [], [])
    finally:
        s.stop()


def test_converted_files_of_today_and_earlier_versions_are_accepted(sqlite_server, tmp_path, capsys):
    """Today's `convert` writes no chunk index (Foxglove's indexed reader refuses one without message
    indexes); the previous version wrote one. Both are complete, chunked files the jobs read chunk by chunk."""
    first = tmp_path / "first.log"
    with gzip.open(REPO / "replay_logs" / "sample_diesel_1min.log.gz", "rt") as f:
        first.write_text("".join(itertools.islice(f, 800)))
    converted = tmp_path / "converted.mcap"
    assert fuelid(["convert", str(first), "-o", str(converted)]) == 0
    token = sqlite_server.token("truck", "YS2R4X20007105543")
    for path in (converted, REPO / "tests" / "logger" / "data" / "convert_chunk_index_only.mcap"):
        stored = upload_file(path, sqlite_server.url, token)
        assert stored["status"] == "stored" and stored["messages"] == 1591


def test_an_upload_with_a_damaged_chunk_is_refused_with_422(tmp_path):
    """Hash and summary intact, one byte inside a compressed chunk flipped (as on a failing SD card)."""
    from mcap.reader import make_reader
    s = Server(tmp_path / "data").start()
    try:
        path = make_mcap(tmp_path / "x.mcap", "T1", messages=300)
        with open(path, "rb") as f:
            chunk = make_reader(f).get_summary().chunk_indexes[1]
        data = bytearray(path.read_bytes())
        data[chunk.chunk_start_offset + chunk.chunk_length - 20] ^= 0x01
        path.write_bytes(bytes(data))
        with pytest.raises(Rejected) as err:
            upload_file(path, s.url, s.token("truck", "T1"))
        assert err.value.status == 422 and "damaged MCAP file: chunk at bytes" in str(err.value)
        assert stored_state(s) == (0, [], [])
    finally:
        s.stop()


def test_upload_resumes_from_the_servers_offset_and_checks_the_hash(sqlite_server, tmp_path):
    s = sqlite_server
    token = s.token("truck", "T1")
    path = make_mcap(tmp_path / "a.mcap", "T1", messages=500, payload_bytes=64)
    data = path.read_bytes()
    digest = __import__("hashlib").sha256(data).hexdigest()
    put = f"{s.url}/api/v1/uploads/{digest}?size={len(data)}"
    status, body, _ = request("PUT", put + "&offset=0", token, data=data[:1000])
    assert status == 202 and json.loads(body)["offset"] == 1000
    with pytest.raises(Rejected) as err:  # a resend from the wrong place is refused with the right offset
        request("PUT", put + "&offset=500", token, data=data[500:900])
    assert err.value.status == 409 and err.value.body["offset"] == 1000
    assert upload_file(path, s.url, token)["status"] == "stored"
    # bytes that do not hash to the declared sha256 are dropped whole
    other = make_mcap(tmp_path / "b.mcap", "T1", seed=3).read_bytes()
    with pytest.raises(Rejected, match="HTTP 422: content hash"):
        request("PUT", f"{s.url}/api/v1/uploads/{'a' * 64}?size={len(other)}&offset=0", token, data=other)
    assert stored_state(s)[0] == 1 and stored_state(s)[2] == []


def test_refit_fetch_and_trucks_commands(sqlite_server, tmp_path, capsys, monkeypatch):
    s = sqlite_server
    monkeypatch.setenv("FUELID_SERVER", s.url)
    monkeypatch.setenv("FUELID_TOKEN", s.token("engineer"))
    for truck in ("T1", "BAD1"):
        upload_file(make_mcap(tmp_path / f"{truck}.mcap", truck), s.url, s.token("truck", truck))

    assert fuelid(["refit", "T1", "--wait", "20", "--json"]) == 0
    [job] = json.loads(capsys.readouterr().out)
    assert (job["status"], job["model_version"], job["reason"]) == ("done", 1, "request")
    assert fuelid(["refit", "--all", "--wait", "20"]) == 1  # BAD1's job fails
    out = capsys.readouterr().out  # no new data for T1: no duplicate version
    assert "BAD1: failed BAD1: too little valid data" in out and "T1: unchanged (no new data since model version 1)" in out
    upload_file(make_mcap(tmp_path / "T1b.mcap", "T1", seed=1), s.url, s.token("admin"))
    assert fuelid(["refit", "T1", "--wait", "20"]) == 0
    assert "T1: done model version 2" in capsys.readouterr().out
    upload_file(make_mcap(tmp_path / "SLOW1.mcap", "SLOW1"), s.url, s.token("truck", "SLOW1"))
    assert fuelid(["refit", "SLOW1", "--wait", "0.5"]) == 1  # a wait that times out is not success
    captured = capsys.readouterr()
    assert "SLOW1: running" in captured.out and "1 of 1 jobs still running after waiting 0.5 s" in captured.err

    assert fuelid(["fetch", "T1", "--version", "1", "-o", str(tmp_path / "m.json"),
                   "--report", str(tmp_path / "r.html"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["version"] == 1
    assert json.loads((tmp_path / "m.json").read_text()) == {"truck": "T1", "files": 1, "previous": False,
                                                              "names": ["T1.mcap"]}  # the uploaded names, not blobs
    assert "T1" in (tmp_path / "r.html").read_text()
    assert fuelid(["fetch", "T1", "-o", str(tmp_path / "latest.json")]) == 0
    assert "T1 model version 2" in capsys.readouterr().out
    assert json.loads((tmp_path / "latest.json").read_text())["previous"] is True

    assert fuelid(["trucks", "--json"]) == 0
    rows = {t["truck"]: t for t in json.loads(capsys.readouterr().out)}
    assert (rows["T1"]["files"], rows["T1"]["latest_model_version"]) == (2, 2)
    assert rows["BAD1"]["latest_model_version"] is None
    assert fuelid(["trucks", "T1"]) == 0
    assert "v2: fit (simulation) 92.0 %" in capsys.readouterr().out

    assert fuelid(["fetch", "T1", "--version", "9"]) == 1
    assert capsys.readouterr().err.strip() == ("fuelid fetch: error: HTTP 404: truck T1 has no model version 9 "
                                               "(/api/v1/trucks/T1/models/9/model.json)")


def test_new_data_starts_one_debounced_refit(tmp_path):
    s = Server(tmp_path / "data", refit_after=1.0).start()
    try:
        token = s.token("truck", "T1")
        for i in range(3):
            upload_file(make_mcap(tmp_path / f"{i}.mcap", "T1", seed=i), s.url, token)
        engineer = s.token("engineer")
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            jobs = request_json("GET", s.url + "/api/v1/jobs?truck=T1", engineer)
            if jobs and jobs[0]["status"] == "done":
                break
            time.sleep(0.2)
        assert [(j["reason"], j["status"], j["model_version"]) for j in jobs] == [("new data", "done", 1)]
        [model] = request_json("GET", s.url + "/api/v1/trucks/T1/models", engineer)
        assert model["metrics"]["fit_percent"]["simulation"] == 93.0 and model["n_samples"] == 300
    finally:
        s.stop()


def test_client_errors_are_one_line(sqlite_server, tmp_path, capsys):
    f = make_mcap(tmp_path / "a.mcap", "T1")
    port = sqlite_server.port
    sqlite_server.stop()
    assert fuelid(["upload", str(f), "--server", f"http://127.0.0.1:{port}", "--token", "x", "--retry-s", "0"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot reach server" in err and "Connection refused" in err
    assert fuelid(["trucks", "--server", "http://127.0.0.1:1"]) == 1
    assert capsys.readouterr().err == "fuelid trucks: error: no token: give --token TOKEN or set FUELID_TOKEN\n"


def test_token_command_offline_bootstraps_an_admin(tmp_path, capsys):
    d = str(tmp_path / "data")
    assert fuelid(["token", "create", "--data-dir", d, "--role", "admin", "--name", "ops"]) == 0
    secret = capsys.readouterr().out.strip()
    assert secret.startswith("fuelid_") and len(secret) > 40
    assert fuelid(["token", "create", "--data-dir", d, "--role", "truck", "--truck", "VIN 1"]) == 1
    assert "truck id 'VIN 1' must be" in capsys.readouterr().err
    assert fuelid(["token", "list", "--data-dir", d, "--json"]) == 0
    [t] = json.loads(capsys.readouterr().out)
    assert (t["role"], t["name"], t["revoked_unix_s"]) == ("admin", "ops", None)
    assert fuelid(["token", "revoke", str(t["id"]), "--data-dir", d]) == 0
    assert fuelid(["token", "revoke", str(t["id"]), "--data-dir", d]) == 1


def test_serve_refuses_an_unreachable_database_in_one_line(tmp_path, capsys):
    assert fuelid(["serve", "--data-dir", str(tmp_path), "--database-url",
                   "postgresql+psycopg://nobody@127.0.0.1:1/fuelid"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("fuelid serve: error: cannot start: ") and err.count("\n") == 1


def test_a_refusal_never_names_another_truck(sqlite_server, tmp_path):
    """A truck asking for a file another truck stored learns only that it is not its own."""
    s = sqlite_server
    path = make_mcap(tmp_path / "t2.mcap", "SECRETTRUCK2")
    stored = upload_file(path, s.url, s.token("truck", "SECRETTRUCK2"))
    t1 = s.token("truck", "T1")
    put = f"{s.url}/api/v1/uploads/{stored['sha256']}?size={path.stat().st_size}&offset=0"
    for attempt in (lambda: upload_file(path, s.url, t1), lambda: request("PUT", put, t1, data=path.read_bytes())):
        with pytest.raises(Rejected) as err:
            attempt()
        assert err.value.status == 403 and "another truck" in str(err.value)
        assert "SECRETTRUCK2" not in str(err.value) + json.dumps(err.value.body)


def test_partial_uploads_are_bounded_per_uploader_and_expire(tmp_path):
    s = Server(tmp_path / "data", max_partial_uploads=2, max_partial_mb=1, partial_expiry_h=1).start()
    try:
        t1, t2 = s.token("truck", "T1"), s.token("truck", "T2")
        files = {name: make_mcap(tmp_path / f"{name}.mcap", truck, seed=k)
                 for k, (name, truck) in enumerate([("a", "T1"), ("b", "T1"), ("c", "T1"), ("d", "T2")])}

        def start(name, token, size=None):
            """Send a file's first 100 bytes (made-up hashes would do as well); the HTTP status."""
            data = files[name].read_bytes()
            sha = __import__("hashlib").sha256(data).hexdigest()
            try:
                return request("PUT", f"{s.url}/api/v1/uploads/{sha}?size={size or len(data)}&offset=0", token,
                               data=data[:100])[0]
            except UploadError as exc:  # 429 is Unavailable: the uploader retries later
                assert "partial uploads" in str(exc)
                return exc.status

        assert [start("a", t1), start("b", t1), start("c", t1)] == [202, 202, 429]  # two at most per truck
        assert start("d", t2) == 202  # another truck's own quota
        upload_file(files["a"], s.url, t1)  # finishing one makes room
        assert start("c", t1) == 202
        s.stop()  # the partial uploads and their quota survive a restart...
        s.start()
        assert start("b", t2, size=2**20) == 429  # ...and bytes count: 100 B held + 1 MiB declared > 1 MiB
        held = sorted(p.stat().st_size for p in (s.data_dir / "incoming").glob("*.part"))
        assert held == [100, 100, 100]
        s.stop()
        for p in (s.data_dir / "incoming").glob("*.part"):  # untouched for 2 h: expired (limit 1 h)
            os.utime(p, (time.time() - 7200, time.time() - 7200))
        s.start()
        assert list((s.data_dir / "incoming").glob("*.part")) == []
        assert start("b", t1) == 202
    finally:
        s.stop()


def test_an_empty_file_is_refused_in_words(sqlite_server, tmp_path, capsys):
    """By the client before it sends anything, and by the server when asked: one line, no validation jargon."""
    s = sqlite_server
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    assert fuelid(["upload", str(empty), "--server", s.url, "--token", s.token("admin")]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.endswith("empty.mcap: an empty file (0 bytes) is not an MCAP recording; nothing to upload")
    with pytest.raises(Rejected) as refused:
        request("GET", f"{s.url}/api/v1/uploads/{'a' * 64}?size=0", s.token("admin"))
    assert refused.value.status == 422 and "an empty file (0 bytes) is not an MCAP recording" in str(refused.value)
