"""fuelid.blas: the fits' BLAS on one thread (a speed choice), the threads given back afterwards."""
import numpy as np
from threadpoolctl import threadpool_info, threadpool_limits

from fuelid.blas import in_one_blas_thread, one_blas_thread


def blas_threads():
    return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]


def test_one_blas_thread_runs_every_blas_on_one_thread_and_gives_the_threads_back():
    np.ones((2, 2)) @ np.ones((2, 2))  # numpy's OpenBLAS loaded
    with threadpool_limits(limits=2, user_api="blas"):
        before = blas_threads()
        with one_blas_thread():
            assert blas_threads() and set(blas_threads()) == {1}
        assert blas_threads() == before
        assert in_one_blas_thread(blas_threads)() == [1] * len(before)
        assert in_one_blas_thread(blas_threads).__name__ == "blas_threads"
        assert blas_threads() == before
