"""BLAS on one thread for fuelid's narrow matrix products: a speed choice.

The prediction-error fits, the validation's correlations and the diagnosis work on N × d matrices and long vectors,
d up to about a hundred, where OpenBLAS's threads cost more time than they save, by far on a busy machine (idle
threads spin). `python benchmarks/bench_blas_threads.py` times the PEM fit of the shipped 1.5 h trip with BLAS on
one thread and on two (docs/explanation/numerics.md has the figures). So the fits run in `one_blas_thread()`, and
whole functions in `in_one_blas_thread`. The number of threads changes no result beyond rounding.
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


def in_one_blas_thread(f):
    """f, run with BLAS on one thread (`one_blas_thread`)."""
    @functools.wraps(f)
    def in_one_thread(*args, **kwargs):
        with one_blas_thread():
            return f(*args, **kwargs)
    return in_one_thread
