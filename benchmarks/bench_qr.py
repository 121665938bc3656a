"""The triangular factor of the PEM's Jacobian chunks: LAPACK's dgeqrt (what ident.pem uses) against dgeqrf
(scipy.linalg.qr's), one thread, on chunks of [R̄; Ψ_k ε_k] as `ident.pem._triangular_factor` factors them.

    python benchmarks/bench_qr.py
    python benchmarks/bench_qr.py --columns 38 50 --rows 1024 2048 4096 --block 8 16 32

Columns: d + 1 for the paper's Box-Jenkins orders with the noise model (d = 37), for the engine model (d = 48), and
the initialisation's wide ARX regressors (a high-order ARX of 30 + 31 m columns: 92 and 186 for m = 2 and 5);
rows: the chunk (QR_CHUNK) plus the d + 1 rows of R̄. Time per sample [ns] (best of --repeat), and the ratio
dgeqrf / dgeqrt; the two factors agree to rounding (largest |ΔR| relative to max |R| printed). Memory: the chunk,
(d + 1 + QR_CHUNK) × (d + 1) numbers, whatever N.
"""
import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the fits run: one BLAS thread (fuelid.blas)

import numpy as np  # noqa: E402
from scipy.linalg import lapack, qr  # noqa: E402


def best(f, a: np.ndarray, repeat: int) -> float:
    """The fastest of `repeat` timings [s] of f on a fresh Fortran copy of a."""
    times = []
    for _ in range(repeat):
        x = np.array(a, order="F")
        t = time.perf_counter()
        f(x)
        times.append(time.perf_counter() - t)
    return min(times)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--columns", type=int, nargs="*", default=[38, 49, 64, 92, 186])
    p.add_argument("--rows", type=int, nargs="*", default=[2048])
    p.add_argument("--block", type=int, nargs="*", default=[8, 16, 32])
    p.add_argument("--repeat", type=int, default=30)
    args = p.parse_args()
    rng = np.random.default_rng(0)
    print("columns  chunk  dgeqrf ns/sample  " + "  ".join(f"dgeqrt nb={nb} ns/sample  ratio" for nb in args.block)
          + "  max |ΔR|/max |R|")
    for n in args.columns:
        for rows in args.rows:
            a = rng.standard_normal((rows + n, n)) * np.logspace(0, -6, n)  # columns of very different scales
            geqrf = best(lambda x: qr(x, mode="raw", overwrite_a=True, check_finite=False), a, args.repeat) / rows
            r_ref = np.abs(np.triu(qr(np.array(a, order="F"), mode="r", check_finite=False)[0][:n]))
            cells, diff = [], 0.0
            for nb in args.block:
                t = best(lambda x: lapack.dgeqrt(min(nb, n), x, overwrite_a=True), a, args.repeat) / rows
                r = np.abs(np.triu(lapack.dgeqrt(min(nb, n), np.array(a, order="F"))[0][:n]))
                diff = max(diff, float(np.max(np.abs(r - r_ref)) / np.max(r_ref)))
                cells.append(f"{t * 1e9:22.0f}  {geqrf / t:5.2f}")
            print(f"{n:7d}  {rows:5d}  {geqrf * 1e9:16.0f}  " + "  ".join(cells) + f"  {diff:17.1e}", flush=True)


if __name__ == "__main__":
    main()
