"""BLAS on one thread for fuelid's narrow matrix products: a speed choice.

The prediction-error fits factor N × d matrices with d up to about a hundred, chunk by chunk (ident.pem), where
OpenBLAS's threads cost more time than they save: `python benchmarks/bench_blas_threads.py` times the fit of the
shipped 1.5 h trip with BLAS on one thread and on every core (docs/explanation/numerics.md has the figures). The
fits run in `one_blas_thread()`; the number of threads changes no result beyond rounding.
"""
from __future__ import annotations

import functools

from threadpoolctl import ThreadpoolController


@functools.lru_cache(maxsize=1)
def _threadpools() -> ThreadpoolController:
    # built on first use, once numpy's and scipy's OpenBLAS are loaded, and once: threadpoolctl scans the
    # process's libraries each time a controller is built (1–2 ms)
    return ThreadpoolController()


def one_blas_thread():
    """A context in which BLAS (every BLAS library loaded when it is first used) runs on one thread."""
    return _threadpools().limit(limits=1, user_api="blas")
