"""The engine model against the paper's linear model on simulated map-engine trips: a quick table
(docs/explanation/engine-model.md). For each VECTO engine and seed: an identification trip (mixed cycle, SECONDS s)
and a validation trip of another day (another seed, 42 t), `fuelid simulate` → `fuelid convert`; the default model
(`fuelid identify`, --model auto) and the linear one (--model linear) identified on the first and simulated on the
second. Prints, per run, the RMS simulation error [L/h] and fit [%] of both on the validation trip, the choice
and the noise floor of the validation trip's truth (RMS of the measured minus the true fuel [L/h]).

    python benchmarks/engine_model_quick.py [--seeds 1 2 3] [--seconds 1800]
"""
import argparse
import contextlib
import io
import json
import tempfile
import time
import warnings
from pathlib import Path

import fuelid.blas  # noqa: F401  (before numpy: fuelid's BLAS kernels)
import numpy as np

from fuelid.cli import main
from fuelid.ident.dataset import build_dataset
from fuelid.ident.modelchoice import ModelKind, identify_chosen
from fuelid.ident.polymodel import PAPER_ORDERS, Structure
from fuelid.ident.validation import evaluate

ENGINES = {"325 kW": "vecto_325kW",
           "220 kW": str(Path(__file__).resolve().parents[2] / "shared/engines/vecto_220kW_7.7l")}


def engine_file(name: str) -> str:
    p = Path(name)
    return str(next(p.glob("*.veng"))) if p.is_dir() else name


def trip(d: Path, name: str, engine: str, seed: int, seconds: float, mass: float) -> tuple[Path, float]:
    log = d / f"{name}.log.gz"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["simulate", "--engine", engine_file(engine), "--cycle", "mixed", "--duration", str(seconds),
                     "--seed", str(seed), "--mass", str(mass), "-o", str(log)]) == 0
        assert main(["convert", str(log), "-o", str(d / f"{name}.mcap")]) == 0
    z = np.load(d / f"{name}.truth.npz")
    return d / f"{name}.mcap", float(np.sqrt(np.mean((z["fuel_measured"] - z["fuel_true"]) ** 2)))


def main_(seeds, seconds):
    warnings.simplefilter("ignore")
    S = Structure(**PAPER_ORDERS)
    print("| engine | seed | chosen | held-out gain | auto RMS L/h | auto fit % | linear RMS L/h | linear fit % | floor L/h | identify CPU s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    for label, engine in ENGINES.items():
        for seed in seeds:
            with tempfile.TemporaryDirectory() as tmp:
                d = Path(tmp)
                ident, _ = trip(d, "ident", engine, seed, seconds, 40000)
                valid, floor = trip(d, "valid", engine, 1000 + seed, seconds * 2 / 3, 42000)
                ds, dv = build_dataset([ident]), build_dataset([valid])
                c0 = time.process_time()
                auto = identify_chosen(ds, S, min_segment_s=30.0)
                cpu = time.process_time() - c0
                linear = identify_chosen(ds, S, kind=ModelKind.LINEAR, min_segment_s=30.0)
                a, li = evaluate(auto, dv), evaluate(linear, dv)
                ch = auto.info["model_choice"]
                gain = ch["held_out"]["improvement_mean"] if ch["held_out"] else float("nan")
                row = (label, seed, ch["chosen"], gain, a["rmse"]["simulation"], a["fit_percent"]["simulation"],
                       li["rmse"]["simulation"], li["fit_percent"]["simulation"], floor, cpu)
                rows.append(row)
                print("| {} | {} | {} | {:+.0%} | {:.2f} | {:.1f} | {:.2f} | {:.1f} | {:.2f} | {:.1f} |".format(*row),
                      flush=True)
    r = np.array([x[4:8] for x in rows], float)
    print(f"mean over {len(rows)} runs: auto RMS {r[:, 0].mean():.2f} ± {r[:, 0].std(ddof=1):.2f} L/h, fit "
          f"{r[:, 1].mean():.1f} %; linear RMS {r[:, 2].mean():.2f} ± {r[:, 2].std(ddof=1):.2f} L/h, fit "
          f"{r[:, 3].mean():.1f} %")


if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    p.add_argument("--seconds", type=float, default=1800.0)
    a = p.parse_args()
    main_(a.seeds, a.seconds)
