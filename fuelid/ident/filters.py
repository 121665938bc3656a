"""lfilter: scipy.signal.lfilter(b, a, x), faster, by a compiled kernel for IIR filters of 1-D and 2-D data.

The prediction-error fits filter short polynomials (2–17 coefficients: D/(C F_i) with the paper's noise-model
orders) through 10⁴–10⁵ samples thousands of times (pem: u_i/F_i, x_i/F_i and B_i/F_i u_i in every
Levenberg–Marquardt trial), and there scipy's generic loop, which keeps the filter's state in memory, is most of
the time. `_iir.c` runs the same recursion (direct form II transposed, the same operations in the same order) with
the state in registers:

    y[t] = z₀ + b₀ x[t],   z_k ← (z_{k+1} + x[t] b_{k+1}) − y[t] a_{k+1},   z_{n−2} ← x[t] b_{n−1} − y[t] a_{n−1}

with b and a zero-padded to one length n ≤ MAX_TAPS and divided by a₀, from zero state — as scipy does; the
numbers agree with scipy's to rounding (tests/ident/test_filters.py). `lfilter_each` filters many 1-D signals, each
through its own filter and restarted at the starts of the data's segments: two of one filter length and segment
length go through the kernel side by side (`_iir.iir_pair`, the two halves of an SSE2 register), the pair in about
the time of one (pem's Jacobian filters 10–20 signals an iteration), each segment written in place. A FIR filter
of 1-D or 2-D data is scipy's own np.convolve(b / a₀, x) of each lane cut to its length, called directly (scipy
wraps it in a per-lane loop that costs as much as the convolution).
Everything else (more than two dimensions; complex data; longer filters) and an install built without a C compiler
go to scipy itself, imported on first use: `fuelid identify`, and the in-cab live estimator, which simulates models
through this module (ident.polymodel), do not load SciPy's signal package.
"""
from __future__ import annotations

import functools

import numpy as np

try:
    from fuelid.ident import _iir
except ImportError:  # built without a C compiler (the extension is optional): scipy's loop, slower
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
    """scipy.signal.lfilter(b, a, x, axis=axis) without initial conditions: y = B(q)/A(q) x
    (b, a the coefficients of B, A in powers of q⁻¹) along `axis` of x (1-D, or 2-D: each column or row alike),
    from zero state."""
    b, a, x = np.asarray(b), np.asarray(a), np.asarray(x)
    if _fir(b, a, x):  # scipy's own convolution, without its per-lane wrapper
        taps = b / a[0]
        if x.ndim == 1:
            return np.convolve(taps, x)[:x.size]
        full = np.apply_along_axis(lambda lane: np.convolve(taps, lane), axis, x)
        cut = [slice(None), slice(None)]
        cut[axis] = slice(x.shape[axis])
        return full[tuple(cut)]
    kernel = _kernel_form(b, a, x)
    if kernel is None:
        return _scipy_lfilter()(b, a, x, axis=axis)
    bn, an = kernel
    y = np.empty(x.shape)
    if x.ndim == 1:
        _iir.iir(bn, an, np.ascontiguousarray(x, dtype=np.float64), y)
        return y
    lanes = np.moveaxis(x, axis, -1)  # each 1-D lane filtered alike, as scipy does
    out = np.moveaxis(y, axis, -1)
    filtered = [np.empty(x.shape[axis]) for _ in range(len(lanes))]
    _through_kernel([(bn, an, np.ascontiguousarray(lane, dtype=np.float64), into)
                     for lane, into in zip(lanes, filtered)])
    for k, lane in enumerate(filtered):
        out[k] = lane
    return y


def lfilter_each(jobs, starts=(0,)) -> list[np.ndarray]:
    """[lfilter(b, a, x) for b, a, x in jobs] for 1-D signals x, each filter restarted from zero state at each index
    of `starts` (the segments' first samples, the first 0; every x as long as the others when there are several).
    IIR filters of one length through segments of one length run two at a time, side by side (`_iir.iir_pair`), in
    about the time of one."""
    jobs = [(np.asarray(b), np.asarray(a), np.asarray(x)) for b, a, x in jobs]
    if len(jobs) == 1 and len(starts) == 1:  # nothing to pair
        return [lfilter(*jobs[0])]
    out, through = [], []  # through: the IIR jobs' segments, each into its place in out
    for b, a, x in jobs:
        segments = [slice(lo, hi) for lo, hi in zip(starts, [*starts[1:], x.size])]
        form = _kernel_form(b, a, x) if x.ndim == 1 else None  # None for a FIR filter
        if form is None:
            pieces = [lfilter(b, a, x[s]) for s in segments]
            out.append(pieces[0] if len(pieces) == 1 else np.concatenate(pieces))
        else:
            x, y = np.ascontiguousarray(x, dtype=np.float64), np.empty(x.size)
            through += [(*form, x[s], y[s]) for s in segments]
            out.append(y)
    _through_kernel(through)
    return out


def _fir(b: np.ndarray, a: np.ndarray, x: np.ndarray) -> bool:
    """Whether lfilter(b, a, x) is a FIR filter of 1-D or 2-D float64 data, convolved lane by lane as scipy does."""
    return (1 <= x.ndim <= 2 and b.ndim == a.ndim == 1 and b.size >= 1 and a.size == 1 and a[0] != 0
            and np.result_type(b, a, x) == np.float64)


def _kernel_form(b: np.ndarray, a: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(b, a) zero-padded to one length n and divided by a₀, as scipy prepares them, when the compiled kernel
    takes lfilter(b, a, x) (an IIR filter of 2 ≤ n ≤ MAX_TAPS coefficients, real 1-D or 2-D data); else None."""
    n = max(b.size, a.size)
    if (_iir is None or not 1 <= x.ndim <= 2 or b.ndim != 1 or a.ndim != 1 or b.size < 1 or not 2 <= a.size
            or n > MAX_TAPS or a[0] == 0 or np.result_type(b, a, x) != np.float64):
        return None
    bn, an = np.zeros(n), np.zeros(n)
    bn[:b.size], an[:a.size] = b, a
    a0 = an[0]
    bn /= a0
    an /= a0
    return bn, an


def _through_kernel(jobs) -> None:
    """Each x of jobs [(b, a, x, y)] (b, a as `_kernel_form` returns them, x C-contiguous 1-D float64) through its
    filter into y (as long as x, C-contiguous) by the compiled kernel, two of one filter length and signal length
    side by side."""
    waiting = {}  # (filter length, signal length) → the job that waits for a partner
    for k, (b, a, x, y) in enumerate(jobs):
        j = waiting.pop((b.size, x.size), None)
        if j is None:
            waiting[b.size, x.size] = k
        else:
            _iir.iir_pair(*jobs[j], b, a, x, y)
    for k in waiting.values():
        _iir.iir(*jobs[k])
