"""A converted file carries its decoded messages twice: as JSON channels (for viewers) and as message columns
(logger.columns attachments), which build_dataset reads instead, without parsing JSON. Both give the same
Dataset; files without columns (older conversions, the daemon's, rewritten ones) read through the JSON."""
import math
from pathlib import Path

import numpy as np
import pytest

from fuelid.errors import FuelidError
from fuelid.ident.dataset import build_dataset
from fuelid.logger.columns import NAME
from fuelid.logger.flowmeter import FlowReading
from fuelid.logger.mcap_log import read_attachments, recover
from fuelid.logger.recorder import Recorder, open_writer
from tests.logger import traffic

SAMPLE = Path(__file__).parents[2] / "replay_logs" / "sample_diesel_1min.log.gz"


def converted(path: Path, seconds: float = 60.0) -> Path:
    """A conversion of FMS traffic (a short frame, the VIN by BAM) and a flow meter at 10 Hz with gaps and nulls."""
    frames = traffic.frames(seconds)
    t0 = frames[0].timestamp
    readings = [FlowReading(t0 + 0.1 * k + 0.003, None, 1.0 + (k % 7) * 0.1,
                            None if k % 13 == 0 else round(3 + math.sin(k / 10), 3), "ok", "")
                for k in range(int(seconds * 10)) if not 200 <= k < 240]
    items = sorted([(m.timestamp, 0, m) for m in frames] + [(r.t, 1, r) for r in readings], key=lambda e: e[0])
    writer = open_writer(path, live=False)
    recorder = Recorder(writer)
    for _, kind, item in items:
        recorder.on_message_received(item) if kind == 0 else recorder.on_flow_reading(item)
    writer.close()
    return path


def without_columns(path: Path) -> Path:
    """The same file as fuelid wrote it before the columns: `recover` copies the channels, not attachments."""
    old = path.with_name("old_" + path.name)
    recover(path, old)
    assert read_attachments(old, NAME) is None
    return old


def assert_same(a, b):
    assert (a.input_names, a.input_units, a.output_name, a.output_unit) == (b.input_names, b.input_units,
                                                                            b.output_name, b.output_unit)
    assert list(a.extra) == list(b.extra) and a.sources == b.sources and a.notes == b.notes and a.y0 == b.y0
    assert a.fuel_lag_s == b.fuel_lag_s and a.fuel_period_s == b.fuel_period_s
    for name in ("t", "u", "y", "valid", "cycle", "u0"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)  # bit for bit
    for name, values in a.extra.items():
        np.testing.assert_array_equal(values, b.extra[name], err_msg=name)


def build(*args, **kwargs):
    with pytest.warns(UserWarning):  # no EC1 in the traffic: torque in %
        return build_dataset(*args, **kwargs)


def test_columns_give_the_dataset_of_the_json_channels(tmp_path):
    new = converted(tmp_path / "new.mcap")
    counts, blocks = read_attachments(new, NAME)
    assert blocks and counts["/flowmeter"] == 560
    ds = build(new)
    assert ds.output_name == "flowmeter.flow_kg_h" and "flowmeter.volts" in ds.extra and ds.valid.sum() > 100
    assert_same(ds, build(without_columns(new)))
    for kwargs in ({"fuel": "lfe1", "Ts": 0.1}, {"max_gap_s": 5.0}):
        assert_same(build(new, **kwargs), build(without_columns(new), **kwargs))


def test_columns_of_a_real_conversion_with_two_source_addresses_and_ec1_by_bam(tmp_path):
    from fuelid.cli import main
    new = tmp_path / "sample.mcap"
    assert main(["convert", str(SAMPLE), "-o", str(new)]) == 0
    ds = build_dataset(new)
    assert ds.input_units[1] == "Nm" and "CCVS1.WheelBasedVehicleSpeed" in ds.extra
    assert_same(ds, build_dataset(without_columns(new)))


def test_files_with_and_without_columns_join_into_one_recording(tmp_path):
    a = converted(tmp_path / "a.mcap", 30.0)
    b = tmp_path / "b.mcap"
    traffic_b = converted(tmp_path / "b_src.mcap", 30.0)  # the same traffic, 100 s later: shifted by a rewrite
    from fuelid.logger.mcap_log import McapLogWriter, read_messages
    with McapLogWriter(b, metadata={}, fsync=False) as w:
        for topic, ns, rec in read_messages(traffic_b):
            if not w.has_channel(topic):
                w.add_channel(topic, {"type": "object"})
            w.write(topic, ns + 100 * 10**9, rec)
    assert_same(build([a, b]), build([without_columns(a), b]))


def test_a_damaged_column_attachment_is_a_clear_error(tmp_path):
    new = converted(tmp_path / "new.mcap")
    data = bytearray(new.read_bytes())
    _, blocks = read_attachments(new, NAME)
    at = data.find(blocks[0][100:140])
    data[at + 10] ^= 0xFF
    new.write_bytes(bytes(data))
    with pytest.raises(FuelidError, match=r"damaged attachment fuelid.columns at bytes \d+-\d+ \(CRC mismatch\)"):
        build_dataset(new)
    assert_same(build(without_columns(new)), build(without_columns(converted(tmp_path / "intact.mcap"))))


def test_columns_that_do_not_hold_every_message_are_an_error(tmp_path):
    path = tmp_path / "partial.mcap"
    writer = open_writer(path, live=False)
    recorder = Recorder(writer)
    for m in traffic.frames(10.0):
        recorder.on_message_received(m)
    writer.write("/j1939/EEC1", 1_700_000_020 * 10**9, {"t": 1_700_000_020.0, "pgn": 61444, "sa": 0, "da": 255,
                                                        "EngSpeed": 700.0, "invalid": {}})  # past the columns
    writer.close()
    with pytest.raises(FuelidError, match="attachments hold .* messages, its channels .*: not written together"):
        build_dataset(path)
