"""Running one benchmark's worker under another version of fuelid: its own interpreter (e.g. main's checkout's
`.venv/bin/python`) runs the script with `--worker …` from outside any checkout, so it imports its own fuelid, on
one BLAS thread (the fits are narrow: threads only cost time). Each worker prints one JSON line per result."""
from __future__ import annotations

import json
import os
import subprocess

ONE_CORE_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def worker_results(python: str, script: str, args: list[str]) -> list[dict]:
    """The JSON lines `python script args` prints, run from / with one BLAS thread."""
    out = subprocess.run([python, script, *args], capture_output=True, text=True, cwd="/",
                         env={**os.environ, **ONE_CORE_ENV}, check=True).stdout
    return [json.loads(line) for line in out.splitlines()]
