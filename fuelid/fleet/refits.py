"""Identification jobs of the fleet server: one per truck at a time, run by `fleet.jobs.JobRunner` on Dask.

A job is asked for by an engineer (`reason` "request"), by a fleet-wide refit ("fleet") or by new data: each
upload pushes the truck's due time to `refit_after_s` [s] later (debounce), so a truck sending a day's files
gets one job after its last file, not one per file. A finished job's model.json, diagnosis.json and
report.html go into the blob store and become the truck's next model version; a failed job keeps its
one-line error. The runner (a Dask LocalCluster unless a scheduler address is given) starts on the first job.
"""
from __future__ import annotations

import logging
import shutil
import threading
import time
from pathlib import Path
from typing import Callable

import sqlalchemy as sa

from fuelid.fleet import db
from fuelid.fleet.storage import BlobStore

log = logging.getLogger("fuelid.fleet")


def dask_runner_factory(scheduler: str | None, n_workers: int | None) -> Callable[[], object]:
    """A factory of the production runner (imported on first use: Dask is slow to import, and fleet.jobs brings
    the identification stack, numba and SciPy, which the server process itself never runs)."""

    def make():
        from fuelid.fleet.jobs import JobRunner

        return JobRunner(scheduler=scheduler, n_workers=n_workers)

    return make


def newest_files(files: list[dict], window_s: float) -> list[dict]:
    """The newest of `files` (ordered by start time) holding at most `window_s` [s] of recorded time, in time
    order: the model follows the truck as it is now, not its whole history. The newest file is always taken."""
    chosen, total_s = [], 0.0
    for f in reversed([f for f in files if f["start_ns"] is not None]):
        total_s += (f["end_ns"] - f["start_ns"]) / 1e9
        if chosen and total_s > window_s:
            break
        chosen.append(f)
    return chosen[::-1]


class RefitManager:
    """Submits identification jobs and records their outcome.

    `runner_factory()` returns an object with `.submit(truck, mcap_paths, out_dir, **kw)` giving a future
    (`add_done_callback`, `result`) and `.close()` — fleet.jobs.JobRunner, or a stand-in in tests.
    `refit_after_s` None turns off refits on new data."""

    def __init__(self, engine: sa.Engine, store: BlobStore, work_dir: Path, runner_factory: Callable[[], object],
                 refit_after_s: float | None = None, window_s: float = 24 * 3600.0):
        self.engine, self.store, self.work_dir = engine, store, Path(work_dir)
        self.refit_after_s, self.window_s = refit_after_s, window_s
        self._runner_factory = runner_factory
        self._runner = None
        self._lock = threading.Lock()
        self._due: dict[str, float] = {}  # truck -> monotonic time its debounced refit starts
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._debounce_loop, name="fuelid-refit", daemon=True)
        self._thread.start()

    def request(self, truck: str, reason: str) -> dict:
        """Start a job for `truck` unless one is queued or running (that one is returned), or unless its latest
        model was identified on exactly the files a job would take now: then a job with status "unchanged" and
        that model's version says so, and no duplicate version is made."""
        with self._lock:
            active = db.list_jobs(self.engine, truck=truck, active_only=True, limit=1)
            if active:
                return active[0]
            job = db.create_job(self.engine, truck, reason)
            latest = db.get_model(self.engine, truck, None)
            files = [f["sha256"] for f in newest_files(db.list_files(self.engine, truck), self.window_s)]
            if latest is not None and latest["metrics"].get("files_sha256") == files:
                db.update_job(self.engine, job["id"], status="unchanged", model_version=latest["version"],
                              started_unix_s=time.time(), finished_unix_s=time.time())
                return db.get_job(self.engine, job["id"])
        try:
            self._submit(job)
        except Exception as exc:  # no runner (Dask missing, scheduler unreachable): the job fails, said why
            self._fail(job["id"], f"could not start the job: {exc}")
        return db.get_job(self.engine, job["id"])

    def data_arrived(self, truck: str) -> None:
        """New file for `truck`: (re)start its debounce timer."""
        if self.refit_after_s is not None:
            with self._lock:
                self._due[truck] = time.monotonic() + self.refit_after_s

    def _debounce_loop(self) -> None:
        while not self._stop.wait(0.5):
            now = time.monotonic()
            with self._lock:
                due = [t for t, at in self._due.items() if at <= now]
                for t in due:
                    del self._due[t]
            for truck in due:
                self.request(truck, "new data")

    def _runner_instance(self):
        with self._lock:
            if self._runner is None:
                self._runner = self._runner_factory()
            return self._runner

    def _submit(self, job: dict) -> None:
        truck = job["truck"]
        files = newest_files(db.list_files(self.engine, truck), self.window_s)
        paths = [str(self.store.path(f["sha256"])) for f in files]
        latest = db.get_model(self.engine, truck, None)
        previous = str(self.store.path(latest["model_sha256"])) if latest else None
        out_dir = self.work_dir / f"job-{job['id']}"
        runner = self._runner_instance()
        db.update_job(self.engine, job["id"], status="running", started_unix_s=time.time())
        future = runner.submit(truck, paths, str(out_dir), previous_model=previous,
                               names=[f["name"] or f["sha256"] for f in files])
        sha256s = [f["sha256"] for f in files]
        future.add_done_callback(lambda fut: self._finished(job["id"], truck, out_dir, fut, sha256s))

    def _fail(self, job_id: int, error: str) -> None:
        db.update_job(self.engine, job_id, status="failed", error=error, finished_unix_s=time.time())

    def _finished(self, job_id: int, truck: str, out_dir: Path, future, files_sha256: list[str]) -> None:
        try:
            result = future.result()
            report = result.get("report_path")
            db.add_model(
                self.engine, truck=truck, job_id=job_id,
                model_sha256=self.store.put_file(result["model_path"]),
                diagnosis_sha256=self.store.put_file(result["diagnosis_path"]),
                report_sha256=self.store.put_file(report) if report else None,
                metrics={**result.get("metrics", {}), "files_sha256": files_sha256}, n_samples=result.get("n_samples"),
                duration_s=result.get("duration_s"), top_effect=result.get("top_effect"))
        except Exception as exc:  # JobError (unusable data) or a worker failure: one line on the job
            message = " ".join(str(exc).split()) or type(exc).__name__
            log.warning("refit of %s (job %d) failed: %s", truck, job_id, message)
            self._fail(job_id, message)
        finally:
            shutil.rmtree(out_dir, ignore_errors=True)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        with self._lock:
            runner, self._runner = self._runner, None
        if runner is not None:
            runner.close()
