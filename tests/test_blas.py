"""fuelid.blas: OpenBLAS's AVX2 kernels asked for on every x86-64 CPU that runs them, so that a model is the same
whichever machine identifies it."""
import json
import os
import subprocess
import sys

import pytest

from fuelid.blas import CORETYPE, NEEDS, cpu_flags, in_one_blas_thread, one_blas_thread, pin_kernels

import scipy.linalg  # noqa: E402, F401  (after fuelid: numpy's and scipy's OpenBLAS loaded, with its kernels)
from threadpoolctl import threadpool_info, threadpool_limits  # noqa: E402


def test_an_x86_64_cpu_with_avx2_gets_the_haswell_kernels():
    env = {}
    assert pin_kernels(env, "x86_64", frozenset({"sse2", "avx", "avx2", "fma", "avx512f"}), False) == "Haswell"
    assert env == {"OPENBLAS_CORETYPE": "Haswell"}


def test_too_late_once_numpy_is_loaded_and_the_user_is_told():
    """Pinned after numpy loaded its OpenBLAS, only scipy's would change: a third set of numbers."""
    env = {}
    with pytest.warns(UserWarning, match="numpy was imported before fuelid"):
        assert pin_kernels(env, "x86_64", NEEDS, True) is None
    assert env == {}


@pytest.mark.parametrize("machine, flags", [("x86_64", {"sse2", "avx"}), ("aarch64", {"fp", "asimd"}),
                                            ("x86_64", set())])
def test_other_cpus_keep_what_openblas_chooses(machine, flags):
    """No AVX2 (the kernels would not run), another architecture, or flags that cannot be read."""
    env = {}
    assert pin_kernels(env, machine, frozenset(flags), False) is None and env == {}


def test_a_core_type_the_user_set_is_kept():
    env = {"OPENBLAS_CORETYPE": "SkylakeX"}
    assert pin_kernels(env, "x86_64", NEEDS, True) == "SkylakeX" and env == {"OPENBLAS_CORETYPE": "SkylakeX"}


def test_cpu_flags_reads_the_flags_line(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: GenuineIntel\nflags\t\t: fpu sse2 avx2 fma\n\nprocessor\t: 1\n")
    assert cpu_flags(str(info)) == {"fpu", "sse2", "avx2", "fma"}
    assert cpu_flags(str(tmp_path / "absent")) == frozenset()


@pytest.mark.skipif(not NEEDS <= cpu_flags(), reason="this CPU does not run OpenBLAS's AVX2 kernels")
def test_importing_fuelid_first_loads_numpy_and_scipy_with_the_haswell_kernels():
    """A fresh process, as the command line and the fleet's workers start: every OpenBLAS loaded after `import
    fuelid` runs the kernels fuelid asked for, whatever this CPU would have chosen."""
    code = ("import fuelid, numpy, scipy.linalg, json; from threadpoolctl import threadpool_info; "
            "print(json.dumps([i.get('architecture') for i in threadpool_info() if i['internal_api'] == 'openblas']))")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_CORETYPE"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    found = json.loads(out.stdout)
    assert found and set(found) == {CORETYPE}, found


def test_one_blas_thread_runs_every_blas_on_one_thread_and_gives_the_threads_back():
    def blas_threads():
        return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]

    with threadpool_limits(limits=2, user_api="blas"):
        before = blas_threads()
        with one_blas_thread():
            assert blas_threads() and set(blas_threads()) == {1}
        assert blas_threads() == before
        assert in_one_blas_thread(blas_threads)() == [1] * len(before)
        assert in_one_blas_thread(blas_threads).__name__ == "blas_threads"
