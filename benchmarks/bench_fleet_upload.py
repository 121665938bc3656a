"""Fleet upload throughput on loopback: uploads per second and MB/s through `fuelid serve` (SQLite, default
settings but no refits) with the trucks' own client (logger.upload.upload_file), several clients at once.

    .venv/bin/python benchmarks/bench_fleet_upload.py [--small 200] [--large 6] [--clients 4]

Files: small ≈ 90 kB and large ≈ 20 MB MCAP logs (random CAN payloads at 100 frames/s, one chunk per second of
log time as the daemon writes them), each of its own truck; every upload is a new file: hash, status query,
8 MiB PUTs, server-side sha256, MCAP check, fsync, rename, database row. For scale, the script also prints the
rate of copying the large files on the same disk with an fsync each, the floor any upload path pays. Client
and server share the machine's two cores.
"""
import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fuelid.fleet import auth, db  # noqa: E402
from fuelid.logger.upload import upload_file  # noqa: E402
from tests.fleet.conftest import free_port, make_mcap  # noqa: E402


def serve(data_dir: Path, port: int) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "fuelid.cli", "serve", "--data-dir", str(data_dir), "--port",
                             str(port), "--no-auto-refit", "--max-upload-mb", "64", "--log-level", "warning"])
    for _ in range(300):
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/api/v1/health", timeout=1)
            return proc
        except OSError:
            time.sleep(0.1)
    raise SystemExit("server did not start")


def run_uploads(url: str, jobs: list[tuple[Path, str]], clients: int) -> tuple[float, int]:
    """(wall time [s], bytes) of uploading every (file, token) with `clients` threads."""
    t0 = time.perf_counter()
    with ThreadPoolExecutor(clients) as pool:
        replies = list(pool.map(lambda job: upload_file(job[0], url, job[1]), jobs))
    wall = time.perf_counter() - t0
    assert all(r["status"] == "stored" for r in replies)
    return wall, sum(p.stat().st_size for p, _ in jobs)


def copy_rate(files: list[Path], out: Path) -> float:
    """MB/s of copying the files on the same disk with an fsync each."""
    t0 = time.perf_counter()
    for k, f in enumerate(files):
        dst = out / f"copy{k}"
        shutil.copyfile(f, dst)
        with open(dst, "rb+") as fh:
            os.fsync(fh.fileno())
    return sum(f.stat().st_size for f in files) / 1e6 / (time.perf_counter() - t0)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", type=int, default=200, help="number of ≈90 kB files")
    ap.add_argument("--large", type=int, default=6, help="number of ≈20 MB files")
    ap.add_argument("--clients", type=int, default=4, help="concurrent uploading clients")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        engine = db.open_database(tmp / "data")
        groups = {"small": (args.small, 600, 100), "large": (args.large, 140_000, 100)}  # messages, payload B
        jobs = {}
        for name, (n, messages, payload) in groups.items():
            jobs[name] = []
            for k in range(n):
                truck = f"{name.upper()}{k:04d}"
                path = make_mcap(tmp / f"{truck}.mcap", truck, seed=k, messages=messages, payload_bytes=payload)
                jobs[name].append((path, auth.create_token(engine, "truck", truck)["token"]))
        engine.dispose()
        port = free_port()
        proc = serve(tmp / "data", port)
        try:
            print(f"{'files':<6} {'n':>4} {'mean size':>10} {'clients':>7} {'uploads/s':>10} {'MB/s':>8}")
            for name, batch in jobs.items():
                wall, nbytes = run_uploads(f"http://127.0.0.1:{port}", batch, args.clients)
                print(f"{name:<6} {len(batch):>4} {nbytes / len(batch) / 1e6:>8.2f} MB {args.clients:>7} "
                      f"{len(batch) / wall:>10.1f} {nbytes / 1e6 / wall:>8.1f}")
        finally:
            proc.terminate()
            proc.wait()
        print(f"reference: local copy + fsync of the large files {copy_rate([p for p, _ in jobs['large']], tmp):.0f} MB/s")


if __name__ == "__main__":
    main()
