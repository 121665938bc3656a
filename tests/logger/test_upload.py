"""The daemon's upload queue against a live fleet server (tests/fleet): it keeps its queue across restarts,
waits for the network with backoff, and deletes a local file only after the server confirmed it."""
import json
import time

from logger.upload import UploadQueue
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
