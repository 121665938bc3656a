"""Compile the online estimators' numba kernels (ident.rpem, ident.kalman) ahead of the first command.

The kernels are compiled on first use and cached (`cache=True`): in __pycache__ beside the installed modules,
or numba's user cache directory when the install is read-only, or $NUMBA_CACHE_DIR. A pip install cannot run
code after installing a wheel, so without this step the first `fuelid online` or `fuelid log --identify`
compiles (tens of seconds of CPU) and every later process loads the cache. `compile_estimators` runs every
estimator those commands build (RPEM from scratch and from a prior; the Kalman and gain trackers) on a few
samples, which compiles each kernel for the argument types they pass; `fuelid warmup` calls it, for an image or
CI step to run once after `pip install` (README, "Installing").
"""
from __future__ import annotations

import time

import numpy as np

from fuelid.ident.live import prior_estimator
from fuelid.ident.polymodel import Structure, parse_orders
from fuelid.ident.rpem import RPEM

WARMUP_SAMPLES = 200


def compile_estimators(orders: str = "paper", Ts: float = 0.3) -> float:
    """Run each online estimator over WARMUP_SAMPLES samples of random inputs [rpm, N·m] and fuel [L/h], so
    numba compiles and caches every kernel; returns the wall time [s] it took (a second or less when the cache
    was already there)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    u = np.column_stack([rng.uniform(600, 1800, WARMUP_SAMPLES), rng.uniform(0, 2000, WARMUP_SAMPLES)])
    y = 5 + 0.01 * u[:, 1] + rng.normal(0, 0.5, WARMUP_SAMPLES)
    scratch = RPEM(Structure(**parse_orders(orders)), Ts, u0=u.mean(axis=0), y0=float(y.mean()))
    scratch.update(u, y, np.ones(WARMUP_SAMPLES, bool), every=50)
    prior = scratch.model()
    for method in ("rpem", "kalman"):
        for adapt in ("gain", "all"):
            prior_estimator(prior, method=method, adapt=adapt).update(u, y, every=50)
    return time.perf_counter() - t0
