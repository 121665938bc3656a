"""The same numbers on every x86-64 CPU: which OpenBLAS kernels numpy and scipy run.

OpenBLAS (in numpy's and scipy's wheels) picks its kernels by CPU when it is loaded: AVX-512 ones (SkylakeX) on a
CPU that has AVX-512, AVX2 ones (Haswell) on AMD Zen and older Intel. The two sum the products of a matrix product
in a different order, so ΨᵀΨ, the LM step and every later iterate differ in the last bits; on the ill-conditioned
fits of real trips (condition numbers near 10¹⁴) the PEM's path and the minimum it ends in follow those bits, and
with them the diagnosis's verdicts on borderline cases. A fleet whose workers are mixed CPUs would then give the
same truck's data different models. So fuelid asks OpenBLAS for its Haswell kernels wherever the CPU runs them
(AVX2 and FMA), before numpy first loads it: `fuelid/__init__.py` calls `pin_kernels` on import. What it does
not reach: a process that imported numpy before fuelid keeps the kernels chosen then, and is warned (pinning
then would give scipy's OpenBLAS other kernels than numpy's: a third set of numbers); a CPU without AVX2; other
platforms (aarch64, macOS on Apple silicon), whose BLAS builds differ anyway.

And on any number of cores: fuelid's matrix products are N × d with d up to about a hundred, where BLAS threads
cost more time than they save (README), and OpenBLAS sums some products, long dot products among them, in another
order on several threads than on one. The fits, the validation's correlations and fit % and the diagnosis run in
`one_blas_thread()` (`in_one_blas_thread` for a whole function), so their numbers are a fleet worker's, which runs
one thread (fleet.jobs), on a laptop of any size.
"""
from __future__ import annotations

import functools
import os
import platform
import sys
import warnings
from collections.abc import MutableMapping

from threadpoolctl import ThreadpoolController

CORETYPE = "Haswell"  # OpenBLAS's AVX2 kernels: the ones it picks by itself on AMD Zen
NEEDS = frozenset({"avx2", "fma"})  # what those kernels execute
LATE = ("numpy was imported before fuelid, so OpenBLAS keeps the kernels it chose for this CPU: results may differ "
        "in the last bits from other machines' (import fuelid first; fuelid.blas)")


def cpu_flags(cpuinfo: str = "/proc/cpuinfo") -> frozenset[str]:
    """The CPU's feature flags as Linux lists them (empty where the file cannot be read: not Linux)."""
    try:
        with open(cpuinfo) as f:
            for line in f:
                if line.startswith("flags"):
                    return frozenset(line.partition(":")[2].split())
    except OSError:
        pass
    return frozenset()


def pin_kernels(environ: MutableMapping[str, str] = os.environ, machine: str | None = None,
                flags: frozenset[str] | None = None, numpy_loaded: bool | None = None) -> str | None:
    """Set OPENBLAS_CORETYPE to CORETYPE in `environ` on an x86-64 CPU with AVX2 and FMA, unless it is set already
    (the user's choice wins) or numpy is loaded already (a warning: too late); the core type in effect after the
    call (None: OpenBLAS chooses)."""
    machine = (machine or platform.machine()).lower()
    if "OPENBLAS_CORETYPE" not in environ and machine in ("x86_64", "amd64") \
            and NEEDS <= (cpu_flags() if flags is None else flags):
        too_late = "numpy" in sys.modules if numpy_loaded is None else numpy_loaded
        if too_late:
            warnings.warn(LATE, stacklevel=3)
        else:
            environ["OPENBLAS_CORETYPE"] = CORETYPE
    return environ.get("OPENBLAS_CORETYPE")


@functools.lru_cache(maxsize=1)
def _threadpools() -> ThreadpoolController:
    # built on first use, once numpy's and scipy's OpenBLAS are loaded (fuelid is imported before numpy), and once:
    # threadpoolctl scans the process's libraries each time a controller is built (1–2 ms)
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
