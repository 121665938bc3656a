"""The nuisance bases the diagnosis tests its candidates against (ident.diagnosis.statistics.nuisance_basis): made by
Cholesky QR twice where the columns allow it, against QR with column pivoting (the way every basis was made before).

    python benchmarks/bench_nuisance_basis.py                                  # the map engine's 90-min fan trip
    python benchmarks/bench_nuisance_basis.py --effect dpf_regeneration --seed 7 --truth map

The bases are those `run_gradients` makes for the model as it is and for the model with the engine's map term (the
prediction-error gradient's and the simulation gradient's, each beside its segments' initial states): per basis, the
dense columns through every segment (N × k), the time to make their part of the basis each way (best of 5, one BLAS
thread, as the diagnosis makes them; both include projecting the initial states' blocks out), the peak memory each
allocates (tracemalloc, which sees numpy's and LAPACK's work arrays), the smallest singular value of the unit-scaled
columns (fuelid takes Cholesky QR twice from 10 × RANK_TOL on, when its first pass comes near enough to orthonormal)
and the largest difference of the two projections of random unit columns.
"""
import argparse
import sys
import time
import tracemalloc
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fuelid.blas import one_blas_thread  # noqa: E402  (fuelid before numpy: fuelid.blas)
from fuelid.ident.diagnosis import run as run_module  # noqa: E402
from fuelid.ident.diagnosis import statistics  # noqa: E402
from fuelid.ident.modelrun import run_model  # noqa: E402
from tests.ident import hidden  # noqa: E402

import numpy as np  # noqa: E402
from scipy.linalg import svdvals  # noqa: E402


def nuisance_columns(model, ds) -> list[tuple[np.ndarray, list]]:
    """(Z, the segments' columns) of each nuisance basis run_gradients makes for `model` on ds."""
    made = []

    def recording(Z, segment_columns=()):
        made.append((Z, list(segment_columns)))
        return statistics.nuisance_basis(Z, segment_columns)

    run_module.nuisance_basis = recording
    try:
        run_module.run_gradients(run_model(model, ds))
    finally:
        run_module.nuisance_basis = statistics.nuisance_basis
    return made


def pivoted_extended(blocks: statistics.NuisanceBasis, Z: np.ndarray) -> np.ndarray:
    """The peer: the dense part of the basis of `blocks` and Z by QR with column pivoting, cut at RANK_TOL
    (fuelid's way when the columns do not allow Cholesky QR)."""
    norms = np.linalg.norm(Z, axis=0)
    return statistics.pivoted_qr_columns(blocks.project_out(Z) / np.where(norms > 0, norms, 1.0), statistics.RANK_TOL)


def timed(f, *args, repeat: int = 5) -> tuple[float, int, np.ndarray]:
    """(least wall time [s] of `repeat` calls, peak memory [bytes] one call allocates, its result)."""
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        out = f(*args)
        best = min(best, time.perf_counter() - t)
    tracemalloc.start()
    f(*args)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return best, peak, out


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--effect", default="engine_fan", help="the effect the trip hides (tests/ident/hidden.py)")
    p.add_argument("--seed", type=int, default=3006)
    p.add_argument("--minutes", type=float, default=90.0)
    p.add_argument("--truth", default="map", help="the engine's fuel truth: map or diesel_p320")
    a = p.parse_args()
    warnings.simplefilter("ignore")
    ds, _, _ = hidden.simulated(a.effect, a.seed, a.minutes * 60.0, truth=a.truth)
    models = {"as it is": hidden.identify(ds), "with engine_map": hidden.identify(ds, effects=["engine_map"])}
    rng = np.random.default_rng(0)
    print(f"{'model':16s} {'basis':22s} {'N × k':>12s} {'pivoted QR [ms]':>16s} {'Cholesky QR² [ms]':>18s} "
          f"{'ratio':>6s} {'peak [MB] piv / chol':>21s} {'σ_min':>9s} {'projection diff':>16s}")
    total = {"pivoted": 0.0, "cholesky": 0.0}
    for name, model in models.items():
        for which, (Z, segment_columns) in zip(("prediction error (Q)", "simulation (QG)"),
                                               nuisance_columns(model, ds)):
            with one_blas_thread():
                blocks = statistics.nuisance_basis(Z[:, :0], segment_columns)
                t_piv, m_piv, dense_piv = timed(pivoted_extended, blocks, Z)
                t_chol, m_chol, basis = timed(blocks.extended, Z)
            norms = np.linalg.norm(Z, axis=0)
            sigma_min = svdvals(blocks.project_out(Z) / np.where(norms > 0, norms, 1.0))[-1]
            X = rng.normal(size=(Z.shape[0], 4)) / np.sqrt(Z.shape[0])
            diff = np.abs((X - dense_piv @ (dense_piv.T @ X)) - (X - basis.dense @ (basis.dense.T @ X))).max()
            total["pivoted"] += t_piv
            total["cholesky"] += t_chol
            print(f"{name:16s} {which:22s} {f'{Z.shape[0]} × {Z.shape[1]}':>12s} {1e3 * t_piv:16.1f} "
                  f"{1e3 * t_chol:18.1f} {t_chol / t_piv:5.2f}× {f'{m_piv / 2**20:.0f} / {m_chol / 2**20:.0f}':>21s} "
                  f"{sigma_min:9.1e} {diff:16.1e}", flush=True)
    print(f"all four: pivoted QR {1e3 * total['pivoted']:.0f} ms, Cholesky QR twice {1e3 * total['cholesky']:.0f} ms "
          f"({total['cholesky'] / total['pivoted']:.2f}×)")


if __name__ == "__main__":
    main()
