"""ident.modelrun: one run of a model over a dataset, which the metrics, the diagnosis and the report read."""
import dataclasses
import warnings

import numpy as np
import pytest

from fuelid.ident.modelrun import min_tested_length, run_model
from fuelid.ident.pem import pem
from fuelid.ident.polymodel import simulate
from fuelid.ident.validation import evaluate, metrics
from tests.ident import hidden


@pytest.fixture(scope="module")
def case():
    ds = hidden.make(None, n=3000, seed=4)
    ds.valid[1000:1010] = False  # two segments, each run from zero state
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = pem(ds.u, ds.y, hidden.STRUCTURE, ds.Ts, u0=ds.u0, y0=ds.y0)
    model = dataclasses.replace(m, input_names=ds.input_names, input_units=ds.input_units,
                                output_name=ds.output_name, output_unit=ds.output_unit)
    return ds, model


def test_each_segment_is_simulated_from_zero_state_and_the_metrics_skip_its_start(case):
    ds, model = case
    run = run_model(model, ds)
    assert [(s.start, s.stop) for s in run.segments] == [(0, 1000), (1010, 3000)]
    second = run.segments[1]
    np.testing.assert_array_equal(run.ysim[second], simulate(model, ds.u[second]))
    assert np.isnan(run.ysim[1000:1010]).all() and np.isnan(run.eps[1000:1010]).all()
    n0 = model.structure.n_start
    assert np.isnan(run.eps[1010:1010 + n0]).all() and np.isfinite(run.eps[1010 + n0:]).all()
    settled = run.settled(run.ysim)
    assert np.isnan(settled[:n0]).all() and np.array_equal(settled[n0:1000], run.ysim[n0:1000])
    assert metrics(run, ds) == evaluate(model, ds)


def test_only_segments_long_enough_are_tested(case):
    ds, model = case
    short = dataclasses.replace(ds, valid=ds.valid.copy())
    short.valid[min_tested_length(model) - 1:1010] = False  # the first segment one sample too short
    run = run_model(model, short)
    assert [(s.start, s.stop) for s in run.tested] == [(1010, 3000)]
    assert np.isnan(run.on_tested(run.ysim)[:1010]).all()
    assert np.array_equal(run.tested_index, np.arange(1010 + model.structure.n_start, 3000))  # what is tested
    short.valid[1010 + min_tested_length(model) - 1:] = False
    with pytest.raises(ValueError, match="no valid segment"):
        run_model(model, short).require_tested()
