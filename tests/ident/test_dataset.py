import json
import warnings

import numpy as np
import pytest

from fuelid.errors import FuelidError
from fuelid.ident.dataset import build_dataset, load_dataset, save_dataset

NS = 1_000_000_000


def eec1(t, speed, pct, sa=0):
    return ("/j1939/EEC1", int(round(t * NS)), {"t": t, "pgn": 61444, "sa": sa, "da": 255,
                                                 "EngSpeed": speed, "ActualEngPercentTorque": pct})


def lfe1(t, rate, sa=0):
    return ("/j1939/LFE1", int(round(t * NS)), {"t": t, "pgn": 65266, "sa": sa, "da": 255, "EngFuelRate": rate})


def ec1(t, ref=2000.0):
    return ("/j1939/EC1", int(round(t * NS)), {"t": t, "pgn": 65251, "sa": 0, "da": 255,
                                               "EngReferenceTorque": ref, "EngMomentOfInertia": 3.5})


def ccvs1(t, v):
    return ("/j1939/CCVS1", int(round(t * NS)), {"t": t, "pgn": 65265, "sa": 0, "da": 255,
                                                 "WheelBasedVehicleSpeed": v, "ParkingBrakeSwitch": 0})


def trip(t_end=60.0, gap=None, with_ec1=True, speed=lambda t: 600 + 10 * t, pct=lambda t: 10.0):
    """EEC1 every 20 ms, LFE1 and CCVS1 every 100 ms; no traffic at all inside `gap` (a, b)."""
    recs = [ec1(0.0)] if with_ec1 else []
    for i in range(int(t_end / 0.02)):
        t = i * 0.02
        if gap and gap[0] <= t < gap[1]:
            continue
        recs.append(eec1(t, speed(t), pct(t)))
        if i % 5 == 0:
            recs.append(lfe1(t, 2.0 + 0.1 * t))
            recs.append(ccvs1(t, 0.0 if t < 10 else 50.0))
    return recs


def test_grid_means_units_and_extras():
    ds = build_dataset(trip(), Ts=0.3)
    assert ds.input_units == ("rpm", "Nm") and ds.output_unit == "L/h"
    assert ds.Ts == 0.3 and np.allclose(np.diff(ds.t), 0.3)
    # bin k holds EEC1 samples t = 0.3k + 0.02j: mean speed = 600 + 10 (0.3k + 0.14)
    k = 10
    assert ds.u[k, 0] == pytest.approx(600 + 10 * (0.3 * k + 0.14), abs=1e-9)
    assert ds.u[k, 1] == pytest.approx(10.0 * 2000.0 / 100.0)
    assert "CCVS1.WheelBasedVehicleSpeed" in ds.extra and "EC1.EngMomentOfInertia" in ds.extra
    assert ds.valid.all() and len(ds.segments()) == 1
    assert ds.sources["EEC1.EngSpeed"] == 0


def test_a_fuel_lag_bins_the_fuel_with_the_interval_it_describes():
    # an ECU that reports at t the mean fuel of [t - 0.1, t): with the lag taken out, bin k holds the
    # fuel of [0.3k, 0.3k + 0.3), the interval of its speed and torque
    fuel = lambda t: 2.0 + 0.1 * t  # noqa: E731  injected fuel [L/h]
    recs = [r for r in trip() if r[0] != "/j1939/LFE1"]
    recs += [lfe1(i / 10, fuel(i / 10 - 0.05)) for i in range(1, 600)]  # the mean over the last 0.1 s
    plain, lagged = build_dataset(recs, Ts=0.3), build_dataset(recs, Ts=0.3, fuel_lag_s=0.1)
    k = 50
    assert lagged.fuel_lag_s == 0.1 and lagged.summary()["fuel_lag_s"] == 0.1
    assert plain.fuel_period_s == pytest.approx(0.1) == lagged.summary()["fuel_period_s"]  # LFE1 every 100 ms
    assert lagged.y[lagged.t == plain.t[k]][0] == pytest.approx(fuel(plain.t[k] + 0.15), abs=1e-9)
    assert plain.y[k] == pytest.approx(fuel(plain.t[k] + 0.05), abs=1e-9)  # a third of a bin late
    np.testing.assert_array_equal(lagged.u[lagged.t == plain.t[k]], plain.u[[k]])
    with pytest.raises(FuelidError, match="lag"):
        build_dataset(recs, Ts=0.3, fuel_lag_s=0.3)


def test_long_gap_is_not_interpolated_and_splits_segments():
    ds = build_dataset(trip(gap=(20.0, 25.0)), Ts=0.3, max_gap_s=1.0)
    inside = (ds.t >= 21.2) & (ds.t < 24.7)
    assert not ds.valid[inside].any()
    assert np.isnan(ds.u[inside & ~np.isin(np.arange(len(ds)), [])][:, 0]).all()
    segs = ds.segments()
    assert len(segs) == 2
    assert ds.t[segs[0].stop - 1] < 21.0 and ds.t[segs[1].start] >= 24.9
    # held for at most max_gap_s: the last valid sample is within 1 s after the last record
    assert ds.t[segs[0].stop - 1] + 0.3 - 19.98 <= 1.0 + 1e-9


def test_short_gap_is_held():
    ds = build_dataset(trip(gap=(20.0, 20.5)), Ts=0.3, max_gap_s=1.0)
    assert ds.valid.all() and len(ds.segments()) == 1
    k = np.flatnonzero((ds.t >= 20.0) & (ds.t < 20.3))[0]
    assert ds.u[k, 0] == pytest.approx(600 + 10 * 19.98)


def test_very_long_break_keeps_grid_small():
    recs = trip(t_end=10.0) + [(topic, ns + 86400 * NS, rec) for topic, ns, rec in trip(t_end=10.0, with_ec1=False)]
    ds = build_dataset(recs, Ts=0.3)
    assert len(ds) < 100
    assert len(ds.segments()) == 2


def test_an_engine_that_is_off_or_starting_is_not_valid_data():
    """A stop with the engine off (0 rpm) and its restart (cranking at 200 rpm) inside a trip: those bins are not
    valid (they split the trip, a note says how long), an engine off throughout is a one-line error."""
    def speed(t):
        return 0.0 if 20 <= t < 30 else 200.0 if 30 <= t < 31 else 600 + 10 * t

    with pytest.warns(UserWarning, match=r"11 s with the engine off or starting \(below 300 rpm\) left out"):
        ds = build_dataset(trip(speed=speed), Ts=0.3)
    assert not ds.valid[(ds.t >= 20.1) & (ds.t < 30.9)].any() and len(ds.segments()) == 2
    assert (ds.u[ds.valid, 0] >= 300).all()
    with pytest.raises(FuelidError, match="the engine is off throughout these data: engine speed stays below 300 rpm"):
        build_dataset(trip(speed=lambda t: 0.0), Ts=0.3)


def test_a_fuel_signal_slower_than_the_grid_is_noted():
    """LFE1 once a second on the 0.3 s grid: each report held over three bins, which a note says."""
    recs = [r for r in trip() if r[0] != "/j1939/LFE1" or round(r[1] / NS, 2) % 1.0 == 0.0]
    with pytest.warns(UserWarning, match=r"the fuel signal \(LFE1.EngFuelRate\) arrives every 1 s, slower than the "
                                         r"grid's 0.3 s.*--ts 1 matches it"):
        ds = build_dataset(recs, Ts=0.3)
    assert ds.fuel_period_s == pytest.approx(1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        build_dataset(recs, Ts=1.0)


def test_source_preference_and_nulls():
    recs = trip(t_end=20.0)
    # a second ECU (0x17) sends EEC1 with other values and nulls; LFE1 only from 0x17
    for i in range(1000):
        t = i * 0.02 + 0.01
        recs.append(eec1(t, None if i % 2 else 5000.0, None, sa=0x17))
    recs = [r for r in recs if r[0] != "/j1939/LFE1"] + [lfe1(i * 0.1, 3.0, sa=0x17) for i in range(200)]
    ds = build_dataset(recs, Ts=0.3)
    assert ds.sources["EEC1.EngSpeed"] == 0 and ds.sources["LFE1.EngFuelRate"] == 0x17
    assert np.nanmax(ds.u[:, 0]) < 1000  # never the 5000 rpm of 0x17
    assert np.allclose(ds.y[ds.valid], 3.0)
    # the engine sends only nulls for speed, valid torque; 0x17 sends both
    recs2 = [r for r in recs if r[0] != "/j1939/EEC1"]
    recs2 += [eec1(i * 0.02, None, 12.0) for i in range(1000)]
    recs2 += [eec1(i * 0.02 + 0.005, 700.0, 12.0, sa=0x17) for i in range(1000)]
    with pytest.warns(UserWarning, match="idle"):
        ds2 = build_dataset(recs2, Ts=0.3)
    # speed: engine never valid → falls back to 0x17; torque: engine valid → engine
    assert ds2.sources["EEC1.EngSpeed"] == 0x17 and ds2.sources["EEC1.ActualEngPercentTorque"] == 0
    assert np.allclose(ds2.u[ds2.valid, 0], 700.0)


def test_torque_percent_fallback_warns():
    with pytest.warns(UserWarning, match="EC1"):
        ds = build_dataset(trip(with_ec1=False), Ts=0.3)
    assert ds.input_units == ("rpm", "%")
    assert ds.u[5, 1] == pytest.approx(10.0)
    assert ds.notes


def test_operating_point_idle():
    speed = lambda t: 600.0 if t < 10 else 1200.0
    pct = lambda t: 5.0 if t < 10 else 60.0
    recs = [r for r in trip(speed=speed, pct=pct)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = build_dataset(recs, Ts=0.3)
    assert ds.u0 == pytest.approx([600.0, 100.0])
    idle = ds.t < 9.9
    assert ds.y0 == pytest.approx(ds.y[idle & ds.valid].mean())
    assert np.allclose(ds.du[3], ds.u[3] - ds.u0)


def test_missing_signals_are_user_errors():
    with pytest.raises(FuelidError, match="fuel"):
        build_dataset([r for r in trip(t_end=5) if r[0] != "/j1939/LFE1"])
    with pytest.raises(FuelidError, match="engine speed"):
        build_dataset([r for r in trip(t_end=5) if r[0] != "/j1939/EEC1"])
    with pytest.raises(FuelidError, match="flow"):
        build_dataset(trip(t_end=5), fuel="flowmeter")


def test_flowmeter_preferred_in_auto():
    recs = trip(t_end=10)
    recs += [("/flowmeter", int(i * 0.1 * NS), {"t": i * 0.1, "device_t": None, "volts": 1.0,
                                                 "flow_kg_h": 12.5, "status": "ok", "raw": "1.0"}) for i in range(100)]
    ds = build_dataset(recs)
    assert ds.output_name == "flowmeter.flow_kg_h" and ds.output_unit == "kg/h"
    assert "LFE1.EngFuelRate" in ds.extra


def test_drive_cycles():
    ds = build_dataset(trip(t_end=100.0, gap=(40.0, 45.0)), Ts=0.3, cycle_s=15.0, min_cycle_s=5.0)
    segs = ds.segments()
    for s in segs:
        assert len(set(ds.cycle[s])) >= 2
    c = ds.cycle[ds.cycle >= 0]
    assert np.all(np.diff(c) >= 0)
    assert np.all(ds.cycle[~ds.valid] == -1)
    durations = np.bincount(c) * 0.3
    assert durations.min() >= 15.0 - 1e-9


@pytest.mark.parametrize("suffix", [".csv", ".mat"])
def test_export_round_trip(tmp_path, suffix):
    ds = build_dataset(trip(t_end=20.0, gap=(10.0, 12.0)), Ts=0.3, fuel_lag_s=0.1)
    back = load_dataset(save_dataset(ds, tmp_path / f"d{suffix}"))
    assert back.Ts == ds.Ts and back.fuel_lag_s == 0.1 and back.fuel_period_s == ds.fuel_period_s > 0
    assert back.input_units == ds.input_units and back.output_name == ds.output_name
    np.testing.assert_allclose(back.t, ds.t)
    np.testing.assert_allclose(back.u, ds.u, equal_nan=True)
    np.testing.assert_allclose(back.y, ds.y, equal_nan=True)
    np.testing.assert_array_equal(back.valid, ds.valid)
    np.testing.assert_array_equal(back.cycle, ds.cycle)
    np.testing.assert_allclose(back.u0, ds.u0)
    assert set(back.extra) == set(ds.extra)
    for k in ds.extra:
        np.testing.assert_allclose(back.extra[k], ds.extra[k], equal_nan=True)


def _write_mcap(path, records):
    from fuelid.logger.mcap_log import McapLogWriter
    with McapLogWriter(path, metadata={"truck": "test"}, fsync=False) as writer:
        for topic, log_ns, rec in records:
            if not writer.has_channel(topic):
                writer.add_channel(topic, {"type": "object"})
            writer.write(topic, log_ns, rec)


def test_files_join_into_one_timeline_but_overlapping_recordings_are_refused(tmp_path):
    first, later, same_time = tmp_path / "a.mcap", tmp_path / "b.mcap", tmp_path / "c.mcap"
    shift = lambda recs, s: [(tp, ns + int(s * NS), {**r, "t": r["t"] + s}) for tp, ns, r in recs]
    _write_mcap(first, trip(60.0))
    _write_mcap(later, shift(trip(60.0), 3600.0))
    _write_mcap(same_time, shift(trip(60.0), 30.0))
    ds = build_dataset([first, later])
    assert len(ds.segments()) == 2 and ds.valid.sum() * ds.Ts == pytest.approx(120.0, abs=1.0)
    with pytest.raises(FuelidError, match="overlap in time"):
        build_dataset([first, same_time])


def test_a_recording_gives_the_dataset_of_its_records(tmp_path):
    """Reading the MCAP (only the decoded topics, skipping the /can/raw frames between them) gives exactly the
    dataset of the same records handed over in memory: every column, the extras and their order. Nulls,
    booleans and text are no samples."""
    recs = trip(40.0)
    recs += [("/j1939/ETC2", int(round(i * 0.1 * NS)), {"t": i * 0.1, "sa": 3, "CurrentGear": None if i % 7 else 4,
                                                         "TransSelectedGear": 5, "Mode": "drive", "Shift": i % 2 == 0})
             for i in range(400)]
    raw = [("/can/raw", ns + 1, {"t": 0.0, "id": 0x0CF00400, "extended": True, "data": "00" * 8})
           for _, ns, _ in recs[::3]]
    path = tmp_path / "trip.mcap"
    _write_mcap(path, sorted(recs + raw, key=lambda r: r[1]))
    from_file, in_memory = build_dataset(path), build_dataset(sorted(recs, key=lambda r: r[1]))
    for name in ("t", "u", "y", "valid", "cycle", "u0"):
        np.testing.assert_array_equal(getattr(from_file, name), getattr(in_memory, name))
    assert list(from_file.extra) == list(in_memory.extra) and from_file.sources == in_memory.sources
    for name, col in in_memory.extra.items():
        np.testing.assert_array_equal(from_file.extra[name], col)
    assert "ETC2.Mode" not in in_memory.extra and "ETC2.Shift" not in in_memory.extra
    gear = in_memory.extra["ETC2.CurrentGear"]
    assert np.nanmax(gear) == 4 and in_memory.sources["ETC2.CurrentGear"] == 3


def test_csv_opens_in_a_spreadsheet_with_units_and_readable_time(tmp_path):
    """The CSV is one header row and numbers (no comment line); time is seconds since the start and an ISO
    timestamp; units are in the header and in the CSVW sidecar, which also carries what load_dataset needs."""
    ds = build_dataset(trip(t_end=20.0), Ts=0.3)
    out = save_dataset(ds, tmp_path / "d.csv")
    lines = out.read_text().splitlines()
    header, first = lines[0].split(","), lines[1].split(",")
    assert header[:2] == ["time_s [s]", "time_utc"] and "EEC1.EngSpeed [rpm]" in header
    assert float(first[0]) == 0.0 and first[1].endswith("Z") and first[1].startswith("1970-01-01T00:00:00")
    assert len(lines) == len(ds) + 1 and not any(line.startswith("#") for line in lines)
    sidecar = json.loads((tmp_path / "d.csv-metadata.json").read_text())
    units = {c["name"]: c.get("schema:unitText") for c in sidecar["tableSchema"]["columns"]}
    assert units["time_s"] == "s" and units["EEC1.EngSpeed"] == "rpm" and units[ds.output_name] == ds.output_unit
    assert sidecar["url"] == "d.csv" and sidecar["fuelid"]["Ts"] == ds.Ts


def test_csv_without_its_sidecar_is_a_one_line_error(tmp_path):
    out = save_dataset(build_dataset(trip(t_end=5.0), Ts=0.3), tmp_path / "d.csv")
    (tmp_path / "d.csv-metadata.json").unlink()
    with pytest.raises(FuelidError, match="d.csv-metadata.json is missing"):
        load_dataset(out)


def test_a_damaged_chunk_is_an_error_unless_skipping_is_asked_for(tmp_path):
    """A flipped byte inside a compressed chunk must never become valid-looking wrong samples."""
    from mcap.reader import make_reader
    path = tmp_path / "trip.mcap"
    _write_mcap(path, trip(60.0))
    with open(path, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    middle = chunks[len(chunks) // 2]
    data = bytearray(path.read_bytes())
    data[middle.chunk_start_offset + middle.chunk_length // 2] ^= 0x08
    path.write_bytes(bytes(data))
    span = f"{middle.chunk_start_offset}-{middle.chunk_start_offset + middle.chunk_length}"
    with pytest.raises(FuelidError, match=f"{path}: damaged chunk at bytes {span}"):
        build_dataset(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        ds = build_dataset(path, skip_damaged=True, max_gap_s=0.5)
    assert any(f"damaged chunk at bytes {span}" in note for note in ds.notes)
    assert len(ds.segments()) == 2  # the lost second of data is a gap, not made-up samples


def test_a_cut_file_with_too_little_left_says_it_is_truncated(tmp_path):
    """A file cut before its first chunk ended holds no engine speed: the error says the file is truncated and how
    much of it is readable, not only that a signal is missing."""
    path = tmp_path / "cut.mcap"
    _write_mcap(path, trip(60.0))
    path.write_bytes(path.read_bytes()[:300])
    with pytest.raises(FuelidError, match=r"no engine speed .*cut.mcap is truncated \(cut before its end\): 0 s readable"):
        build_dataset(path)
