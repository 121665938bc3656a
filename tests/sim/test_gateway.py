"""Every frame on the simulated bus decodes back, through `fuelid convert`, to the simulator's values within one
quantisation step."""
import can
import cantools
import numpy as np
import pytest

from fuelid.dbc import FMS_DBC
from fuelid.cli import main
from fuelid.logger.mcap_log import read_messages
from fuelid.sim import gateway
from fuelid.sim.trip import TripConfig, simulate, write

DB = cantools.database.load_file(FMS_DBC)


def decode_log(path):
    """{(DBC message name, source address): [(t, {signal: value or None}), ...]} of a candump log, converted to
    MCAP by `fuelid convert` and read back; None where the value is not available / error / reserved."""
    mcap = path.with_name(path.name.split(".")[0] + ".mcap")
    assert main(["convert", str(path), "-o", str(mcap), "--json"]) == 0
    out = {}
    for topic, _, record in read_messages(mcap):
        if topic.startswith("/j1939/") and "tp" not in record:
            out.setdefault((topic[len("/j1939/"):], record["sa"]), []).append((record["t"], record))
    return out


def test_vectorised_packing_matches_cantools():
    rng = np.random.default_rng(0)
    for name in ("EEC1", "CCVS1", "ETC2", "AMB", "LFC1"):
        m = DB.get_message_by_name(name)
        values = {s.name: rng.uniform(s.minimum, min(s.maximum, s.offset + s.scale * gateway.max_valid_raw(s.length)), 50)
                  for s in m.signals}
        data, sent = gateway.pack(m, values, 50)
        for k in range(50):
            assert bytes(data[k]) == m.encode({s: v[k] for s, v in values.items()}, padding=True), name


def test_every_frame_decodes_to_the_simulated_values(tmp_path):
    cfg = TripConfig(cycle="urban", duration_s=150.0, seed=21)
    trip = simulate(cfg)
    rng = np.random.default_rng(np.random.SeedSequence(cfg.seed).spawn(8)[6])
    blocks = gateway.fms_frames(gateway.load_dbc(), trip.signals, True, cfg.start_unix_s, cfg.duration_s,
                                cfg.dt_s, rng, {"EngSpeedAtIdlePoint1": 600, "EngReferenceTorque": 1600,
                                                "EngMomentOfInertia": 3.2}, cfg.vehicle_id)
    paths = write(trip, tmp_path / "t.log.gz")
    decoded = decode_log(paths["log"])
    checked = 0
    for b in blocks:
        if b.can_id < 0:
            continue
        got = decoded[(b.name, b.can_id & 0xFF)]
        assert len(got) == len(b.t)
        assert np.allclose([t for t, _ in got], b.t, atol=1e-6)
        m = DB.get_message_by_name(b.name)
        for s in m.signals:
            expected = b.values.get(s.name)
            values = np.array([np.nan if v[s.name] is None else v[s.name] for _, v in got])
            if expected is None:  # not sent: all ones
                assert np.isnan(values).all(), (b.name, s.name)
                continue
            assert np.array_equal(np.isnan(values), np.isnan(expected)), (b.name, s.name)
            ok = ~np.isnan(expected)
            assert np.all(np.abs(values[ok] - expected[ok]) <= s.scale * 0.5 + 1e-9), (b.name, s.name)
            checked += ok.sum()
    assert checked > 50000


def test_bus_layout_is_realistic(tmp_path):
    paths = write(simulate(TripConfig(truth="gas_p340", cycle="urban", duration_s=120.0, seed=22)),
                  tmp_path / "g.log")
    decoded = decode_log(paths["log"])
    eec1 = [t for t, _ in decoded[("EEC1", 0x00)]]
    assert np.median(np.diff(eec1)) == pytest.approx(0.02, abs=1e-3)
    assert ("ETC2", 0x03) in decoded and ("CCVS1", 0x31) in decoded and ("LFE1", 0x31) in decoded
    # The gas truck has no fuel rate on CAN: its LFE1 carries none.
    assert all(v["EngFuelRate"] is None for _, v in decoded[("LFE1", 0x00)])
    assert paths["flow"].exists()
    # EC1 and VI arrive by BAM (TP.CM 0xEC00 from the engine).
    ids = {m.arbitration_id for m in can.LogReader(str(paths["log"]))}
    assert 0x1CECFF00 in ids and 0x1CEBFF00 in ids
