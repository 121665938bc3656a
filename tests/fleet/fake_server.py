"""The fleet server as `fuelid serve` runs it, but with a stand-in job runner, for tests in a subprocess:

    python -m tests.fleet.fake_server --data-dir D --port P [--database-url URL] [--max-upload-mb MB]

The stand-in (FakeRunner) writes a small model.json and diagnosis.json per job in a thread instead of
identifying on Dask, so registry and job handling are tested in seconds; trucks named BAD* fail like
fleet.jobs.JobError does for unusable data, and trucks named SLOW* take 3 s.
"""
import argparse
import json
import resource
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from fuelid.fleet.app import MiB, Settings, create_app
from fuelid.fleet.limits import Timeouts, run_server


def fake_identify(truck: str, mcap_paths: list[str], out_dir: str, previous_model: str | None = None,
                  names: list[str] | None = None) -> dict:
    if truck.startswith("BAD"):
        raise RuntimeError(f"{truck}: too little valid data to identify 41 parameters")
    if truck.startswith("SLOW"):
        time.sleep(3.0)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "model.json").write_text(json.dumps({"truck": truck, "files": len(mcap_paths),
                                                "previous": previous_model is not None, "names": names}))
    (out / "diagnosis.json").write_text(json.dumps({"truck": truck, "verdict": "nothing missing"}))
    (out / "report.html").write_text(f"<html><body>{truck}</body></html>")
    return {"truck": truck, "model_path": str(out / "model.json"), "diagnosis_path": str(out / "diagnosis.json"),
            "report_path": str(out / "report.html"),
            "metrics": {"fit_percent": {"simulation": 90.0 + len(mcap_paths), "prediction": 99.0}, "rmse": 0.5,
                        "cycle_fuel_error_percent": {"mean": 0.1, "rms": 0.5}},
            "n_samples": 100 * len(mcap_paths), "duration_s": 30.0 * len(mcap_paths), "wall_s": 0.01,
            "top_effect": None}


class FakeRunner:
    def __init__(self):
        self.pool = ThreadPoolExecutor(2)

    def submit(self, truck, mcap_paths, out_dir, **kw):
        time.sleep(0.05)
        return self.pool.submit(fake_identify, truck, mcap_paths, out_dir, **kw)

    def close(self):
        self.pool.shutdown()


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--data-dir", required=True)
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--database-url")
    p.add_argument("--max-upload-mb", type=float, default=64)
    p.add_argument("--refit-after", type=float)
    p.add_argument("--max-partial-uploads", type=int, default=8)
    p.add_argument("--max-partial-mb", type=float)
    p.add_argument("--partial-expiry-h", type=float, default=168.0)
    p.add_argument("--header-timeout", type=float, default=10.0)
    p.add_argument("--body-idle-timeout", type=float, default=30.0)
    p.add_argument("--request-timeout", type=float, default=600.0)
    p.add_argument("--max-connections", type=int)
    p.add_argument("--open-files", type=int, help="the process's open-file limit (`ulimit -n`)")
    a = p.parse_args()
    if a.open_files:
        resource.setrlimit(resource.RLIMIT_NOFILE, (a.open_files, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))
    timeouts = Timeouts(header_s=a.header_timeout, body_idle_s=a.body_idle_timeout, request_s=a.request_timeout,
                        max_connections=a.max_connections)
    settings = Settings(data_dir=Path(a.data_dir), database_url=a.database_url,
                        max_upload_bytes=int(a.max_upload_mb * MiB), refit_after_s=a.refit_after,
                        max_partial_uploads=a.max_partial_uploads,
                        max_partial_bytes=int(a.max_partial_mb * MiB) if a.max_partial_mb else None,
                        partial_expiry_s=a.partial_expiry_h * 3600.0, timeouts=timeouts)
    run_server(create_app(settings, runner_factory=FakeRunner), "127.0.0.1", a.port, timeouts, "warning")


if __name__ == "__main__":
    main()
