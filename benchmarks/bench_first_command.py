"""The first `fuelid online` after an install, with and without `fuelid warmup`, against a warm cache, in one run.

    .venv/bin/python benchmarks/bench_first_command.py [--json]

The online estimators' numba kernels compile on first use and are cached (ident.warmup). Each case gets a fresh,
empty NUMBA_CACHE_DIR (a new install, CI runner or container) and runs, each command in a fresh process:
  cold     `fuelid online` on the shipped 1-minute sample (replay_logs/sample_diesel_1min, converted once into
           benchmarks/.cache/first/) — it compiles;
  warm     the same command again — it loads the cache;
  warmup   `fuelid warmup`, then `fuelid online` and `fuelid online --prior --method kalman` — neither compiles.
Reported: CPU seconds (user + system) and wall seconds of every command, and the load average before and after.
"""
import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CACHE = REPO / "benchmarks" / ".cache" / "first"
FUELID = [sys.executable, "-m", "fuelid.cli"]


def sample() -> tuple[Path, Path]:
    """The 1-minute sample as MCAP and a prior model identified on it (made once)."""
    mcap, prior = CACHE / "sample_diesel_1min.mcap", CACHE / "prior.json"
    if not prior.exists():
        CACHE.mkdir(parents=True, exist_ok=True)
        subprocess.run(FUELID + ["convert", str(REPO / "replay_logs" / "sample_diesel_1min.log.gz"), "-o", str(mcap),
                                 "--json"], check=True, stdout=subprocess.DEVNULL, cwd=REPO)
        subprocess.run(FUELID + ["identify", str(mcap), "--orders", "nb=2,2;nf=2,2;nk=3,0;nc=2;nd=2", "-o",
                                 str(prior)], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO)
    return mcap, prior


def timed(args: list[str], cache_dir: str) -> dict:
    """CPU [s] (user + system of the child) and wall time [s] of one fuelid command in a fresh process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(FUELID + args, check=True, stdout=subprocess.DEVNULL, cwd=REPO,
                   env={**os.environ, "NUMBA_CACHE_DIR": cache_dir})
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"command": "fuelid " + " ".join(args), "wall_s": time.perf_counter() - t0,
            "cpu_s": after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    mcap, prior = sample()
    online = ["online", str(mcap), "-o", os.devnull]
    load_before = os.getloadavg()
    runs = {}
    with tempfile.TemporaryDirectory() as first, tempfile.TemporaryDirectory() as warmed:
        runs["cold"] = timed(online, first)
        runs["warm"] = timed(online, first)
        runs["warmup"] = timed(["warmup"], warmed)
        runs["after warmup"] = timed(online, warmed)
        runs["after warmup, kalman"] = timed(online + ["--prior", str(prior), "--method", "kalman"], warmed)
    summary = {"load_average_before": load_before, "load_average_after": os.getloadavg(), "runs": runs,
               "cold_over_warm_cpu": runs["cold"]["cpu_s"] / runs["warm"]["cpu_s"]}
    if args.json:
        print(json.dumps(summary, indent=1))
        return
    print(f"load average before {load_before[0]:.2f}, after {summary['load_average_after'][0]:.2f}")
    print(f"{'case':22} {'CPU s':>7} {'wall s':>7}  command")
    for name, r in runs.items():
        print(f"{name:22} {r['cpu_s']:7.2f} {r['wall_s']:7.2f}  {r['command']}")
    print(f"cold / warm CPU: {summary['cold_over_warm_cpu']:.1f}×")


if __name__ == "__main__":
    main()
