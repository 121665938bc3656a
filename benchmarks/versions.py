"""Running one benchmark's worker under another version of fuelid: its own interpreter (e.g. main's checkout's
`.venv/bin/python`) runs the script with `--worker …` from outside any checkout, so it imports its own fuelid, on
one BLAS thread unless asked for more (the fits are narrow: threads only cost time). Each worker prints one JSON
line per result."""
from __future__ import annotations

import json
import os
import subprocess


def blas_threads_env(threads: int) -> dict[str, str]:
    """The environment variables that set how many threads BLAS (OpenBLAS, MKL, OpenMP) may run."""
    return {name: str(threads) for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}


def oe_iterations(info: dict) -> int:
    """The OE start's iterations in a model's info: by LM, then by variable projection (a version from before
    28 Nov records no projection: 0)."""
    counts = info["initialisation_iterations"]
    return counts["output_error"] + counts.get("output_error_projected", 0)


def worker_results(python: str, script: str, args: list[str], blas_threads: int = 1) -> list[dict]:
    """The JSON lines `python script args` prints, run from / with `blas_threads` BLAS threads."""
    out = subprocess.run([python, script, *args], capture_output=True, text=True, cwd="/",
                         env={**os.environ, **blas_threads_env(blas_threads)}, check=True).stdout
    return [json.loads(line) for line in out.splitlines()]
