"""The daemon's upload queue against a live fleet server (tests/fleet): it keeps its queue across restarts,
waits for the network with backoff, and deletes a local file only after the server confirmed it."""
import json
import time

from fuelid.ident.dataset import build_dataset
from fuelid.logger.columns import NAME
from fuelid.logger.mcap_log import read_attachments, read_messages
from fuelid.logger.upload import UploadQueue
from tests.fleet.conftest import Server, make_mcap


def wait_for(condition, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def test_queue_survives_a_restart_and_deletes_only_confirmed_files(tmp_path):
    server = Server(tmp_path / "data")  # not started yet: no network
    token = server.token("truck", "T1")
    spool = tmp_path / "spool"
    files = [make_mcap(tmp_path / f"{k}.mcap", "T1", seed=k) for k in range(3)]
    foreign = make_mcap(tmp_path / "foreign.mcap", "T2", seed=9)

    queue = UploadQueue(spool, server.url, token, "T1", delete_after_upload=True, initial_backoff_s=0.05,
                        max_backoff_s=0.2)
    for f in files + [foreign]:
        queue.enqueue(f)
    queue.enqueue(files[0])  # queued twice, uploaded once
    time.sleep(0.5)  # several failed tries against the closed port
    assert queue.status()["queued"] == 4 and "cannot reach server" in queue.status()["last_error"]
    queue.stop()
    journal = json.loads((spool / "upload-queue.json").read_text())
    assert journal["pending"] == [str(f) for f in files + [foreign]]
    assert all(f.exists() for f in files)

    server.start()  # the network is back; a new queue (the daemon restarted) finds the journal
    try:
        with UploadQueue(spool, server.url, token, "T1", delete_after_upload=True, initial_backoff_s=0.05) as q:
            wait_for(lambda: q.status()["queued"] == 0)
            status = q.status()
            assert (status["queued"], status["uploaded"], status["rejected"]) == (0, 3, 1)
        assert not any(f.exists() for f in files)  # confirmed, so deleted
        assert foreign.exists()  # refused by the server (another truck's file): kept, and said why
        [refused] = json.loads((spool / "upload-queue.json").read_text())["rejected"]
        assert refused["path"] == str(foreign) and "HTTP 403" in refused["error"]
        with server.engine.connect() as conn:
            assert conn.exec_driver_sql("SELECT count(*) FROM files").scalar() == 3
    finally:
        server.stop()


def test_queue_keeps_files_without_delete_after_upload(tmp_path):
    server = Server(tmp_path / "data").start()
    try:
        f = make_mcap(tmp_path / "a.mcap", "T1")
        with UploadQueue(tmp_path / "spool", server.url, server.token("truck", "T1"), "T1") as q:
            q.enqueue(f)
            wait_for(lambda: q.status()["uploaded"] == 1)
        assert f.exists()
    finally:
        server.stop()


def test_daemon_uploads_every_closed_file(tmp_path, capsys):
    from fuelid.cli import main
    from fuelid.logger.replay import replay
    from tests.logger import traffic
    from tests.logger.test_daemon import Running

    server = Server(tmp_path / "data").start()
    try:
        token_file = tmp_path / "truck.token"
        token_file.write_text(server.token("truck", traffic.VIN) + "\n")  # the truck is named by its VIN
        settings = dict(truck=traffic.VIN, rotate_s=0.5, upload_server=server.url, upload_token_file=token_file,
                        delete_after_upload=True)
        drive = tmp_path / "drive.log"
        traffic.write_candump(drive, 3.0)
        run = Running(tmp_path, "upload", **settings)
        replay([drive], run.tx, speed=4)
        wait_for(lambda: run.daemon.sink.closed_files >= 2 and run.daemon.uploads.status()["queued"] == 0)
        uploaded = run.daemon.uploads.status()["uploaded"]
        run.stop()  # closes the last file; the stopped queue keeps it in its journal
        logs = run.config.output_dir
        journal = json.loads((logs / "upload-queue.json").read_text())
        assert journal["pending"] == [str(p) for p in logs.glob("*.mcap")] and len(journal["pending"]) == 1
        assert run.status()["upload"]["uploaded"] == uploaded
        main(["status", "--status-file", str(run.config.status_file)])  # stopped: exit 1, still shows the queue
        assert f"upload:     1 queued, {uploaded} uploaded, 0 refused" in capsys.readouterr().out

        again = Running(tmp_path, "upload2", **settings)  # the next start sends what was left
        wait_for(lambda: again.daemon.uploads.status()["queued"] == 0)
        again.stop()
        with server.engine.connect() as conn:
            stored = conn.exec_driver_sql("SELECT count(*) FROM files").scalar()
        assert stored == uploaded + 1 and not journal["rejected"]
        journal = json.loads((logs / "upload-queue.json").read_text())  # now only the second run's own file
        assert journal["pending"] == [str(p) for p in logs.glob("*.mcap")] and len(journal["pending"]) == 1
    finally:
        server.stop()


def test_upload_needs_a_token(tmp_path, monkeypatch, capsys):
    from fuelid.cli import main

    monkeypatch.delenv("FUELID_TOKEN", raising=False)
    assert main(["log", "--interface", "virtual", "--output-dir", str(tmp_path), "--upload-server",
                 "http://127.0.0.1:9"]) == 1
    err = capsys.readouterr().err
    assert "token" in err and len(err.strip().splitlines()) == 1


def test_a_damaged_journal_is_set_aside_and_rebuilt_from_the_folder(tmp_path):
    from fuelid.logger.config import LoggerConfig
    from fuelid.logger.daemon import Daemon

    logs = tmp_path / "logs"
    logs.mkdir()
    files = [make_mcap(logs / f"fuelid-2026010{k}T000000.000Z.mcap", "T1", seed=k) for k in range(2)]
    damaged = b'{"version": 1, "pending": ["/x/a.mc'  # a write cut short on a file system without atomic rename
    (logs / "upload-queue.json").write_bytes(damaged)
    token = tmp_path / "token"
    token.write_text("fuelid_x\n")
    daemon = Daemon(LoggerConfig(interface="virtual", output_dir=logs, upload_server="http://127.0.0.1:9",
                                 upload_token_file=token))  # logging starts all the same
    try:
        assert daemon.uploads.pending == [str(f) for f in files]  # rebuilt from the closed files in the folder
        assert daemon.uploads.status()["journal_set_aside"].startswith(str(logs / "upload-queue.json.damaged"))
    finally:
        daemon.uploads.stop()
    [aside] = logs.glob("upload-queue.json.damaged*")
    assert aside.read_bytes() == damaged
    assert json.loads((logs / "upload-queue.json").read_text())["pending"] == [str(f) for f in files]


def test_a_failed_journal_write_is_retried_and_shown(tmp_path, monkeypatch):
    from fuelid.logger import upload

    disk = {"full": True}
    real = upload.write_atomic

    def write_atomic(path, data):
        if disk["full"]:
            raise OSError(28, "No space left on device")
        real(path, data)

    monkeypatch.setattr(upload, "write_atomic", write_atomic)
    server = Server(tmp_path / "data").start()
    try:
        files = [make_mcap(tmp_path / f"{k}.mcap", "T1", seed=k) for k in range(2)]
        with UploadQueue(tmp_path / "spool", server.url, server.token("truck", "T1"), "T1",
                         initial_backoff_s=0.05, max_backoff_s=0.1) as q:
            q.enqueue(files[0])  # the journal cannot be written: queued in memory all the same
            wait_for(lambda: q.status()["uploaded"] == 1)  # the upload thread survives its journal's failures
            q.enqueue(files[1])
            wait_for(lambda: q.status()["uploaded"] == 2)
            assert "No space left" in q.status()["journal_error"] and q._thread.is_alive()
            assert not (tmp_path / "spool" / "upload-queue.json").exists()
            disk["full"] = False  # space is back: the journal catches up
            wait_for(lambda: q.status()["journal_error"] is None)
            assert json.loads((tmp_path / "spool" / "upload-queue.json").read_text())["pending"] == []
    finally:
        server.stop()


def test_a_refused_token_holds_the_queue_until_a_new_token_is_installed(tmp_path):
    server = Server(tmp_path / "data").start()
    try:
        token_file = tmp_path / "token"
        token_file.write_text("fuelid_mistyped\n")
        files = [make_mcap(tmp_path / f"{k}.mcap", "T1", seed=k) for k in range(2)]
        with UploadQueue(tmp_path / "spool", server.url, lambda: token_file.read_text().strip(), None,
                         initial_backoff_s=0.05, max_backoff_s=0.1, token_check_s=0.05) as q:
            for f in files:
                q.enqueue(f)
            wait_for(lambda: q.status()["last_error"] is not None)
            time.sleep(0.3)
            status = q.status()
            assert "HTTP 401" in status["last_error"] and "new token" in status["last_error"]
            assert (status["queued"], status["rejected"]) == (2, 0)  # nothing refused for good: the token was
            token_file.write_text(server.token("truck", "T1") + "\n")  # the right token
            wait_for(lambda: q.status()["uploaded"] == 2)
            assert q.status()["last_error"] is None
    finally:
        server.stop()


def test_files_closed_before_the_vin_are_relabelled_and_uploaded(tmp_path):
    """The truck sends its VIN only after the first files were closed (named "unknown", refused by the
    VIN's token): once the VIN is seen, those files are relabelled and uploaded."""
    from tests.logger import traffic
    from tests.logger.test_daemon import Running

    server = Server(tmp_path / "data").start()
    try:
        token_file = tmp_path / "truck.token"
        token_file.write_text(server.token("truck", traffic.VIN) + "\n")
        msgs = traffic.frames(2.0)
        vin = [m for m in msgs if m.arbitration_id & 0x1FFFFF00 in (0x1CECFF00, 0x1CEBFF00)]
        others = [m for m in msgs if m not in vin]
        run = Running(tmp_path, "relabel", rotate_s=0.3, upload_server=server.url, upload_token_file=token_file)
        uploads = run.daemon.uploads
        try:
            for m in others[: len(others) // 2]:
                run.tx.send(m)
            wait_for(lambda: uploads.status()["rejected"] >= 1)  # a file named "unknown": 403
            assert "HTTP 403" in uploads.status()["last_error"]
            for m in vin + others[len(others) // 2:]:
                run.tx.send(m)
            wait_for(lambda: run.daemon.sink.recorder.vin == traffic.VIN)
            wait_for(lambda: run.daemon.sink.closed_files >= 3 and uploads.status()["queued"] == 0
                     and uploads.status()["rejected"] == 0)
            uploaded = uploads.status()["uploaded"]
        finally:
            run.stop()
        with server.engine.connect() as conn:
            trucks = [t for (t,) in conn.exec_driver_sql("SELECT truck FROM files").all()]
        assert len(trucks) == uploaded >= 3 and set(trucks) == {traffic.VIN}
        assert len(run.raw()) == len(msgs)  # relabelling kept every frame
        decoded = [f for f in sorted(run.config.output_dir.glob("*.mcap"))
                   if any(topic != "/can/raw" for topic, _, _ in read_messages(f))]
        assert decoded and all(read_attachments(f, NAME) for f in decoded)  # and the message columns
        build_dataset(decoded, fuel="lfe1")  # (they hold as many messages as the channels, or it raises)
    finally:
        server.stop()


def test_files_closed_while_the_journal_could_not_be_written_are_queued_at_the_next_start(tmp_path, monkeypatch):
    from fuelid.logger import upload

    spool = tmp_path / "logs"
    spool.mkdir()
    first = make_mcap(spool / "fuelid-20260101T000000.000Z.mcap", "T1", seed=1)
    queue = UploadQueue(spool, "http://127.0.0.1:9", "t", None, start=False)
    queue.enqueue(first)
    monkeypatch.setattr(upload, "write_atomic", lambda path, data: (_ for _ in ()).throw(OSError(28, "No space")))
    time.sleep(0.01)
    second = make_mcap(spool / "fuelid-20260101T010000.000Z.mcap", "T1", seed=2)
    queue.enqueue(second)  # the journal cannot say so; then the logger stops
    monkeypatch.undo()
    again = UploadQueue(spool, "http://127.0.0.1:9", "t", None, start=False)
    assert again.pending == [str(first), str(second)]
