"""lfilter: scipy.signal.lfilter(b, a, x) to the bit, by a compiled kernel for IIR filters of 1-D and 2-D data.

The prediction-error fits filter short polynomials (2–17 coefficients: D/(C F_i) with the paper's noise-model
orders) through 10⁴–10⁵ samples thousands of times (pem: u_i/F_i, x_i/F_i and B_i/F_i u_i in every
Levenberg–Marquardt trial), and there scipy's generic loop, which keeps the filter's state in memory, is most of
the time. `_iir.c` runs the same recursion (direct form II transposed, the same operations in the same order) with
the state in registers:

    y[t] = z₀ + b₀ x[t],   z_k ← (z_{k+1} + x[t] b_{k+1}) − y[t] a_{k+1},   z_{n−2} ← x[t] b_{n−1} − y[t] a_{n−1}

with b and a zero-padded to one length n ≤ MAX_TAPS and divided by a₀, from zero state — as scipy does, so the
numbers are the same to the last bit (tests/ident/test_filters.py). Everything else (FIR filters, which scipy
computes by convolution; more than two dimensions; complex data; longer filters) and an install built without a C
compiler go to scipy itself, imported on first use so that the in-cab live estimator, which simulates models
through this module (ident.polymodel), does not load SciPy's signal package.
"""
from __future__ import annotations

import functools

import numpy as np

try:
    from fuelid.ident import _iir
except ImportError:  # built without a C compiler (the extension is optional): scipy's loop, the same numbers
    _iir = None

MAX_TAPS = 32  # the longest b, a the kernel takes (_iir.c)


@functools.cache
def _scipy_lfilter():
    from scipy.signal import lfilter as scipy_lfilter

    return scipy_lfilter


def compiled() -> bool:
    """Whether the compiled kernel is there (the install had a C compiler)."""
    return _iir is not None


def lfilter(b, a, x, axis: int = -1) -> np.ndarray:
    """scipy.signal.lfilter(b, a, x, axis=axis) without initial conditions, the same to the bit: y = B(q)/A(q) x
    (b, a the coefficients of B, A in powers of q⁻¹) along `axis` of x (1-D, or 2-D: each column or row alike),
    from zero state."""
    if _iir is not None:
        b, a, x = np.asarray(b), np.asarray(a), np.asarray(x)
        n = max(b.size, a.size)
        if (1 <= x.ndim <= 2 and b.ndim == a.ndim == 1 and 2 <= a.size and n <= MAX_TAPS and a[0] != 0
                and np.result_type(b, a, x) == np.float64):
            bn, an = np.zeros(n), np.zeros(n)
            bn[:b.size], an[:a.size] = b, a
            a0 = an[0]
            bn /= a0
            an /= a0
            y = np.empty(x.shape)
            if x.ndim == 1:
                _iir.iir(bn, an, np.ascontiguousarray(x, dtype=np.float64), y)
                return y
            lanes = np.moveaxis(x, axis, -1)  # each 1-D lane filtered alike, as scipy does
            out = np.moveaxis(y, axis, -1)
            for k in range(lanes.shape[0]):
                lane = np.empty(lanes.shape[1])
                _iir.iir(bn, an, np.ascontiguousarray(lanes[k], dtype=np.float64), lane)
                out[k] = lane
            return y
    return _scipy_lfilter()(b, a, x, axis=axis)
