"""`fuelid identify` end to end as a user runs it, against the goal of 2 s for the shipped 1.5 h trip: the command in
a fresh process, wall clock and CPU time (user + system of the child, BLAS's threads included), `--no-cache`, with
its defaults (`--model auto --fuel-lag auto`: the held-out fits of both kinds on the fuel as logged, the kept kind's
with the fuel lag, then the model kept) and with the paper's linear model alone (`--model linear --fuel-lag 0`).

    .venv/bin/python benchmarks/bench_identify_command.py [--rounds 3] [--trips diesel_ident_90min map_ident_90min]

Trips: replay_logs/diesel_ident_90min (the paper's linear engine) and map_ident_90min (VECTO's 325 kW engine),
converted once by `fuelid convert` into benchmarks/.cache/dataset/; the model files go to a temporary directory.
The interpreter running this script runs the commands, with its own installation: the README's first command
installs fuelid without extras, and the `[mf4]` extra (in `[test]`) adds about 0.3 s to every command (python-can
then imports asammdf and pandas), so measure with an environment of `pip install -e .`. Imports are part of the
time (`python -X importtime -m fuelid.cli identify --help` shows them). The rounds alternate the variants; the
load average is printed with each run, since both figures move with what runs beside them.
"""
import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_dataset import converted_trip  # noqa: E402

GOAL_S = 2.0  # [s] the shipped 1.5 h trip, end to end, on a 2-core machine
VARIANTS = {"defaults": [], "linear alone": ["--model", "linear", "--fuel-lag", "0"]}


def timed(path: Path, options: list[str], out: Path) -> tuple[float, float]:
    """(wall clock, CPU) [s] of `fuelid identify PATH -o OUT --no-cache OPTIONS` in a child process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "fuelid.cli", "identify", str(path), "-o", str(out), "--no-cache",
                           *options], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd="/")
    wall = time.perf_counter() - t
    if done.returncode:
        raise SystemExit(f"fuelid identify {path.name} {' '.join(options)} failed: {done.stderr.strip()}")
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--rounds", type=int, default=3, help="runs of each trip and variant, alternating")
    p.add_argument("--trips", nargs="*", default=["diesel_ident_90min", "map_ident_90min"])
    args = p.parse_args()
    paths = {trip: converted_trip(trip) for trip in args.trips}
    times = {(trip, v): [] for trip in args.trips for v in VARIANTS}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(1, args.rounds + 1):
            for (trip, variant), runs in times.items():
                wall, cpu = timed(paths[trip], VARIANTS[variant], Path(tmp) / "model.json")
                runs.append((wall, cpu))
                print(f"round {k}  load {os.getloadavg()[0]:4.2f}  {trip:18s} {variant:13s} wall {wall:5.2f} s  "
                      f"CPU {cpu:5.2f} s", flush=True)
    print(f"\n{'trip':18s} {'variant':13s} {'wall [s]':>12s} {'CPU [s]':>12s}  median wall / {GOAL_S:g} s goal")
    for (trip, variant), runs in times.items():
        walls, cpus = [w for w, _ in runs], [c for _, c in runs]
        print(f"{trip:18s} {variant:13s} {min(walls):5.2f}–{max(walls):5.2f} {min(cpus):5.2f}–{max(cpus):5.2f}  "
              f"{statistics.median(walls) / GOAL_S:.2f}×")


if __name__ == "__main__":
    main()
