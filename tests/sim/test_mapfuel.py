"""The map-based engine truth: the VECTO map at the engine's instantaneous speed and torque, bounded by the
full-load curve, cut while motoring, a few % transient fuelling, LFE1 as the ECU reports it."""
import dataclasses
import tempfile
from pathlib import Path

import numpy as np
import pytest

from fuelid.logger.readers import read_frames
from fuelid.logger.recorder import Recorder
from fuelid.sim import mapfuel, route
from fuelid.sim.drive import DRIVE, simulate_drive
from fuelid.sim.effects import ALL_EFFECTS
from fuelid.sim.trip import TripConfig, simulate, write
from fuelid.sim.vecto import read_engine
from fuelid.sim.vehicle import Truck

DT = 0.01


@pytest.fixture(scope="module")
def vecto():
    return read_engine("vecto_325kW")


def test_steady_state_fuel_is_the_map_at_its_points(vecto):
    inside = vecto.map_nm <= vecto.full_load(vecto.map_rpm)
    for n, t, g_h in zip(vecto.map_rpm[inside], vecto.map_nm[inside], vecto.map_g_h[inside]):
        f = mapfuel.injected_fuel_l_h(vecto, np.full(300, n), np.full(300, t), DT)
        np.testing.assert_allclose(f, g_h / 835.0, rtol=1e-9)


def test_transient_fuelling_is_zero_when_steady_and_at_most_twice_the_urban_whtc_surcharge(vecto):
    steady = mapfuel.transient_factor(vecto, np.full(1000, 900.0), DT)
    assert np.all(steady == 1.0)
    step = np.r_[np.full(200, 200.0), np.full(800, 2000.0)]  # a full-load step within one 10 ms step
    k = mapfuel.transient_factor(vecto, step, DT)
    c_max = 2.0 * (1.04 - 1.0)
    assert np.all((k >= 1.0) & (k < 1.0 + c_max)) and k.max() > 1.0 + 0.4 * c_max
    assert k[-1] - 1.0 < 0.01 * (k.max() - 1.0)  # gone again within 8 s (τ = 1 s)
    ramp = mapfuel.transient_factor(vecto, np.linspace(200.0, 2000.0, 1000), DT)  # 10 s ramp: mild
    assert 1.0 < ramp.max() < 1.0 + 0.1 * c_max


def test_the_benchmarks_steady_engine_is_the_same_map_without_transient_fuelling(vecto):
    steady = read_engine(Path(__file__).resolve().parents[2] / "benchmarks" / "engines" / "325kW_steady.veng")
    np.testing.assert_array_equal(steady.map_g_h, vecto.map_g_h)
    np.testing.assert_array_equal(steady.full_load_nm, vecto.full_load_nm)
    assert (steady.idle_speed_rpm, steady.inertia_kgm2) == (vecto.idle_speed_rpm, vecto.inertia_kgm2)
    step = np.r_[np.full(200, 200.0), np.full(800, 2000.0)]
    assert np.all(mapfuel.transient_factor(steady, step, DT) == 1.0)


def test_the_ecu_reports_each_update_periods_mean_one_period_late():
    f = np.r_[np.full(50, 10.0), np.full(50, 20.0)]
    out = mapfuel.ecu_reported(f, DT, 0.1)
    assert np.all(out[:60] == 10.0) and np.all(out[60:] == 20.0)
    np.testing.assert_allclose(mapfuel.ecu_reported(np.arange(30.0), DT, 0.1)[10:20], 4.5)


def test_the_drive_engine_is_the_vecto_engine(vecto):
    e = mapfuel.sim_engine(vecto)
    rpm = np.arange(600.0, 2200.0, 7.0)
    np.testing.assert_allclose(e.max_brake_torque_nm(rpm), vecto.full_load(rpm) - e.aux_nm, atol=1e-9)
    np.testing.assert_allclose(e.drag_torque_nm(rpm), -vecto.motoring(rpm) + e.aux_nm, atol=1e-9)
    assert e.reference_torque_nm == 2134.0 and e.idle_speed_rpm == 600.0 and e.inertia_kgm2 == vecto.inertia_kgm2


def _flywheel_nm(trip, vecto):
    """Flywheel torque from combustion at t_s [N m]: indicated minus friction (= the motoring torque)."""
    tr = trip.truth
    return tr["torque_true_pct"] / 100.0 * vecto.max_torque_nm + vecto.motoring(tr["engine_speed_rpm"])


def test_torque_never_exceeds_full_load_and_speed_stays_in_the_curve(trip, vecto):
    t = trip(truth="map", cycle="mixed", duration_s=900.0, seed=31)
    rpm = t.signals["engine_speed_rpm"]
    assert rpm.min() > 550.0 and rpm.max() < 2200.0
    torque = _flywheel_nm(t, vecto)
    rpm_ts = t.truth["engine_speed_rpm"]  # the drive tabulates the curve per 1 rpm: allow that step
    assert np.all(torque <= np.maximum(vecto.full_load(rpm_ts), vecto.full_load(rpm_ts - 1.0)) + 1e-6)
    assert torque.max() > 0.9 * vecto.max_torque_nm  # the drive uses the whole curve


def test_no_fuel_while_motoring_and_idle_fuel_from_the_map(trip, vecto):
    t = trip(truth="map", cycle="rural", duration_s=900.0, seed=32, hilliness=1.8)
    tr, s = t.truth, t.signals
    motoring = s["torque_reported_pct"] <= 0.0  # indicated torque 0: flywheel torque = the motoring torque
    k = int(0.2 / DT)  # the ECU reports the mean of its previous 0.1 s period
    held = np.convolve(motoring, np.ones(k), mode="full")[: len(motoring)] == k
    assert held.sum() > 2000 and np.all(s["fuel_rate_l_h"][held] == 0.0)
    idle = (tr["speed_kmh"] == 0) & (tr["t_s"] > 20) & (np.abs(tr["engine_speed_rpm"] - 600.0) < 5.0)
    idle_l_h = vecto.fuel_g_h(600.0, 32.0) / 835.0  # the map at idle speed with the 32 Nm auxiliaries
    assert idle.sum() > 50 and abs(np.median(tr["fuel_true"][idle]) - idle_l_h) < 0.1


def test_the_paper_effects_switch_on_over_the_map_engine(trip):
    base = trip(truth="map", cycle="mixed", duration_s=600.0, seed=33).truth
    dpf = trip(truth="map", cycle="mixed", duration_s=600.0, seed=33, effects=(("dpf_regeneration", 0.1),)).truth
    active = dpf["dpf_active"] > 0
    before = np.r_[False, active[:-1]]  # LFE1 shows a change 0.1 s late: skip the sample after each switch
    on, off = active & before, ~active & ~before
    assert on.sum() > 100 and off.sum() > 100
    np.testing.assert_allclose(dpf["fuel_true"][on], 1.1 * base["fuel_true"][on], rtol=1e-6)
    np.testing.assert_array_equal(dpf["fuel_true"][off], base["fuel_true"][off])


def test_a_map_trip_decodes_with_the_engines_reference_torque(trip, vecto):
    t = trip(truth="map", cycle="urban", duration_s=120.0, seed=34)
    records = []

    class Sink:
        columns = None  # no message columns (logger.columns)

        def add_channel(self, topic, schema):
            pass

        def set_metadata(self, metadata):
            pass

        def write(self, topic, log_time_ns, record):
            records.append((topic, record))

    with tempfile.TemporaryDirectory() as tmp:
        paths = write(t, Path(tmp) / "trip.log.gz")
        recorder = Recorder(Sink())
        for frame in read_frames(paths["log"]):
            recorder.on_message_received(frame)
    ec1 = [r for topic, r in records if topic == "/j1939/EC1"]
    assert ec1 and all(r["EngReferenceTorque"] == vecto.max_torque_nm for r in ec1)
    assert all(r["EngSpeedAtIdlePoint1"] == 600.0 for r in ec1)
    fuel = [r["EngFuelRate"] for topic, r in records if topic == "/j1939/LFE1" and r.get("EngFuelRate") is not None]
    assert len(fuel) > 1000 and 0.0 <= min(fuel) and max(fuel) < 100.0


def test_a_pt1_full_load_slows_the_torque_build_up(vecto):
    """With a PT1 time constant τ in the .vfld, each 10 ms step of the drive moves the brake torque at most
    1 - exp(-dt/τ) of the way to the static full load (plus the 1 rpm table step)."""
    tau = 1.5
    slow = dataclasses.replace(vecto, pt1_s=np.full(len(vecto.fld_rpm), tau))
    engines = {"static": mapfuel.sim_engine(vecto), "pt1": mapfuel.sim_engine(slow)}
    drives = {}
    for name, engine in engines.items():
        rng = np.random.default_rng(5)
        profile = route.speed_profile("urban", 600.0, DT, rng)
        road = route.road_profile("urban", 20000.0, rng)
        drives[name] = simulate_drive(profile, road, Truck(), engine, np.full(len(profile.v_ref), 1.2), DT,
                                      np.random.default_rng(6))
    d, engine = drives["pt1"], engines["pt1"]
    both = (d.mode[1:] == DRIVE) & (d.mode[:-1] == DRIVE)
    tb, rpm = d.brake_torque_nm, d.engine_speed_rpm
    t_max = np.maximum(engine.max_brake_torque_nm(rpm[1:]), engine.max_brake_torque_nm(rpm[1:] - 1.0))
    bound = tb[:-1] + (t_max - tb[:-1]) * -np.expm1(-DT / tau)
    assert np.all(tb[1:][both] <= np.maximum(bound[both], tb[:-1][both]) + 1e-6)
    def rise(x):  # fastest build-up in gear [Nm/s] (launches and shift ramps are the gearbox's, not the PT1's)
        in_gear = (x.mode[1:] == DRIVE) & (x.mode[:-1] == DRIVE)
        return np.percentile(np.diff(x.brake_torque_nm)[in_gear] / DT, 99.9)

    assert rise(d) < 0.5 * rise(drives["static"])


def test_the_fuel_noise_leaves_the_noise_free_truth_and_sets_the_floor(trip):
    quiet = trip(truth="map", cycle="mixed", duration_s=900.0, seed=31)  # the trip of the envelope test above
    noisy = trip(truth="map", cycle="mixed", duration_s=900.0, seed=31, noise=0.5)
    assert quiet.summary["noise_floor"]["rms"] == 0.0 and not quiet.truth["fuel_noise_bin"].any()
    np.testing.assert_array_equal(noisy.truth["fuel_true"], quiet.truth["fuel_true"])
    floor = noisy.summary["noise_floor"]
    assert 0.3 < floor["rms"] < 0.7 and floor["unit"] == "L/h"  # 0.5 L/h std, less while the injection is cut
    assert floor["rms"] == pytest.approx(np.sqrt(np.mean(noisy.truth["fuel_noise_bin"] ** 2)), abs=1e-6)
    cut = quiet.signals["fuel_rate_l_h"] == 0.0  # no noise while no fuel is injected: the ECU reports 0
    assert cut.mean() > 0.02 and np.all(noisy.signals["fuel_rate_l_h"][cut] == 0.0)


def test_every_built_in_effect_runs_on_each_shared_engine(shared_engine):
    effects = tuple((name, e.default) for name, e in ALL_EFFECTS.items())
    t = simulate(TripConfig(truth="map", engine=str(shared_engine), cycle="urban", duration_s=120.0, seed=36,
                            effects=effects, noise=0.5))
    assert {e["name"] for e in t.summary["effects"]} == set(ALL_EFFECTS)
    assert np.all(np.isfinite(t.truth["fuel_measured"])) and t.truth["fuel_measured"].mean() > 1.0
    engine = t.summary["fuel_truth"]["engine"]
    assert engine["file"] == shared_engine.name and engine["name"] == read_engine(shared_engine).name
    assert t.summary["engine"]["reference_torque_nm"] == read_engine(shared_engine).max_torque_nm
