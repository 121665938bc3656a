"""build_dataset reads MCAP files column-wise, chunk batch by chunk batch. These tests pin its results to the
values the earlier record-by-record implementation gave on the same files (frozen in
data/dataset_golden.npz), on recordings with the awkward cases: nulls, several source addresses, a record
that is not numbers, transport-protocol records, a gap, a clock that steps back, files joined in either order."""
import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from fuelid.ident.dataset import build_dataset
from fuelid.logger.mcap_log import McapLogWriter

GOLDEN = Path(__file__).parent / "data" / "dataset_golden.npz"
NS = 1_000_000_000


def _record(t, pgn, sa, values, tp=None):
    rec = {"t": t, "pgn": pgn, "sa": sa, "da": 255, **values,
           "invalid": {k: "not_available" for k, v in values.items() if v is None}}
    if tp:
        rec["tp"] = tp
    return rec


def recording(t0: float, seconds: float, seed: int, step_back_at: float | None = None) -> list:
    """(topic, log_ns, record) of a synthetic truck, laid out as the logger writes them: EEC1 every 20 ms from
    the engine (0x00, nulls now and then) and from a second ECU (0x17); LFE1, CCVS1, ETC2 (0x03) every 100 ms;
    EC1 by BAM every second; a flow meter at 10 Hz; a 4 s silence in the middle; with step_back_at the log
    clock jumps back 0.37 s there."""
    rng = np.random.default_rng(seed)
    out = []
    clock_shift = 0.0
    for i in range(int(seconds / 0.02)):
        t = float(round(t0 + i * 0.02 + rng.uniform(0, 0.004), 6))
        if seconds * 0.45 <= i * 0.02 < seconds * 0.45 + 4.0:
            continue
        if step_back_at is not None and i * 0.02 >= step_back_at:
            clock_shift = -0.37
        lt = t + clock_shift
        speed = None if rng.random() < 0.03 else float(round(800 + 400 * np.sin(i / 300) + rng.normal(0, 3), 3))
        pct = None if rng.random() < 0.02 else float(rng.integers(0, 125))
        out.append(("/j1939/EEC1", int(round(lt * NS)), _record(lt, 61444, 0, {
            "EngTorqueMode": 0, "DriversDemandEngPercentTorque": pct, "ActualEngPercentTorque": pct,
            "EngSpeed": speed, "SrcAddrssOfCtrllngDvcFrEngCtrl": None, "EngStarterMode": 0,
            "EngDemandPercentTorque": None})))
        if i % 3 == 0:
            out.append(("/j1939/EEC1", int(round((lt + 0.001) * NS)), _record(lt + 0.001, 61444, 0x17, {
                "EngTorqueMode": 0, "DriversDemandEngPercentTorque": None, "ActualEngPercentTorque": 50.0,
                "EngSpeed": None if i % 2 else 5000.0, "SrcAddrssOfCtrllngDvcFrEngCtrl": None, "EngStarterMode": 0,
                "EngDemandPercentTorque": None})))
        if i % 5 == 0:
            out.append(("/j1939/LFE1", int(round(lt * NS)), _record(lt, 65266, 0, {
                "EngFuelRate": None if rng.random() < 0.05 else float(round(5 + 20 * rng.random(), 2)),
                "EngInstantaneousFuelEconomy": 0.001953125 * int(rng.integers(0, 60000)),
                "EngAverageFuelEconomy": None, "EngThrottleValve1Position1": 0.4 * int(rng.integers(0, 250))})))
            out.append(("/j1939/CCVS1", int(round(lt * NS)), _record(lt, 65265, 0, {
                "WheelBasedVehicleSpeed": 0.0 if i * 0.02 < 8 else float(round(60 + rng.normal(0, 1), 4)),
                "ParkingBrakeSwitch": 0, "CruiseCtrlActive": None})))
            out.append(("/j1939/ETC2", int(round(lt * NS)), _record(lt, 61445, 3, {
                "TransSelectedGear": 5, "TransActualGearRatio": 0.001 * int(rng.integers(500, 9000)),
                "TransCurrentGear": None if i % 35 else 4})))
            out.append(("/flowmeter", int(round(lt * NS)), {
                "t": lt, "device_t": None, "volts": 1.0, "flow_kg_h": None if i % 45 == 0 else float(round(12 * rng.random(), 3)),
                "status": "ok", "raw": "1.0"}))
        if i % 50 == 0:
            out.append(("/j1939/EC1", int(round(lt * NS)), _record(lt, 65251, 0, {
                "EngSpeedAtIdlePoint1": 600.0 + 25 * (i % 100 == 0), "EngReferenceTorque": 2000.0 + (i % 150 == 0),
                "EngMomentOfInertia": 3.5}, tp="bam")))
        if i % 500 == 7:  # a record that is not numbers: read one by one, its text is no sample
            out.append(("/j1939/ERC1", int(round(lt * NS)), {"t": lt, "pgn": 61440, "sa": 15, "da": 255,
                                                             "RetarderTorqueMode": "drive", "Active": True,
                                                             "ActualRetarderPercentTorque": -12.5, "invalid": {}}))
    return out


def write_mcap(path, records):
    with McapLogWriter(path, metadata={"truck": "test"}, fsync=False) as writer:
        for topic, log_ns, rec in records:
            if not writer.has_channel(topic):
                writer.add_channel(topic, {"type": "object"})
            writer.write(topic, log_ns, rec)
    return path


def cases(tmp: Path) -> dict:
    """Case name → (the build_dataset call's sources, keyword arguments)."""
    a = write_mcap(tmp / "a.mcap", recording(1_700_000_000.0, 120.0, 1))
    b = write_mcap(tmp / "b.mcap", recording(1_700_000_300.0, 60.0, 2))
    back = write_mcap(tmp / "back.mcap", recording(1_700_000_000.0, 90.0, 3, step_back_at=40.0))
    return {"one_file": ([a], {}), "joined": ([a, b], {}), "joined_reversed": ([b, a], {}),
            "clock_steps_back": ([back], {}), "lfe1_ts_0.1": ([a], {"fuel": "lfe1", "Ts": 0.1, "max_gap_s": 0.5})}


def frozen(ds) -> dict[str, np.ndarray]:
    arrays = {"t": ds.t, "u": ds.u, "y": ds.y, "valid": ds.valid, "cycle": ds.cycle, "u0": ds.u0,
              **{f"extra/{k}": v for k, v in ds.extra.items()}}
    meta = {"y0": ds.y0, "extra": list(ds.extra), "sources": ds.sources, "notes": ds.notes,
            "names": [list(ds.input_names), list(ds.input_units), ds.output_name, ds.output_unit]}
    return {**arrays, "meta": np.array(json.dumps(meta))}


def build(sources, kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return build_dataset(sources, **kwargs)


@pytest.mark.parametrize("case", ["one_file", "joined", "joined_reversed", "clock_steps_back", "lfe1_ts_0.1"])
def test_file_datasets_equal_the_frozen_ones(tmp_path, case):
    sources, kwargs = cases(tmp_path)[case]
    got = frozen(build(sources, kwargs))
    with np.load(GOLDEN) as golden:
        want = {k[len(case) + 1:]: golden[k] for k in golden.files if k.startswith(case + ":")}
    assert json.loads(str(got.pop("meta"))) == json.loads(str(want.pop("meta")))
    assert sorted(got) == sorted(want)
    for name, values in want.items():
        np.testing.assert_array_equal(got[name], values, err_msg=name)  # bit for bit, NaN where NaN


def test_a_file_gives_the_dataset_of_its_records_in_memory(tmp_path):
    recs = recording(1_700_000_000.0, 60.0, 4)
    from_file = build([write_mcap(tmp_path / "r.mcap", recs)], {})
    in_memory = build(recs, {})
    got, want = frozen(from_file), frozen(in_memory)
    assert sorted(got) == sorted(want) and str(got.pop("meta")) == str(want.pop("meta"))
    for name, values in want.items():
        np.testing.assert_array_equal(got[name], values, err_msg=name)


if __name__ == "__main__":  # regenerate the frozen values (only when the dataset's maths changes on purpose)
    import sys
    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        out = {f"{name}:{k}": v for name, (sources, kwargs) in cases(Path(tmp)).items()
               for k, v in frozen(build(sources, kwargs)).items()}
    np.savez_compressed(sys.argv[1] if len(sys.argv) > 1 else GOLDEN, **out)


def test_a_cut_file_gives_the_dataset_of_the_messages_it_still_holds(tmp_path):
    """A file without its footer (power cut) is scanned, not read through its index: same dataset as its
    readable messages handed over in memory."""
    from fuelid.logger.mcap_log import read_messages
    whole = write_mcap(tmp_path / "whole.mcap", recording(1_700_000_000.0, 60.0, 5))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size * 2 // 3])
    got, want = frozen(build([cut], {})), frozen(build(list(read_messages(cut)), {}))
    assert sorted(got) == sorted(want) and str(got.pop("meta")) == str(want.pop("meta"))
    for name, values in want.items():
        np.testing.assert_array_equal(got[name], values, err_msg=name)


def test_a_file_of_decoded_messages_only_reads_to_its_last_byte(tmp_path):
    """The last value of a batch sits a few bytes before the end of the chunk data: parsing it must not read
    past the end (a file without /can/raw or flow-meter messages after the last /j1939 record)."""
    recs = [(topic, ns, rec) for topic, ns, rec in recording(1_700_000_000.0, 30.0, 6)
            if topic in ("/j1939/EEC1", "/j1939/LFE1", "/j1939/EC1")]
    recs.append(("/j1939/EEC1", recs[-1][1] + 1, _record(recs[-1][2]["t"], 61444, 0, {
        "EngTorqueMode": 0.15000000000000002, "DriversDemandEngPercentTorque": 1.0000000000000002,
        "ActualEngPercentTorque": 3.0000000000000004, "EngSpeed": 1234.5678901234567})))
    got, want = frozen(build([write_mcap(tmp_path / "d.mcap", recs)], {})), frozen(build(recs, {}))
    assert str(got.pop("meta")) == str(want.pop("meta"))
    for name, values in want.items():
        np.testing.assert_array_equal(got[name], values, err_msg=name)
