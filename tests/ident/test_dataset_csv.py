"""The dataset CSV (ident.dataset.save_dataset, pyarrow's writer) holds what the row-by-row writer before it held:
the same header with units, every number equal to the dataset's to the last bit, NaN as an empty field, the
same ISO 8601 UTC time to the millisecond — also across the writer's chunks."""
import csv

import numpy as np
import pytest

from fuelid.ident import dataset
from fuelid.ident.dataset import build_dataset, save_dataset
from tests.ident.test_dataset import trip


def reference_rows(ds):
    """The rows as the row-by-row writer wrote them: time since the first sample, the ISO time, then valid,
    cycle, speed, torque, fuel and the extras, each as repr(float) or empty for NaN."""
    cols = [ds.t - ds.t[0], ds.valid.astype(float), ds.cycle.astype(float), ds.u[:, 0], ds.u[:, 1], ds.y,
            *ds.extra.values()]
    stamps = np.datetime64("1970-01-01T00:00:00", "ms") + np.round(ds.t * 1e3).astype("timedelta64[ms]")
    data = np.column_stack(cols)
    return [["" if np.isnan(row[0]) else repr(float(row[0])), f"{s}Z"]
            + ["" if np.isnan(v) else repr(float(v)) for v in row[1:]] for s, row in zip(stamps.astype(str), data)]


@pytest.mark.parametrize("chunk", [1 << 16, 7])
def test_the_csv_holds_what_the_row_writer_held(tmp_path, monkeypatch, chunk):
    ds = build_dataset(trip(t_end=20.0, gap=(10.0, 12.0)), Ts=0.3)
    ds.t = ds.t + 1_700_000_000.0  # a real date
    next(iter(ds.extra.values()))[::5] = np.nan
    monkeypatch.setattr(dataset, "CSV_CHUNK_ROWS", chunk)
    out = save_dataset(ds, tmp_path / "d.csv")
    with open(out, newline="") as f:
        header, *written = list(csv.reader(f))
    units = [f"{n} [{u}]" for n, u in zip(ds.input_names, ds.input_units)] + [f"{ds.output_name} [{ds.output_unit}]"]
    assert header[:7] == ["time_s [s]", "time_utc", "valid", "cycle", *units]
    assert [h.split(" [")[0] for h in header[7:]] == list(ds.extra) and "EC1.EngReferenceTorque [Nm]" in header
    expected = reference_rows(ds)
    assert len(written) == len(expected)
    for got, want in zip(written, expected):
        assert got[1] == want[1]  # the ISO time, to the millisecond
        assert [g == "" for g in got] == [w == "" for w in want]  # NaN is an empty field, nothing else is
        assert [float(g) for g in got if g and not g.endswith("Z")] == [float(w) for w in want if w and not w.endswith("Z")]
