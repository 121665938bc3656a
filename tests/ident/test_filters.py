"""ident.filters: scipy.signal.lfilter to rounding, by the compiled IIR kernel (fuelid/ident/_iir.c) where it
applies and by scipy itself elsewhere."""
import shutil

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.signal import lfilter as scipy_lfilter

from fuelid.ident import filters

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)


def agree(x, y) -> bool:
    """Same shape and type, the same numbers to rounding (1e-9 of the largest: the filters' poles reach |z| = 0.99,
    which amplifies rounding by up to a hundred)."""
    x, y = np.asarray(x), np.asarray(y)
    scale = float(np.abs(y).max()) if y.size else 0.0
    return x.shape == y.shape and x.dtype == y.dtype and np.allclose(x, y, rtol=1e-9, atol=1e-9 * max(scale, 1e-300))


@st.composite
def stable_filters(draw, max_taps: int = filters.MAX_TAPS):
    """(b, a): a with real roots and complex-conjugate pairs inside |z| < 0.99 and a₀ not always 1, b any length up
    to max_taps."""
    roots = []
    while not roots or draw(st.booleans()) and len(roots) < max_taps - 2:
        r, phi = draw(st.floats(0.0, 0.99)), draw(st.floats(0.0, np.pi))
        roots += [r * np.exp(1j * phi), r * np.exp(-1j * phi)] if draw(st.booleans()) else [r * np.cos(phi)]
    a = np.real(np.poly(roots)) * draw(st.sampled_from([1.0, 2.5, -0.7]))
    b = np.array(draw(st.lists(finite, min_size=1, max_size=max_taps)))
    return b, a


@settings(max_examples=300, deadline=None)
@given(stable_filters(), hnp.arrays(np.float64, st.integers(0, 400), elements=finite))
def test_a_1d_signal_is_filtered_as_scipy_does(ba, x):
    b, a = ba
    assert agree(filters.lfilter(b, a, x), scipy_lfilter(b, a, x))


@settings(max_examples=200, deadline=None)
@given(hnp.arrays(np.float64, st.integers(1, 40), elements=finite), st.sampled_from([1.0, 2.5, -0.7]),
       hnp.arrays(np.float64, st.integers(1, 400), elements=finite))
def test_a_1d_signal_through_a_fir_filter_is_scipys_convolution_as_scipy_does(b, a0, x):
    ours, scipys = filters.lfilter(b, [a0], x), scipy_lfilter(b, [a0], x)
    assert agree(ours, scipys) and ours.strides == scipys.strides


@settings(max_examples=100, deadline=None)
@given(hnp.arrays(np.float64, st.integers(1, 40), elements=finite), st.sampled_from([1.0, 2.5, -0.7]),
       hnp.arrays(np.float64, st.tuples(st.integers(1, 200), st.integers(1, 4)), elements=finite),
       st.sampled_from([0, -1]))
def test_the_lanes_of_a_2d_array_through_a_fir_filter_are_scipys_convolutions(b, a0, x, axis):
    """Each column or row convolved as scipy does (the identification's high-order ARX prefilter: 31 taps through
    the inputs' columns), without importing scipy.signal."""
    ours, scipys = filters.lfilter(b, [a0], x, axis=axis), scipy_lfilter(b, [a0], x, axis=axis)
    assert agree(ours, scipys) and ours.strides == scipys.strides


def test_an_empty_signal_through_a_fir_filter_is_refused_as_scipy_refuses_it():
    for lfilter in (filters.lfilter, scipy_lfilter):
        for empty in (np.array([]), np.zeros((0, 2)), np.zeros((5, 0))):
            with pytest.raises(ValueError):
                lfilter([1.0, 0.5], [1.0], empty, axis=0)


@settings(max_examples=100, deadline=None)
@given(stable_filters(max_taps=9), hnp.arrays(np.float64, st.tuples(st.integers(0, 200), st.integers(1, 4)),
                                               elements=finite), st.sampled_from([0, -1]))
def test_the_columns_or_rows_of_a_2d_array_are_filtered_as_scipy_does(ba, x, axis):
    b, a = ba
    ours, scipys = filters.lfilter(b, a, x, axis=axis), scipy_lfilter(b, a, x, axis=axis)
    assert agree(ours, scipys) and ours.strides == scipys.strides


@settings(max_examples=100, deadline=None)
@given(st.lists(stable_filters(max_taps=6), min_size=1, max_size=7), st.integers(0, 300), st.data())
def test_many_signals_each_through_its_own_filter_are_filtered_as_scipy_does(filters_, n, data):
    """lfilter_each pairs the filters of one length through signals of one length (side by side in the kernel):
    every signal comes out as scipy filters it alone, whatever the mix (FIR filters and signals of another length
    among them)."""
    jobs = []
    for b, a in filters_:
        length = data.draw(st.sampled_from([n, n + 1]))
        x = data.draw(hnp.arrays(np.float64, length, elements=finite))
        jobs.append((b, a[:1] if data.draw(st.booleans()) and length else a, x))
    for (b, a, x), ours in zip(jobs, filters.lfilter_each(jobs), strict=True):
        assert agree(ours, scipy_lfilter(b, a, x))


@settings(max_examples=100, deadline=None)
@given(st.lists(stable_filters(max_taps=6), min_size=1, max_size=5), st.integers(1, 300), st.data())
def test_each_filter_restarts_at_the_segment_starts(filters_, n, data):
    """lfilter_each(jobs, starts): every signal filtered as scipy filters each of its segments alone, from zero
    state (the segments' first samples at `starts`), FIR filters among them."""
    starts = (0, *sorted(data.draw(st.sets(st.integers(1, n - 1), max_size=4)) if n > 1 else ()))
    jobs = [(b, a[:1] if data.draw(st.booleans()) else a, data.draw(hnp.arrays(np.float64, n, elements=finite)))
            for b, a in filters_]
    for (b, a, x), ours in zip(jobs, filters.lfilter_each(jobs, starts), strict=True):
        want = np.concatenate([scipy_lfilter(b, a, p) for p in np.split(x, starts[1:])])
        assert agree(ours, want)


def test_views_lists_and_integers_are_taken_as_scipy_takes_them():
    x = np.arange(60, dtype=float)[::3]  # not contiguous
    assert agree(filters.lfilter([1.0], [1.0, -0.5], x), scipy_lfilter([1.0], [1.0, -0.5], x))
    ints = np.arange(20)
    assert agree(filters.lfilter([1, 2], [1, -0.25], ints), scipy_lfilter([1, 2], [1, -0.25], ints))
    assert agree(filters.lfilter([1.0], [1.0, 0.5], np.array([])), scipy_lfilter([1.0], [1.0, 0.5], np.array([])))


def test_what_the_kernel_does_not_take_goes_to_scipy_alike():
    """Filters longer than MAX_TAPS, complex data, more than two dimensions: scipy's own result."""
    x = np.random.default_rng(0).normal(size=300)
    long_a = np.real(np.poly(np.full(filters.MAX_TAPS, 0.5)))
    for b, a, xx in (([1.0], long_a, x), ([1.0], [1.0, -0.5], x + 1j * x),
                     ([0.5, 0.25], [1.0, -0.5], x.reshape(10, 10, 3))):
        ours, scipys = filters.lfilter(b, a, xx, axis=0), scipy_lfilter(b, a, xx, axis=0)
        assert agree(ours, scipys) and ours.strides == scipys.strides


def test_without_the_kernel_scipy_gives_the_same_numbers(monkeypatch):
    x = np.random.default_rng(1).normal(size=500)
    a = np.real(np.poly([0.9, 0.5 + 0.3j, 0.5 - 0.3j]))
    jobs = [([1.0, 0.2], a, x), ([0.5, 0.1, 0.2, 0.3], [1.0, -0.3], x[::-1]), ([1.0, 0.5], [2.0], x)]
    compiled, compiled_each = filters.lfilter([1.0, 0.2], a, x), filters.lfilter_each(jobs)
    monkeypatch.setattr(filters, "_iir", None)
    assert not filters.compiled() and agree(filters.lfilter([1.0, 0.2], a, x), compiled)
    assert all(agree(y, want) for y, want in zip(filters.lfilter_each(jobs), compiled_each, strict=True))


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler: the install cannot build the kernel")
def test_an_install_with_a_c_compiler_has_the_kernel():
    """The extension is optional (pyproject.toml); where a compiler was there, an install that lost it is a slow
    one — re-run `pip install -e .`."""
    assert filters.compiled()
