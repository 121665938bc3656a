"""Each physical effect changes the fuel (or the reported torque) only where it physically should.

Every test compares a trip with the effect against the same trip (same seed: same route, driving and noise)
without it, on the noise-free truth.
"""
import numpy as np
import pytest

from fuelid.sim import effects as fx

BASE = dict(cycle="mixed", duration_s=600.0, seed=31)


def pair(trip, name, magnitude=None, **overrides):
    kw = {**BASE, **overrides}
    m = fx.ALL_EFFECTS[name].default if magnitude is None else magnitude
    return trip(**kw), trip(**kw, effects=((name, m),)), m


def test_every_effect_is_documented():
    for e in fx.EFFECTS.values():
        assert e.unit and e.signals and e.spns and e.description
    assert fx.parse_effects(["dpf_regeneration", "fuel_delay=0.17"]) == {"dpf_regeneration": 0.1, "fuel_delay": 0.17}
    with pytest.raises(ValueError):
        fx.parse_effects(["warp_drive"])


def test_generic_effects_act_only_through_decoded_bus_signals_fuelid_has_no_effect_for():
    from fuelid.ident import effects as ident_effects
    from fuelid.ident.effectfile import dbc_signals

    claimed = {s for e in ident_effects.EFFECTS.values() for s in e.signals}
    for name, e in fx.GENERIC_EFFECTS.items():
        assert name not in ident_effects.EFFECTS and e.unit and e.description
        assert set(e.signals) <= dbc_signals() and not set(e.signals) & claimed
        assert fx.parse_effects([name]) == {name: e.default}


def test_hot_intake_air_scales_the_fuel_above_30_c_of_spn172(trip):
    base, on, m = pair(trip, "hot_intake_air", cycle="rural", hilliness=1.8, ambient_c=25.0)
    inlet = on.truth["inlet_c"]
    hot = inlet > 30.0
    assert 0.1 < hot.mean() < 0.9 and inlet.max() > 35.0
    np.testing.assert_allclose(on.truth["fuel_true"], base.truth["fuel_true"]
                               * (1 + m * np.maximum(inlet - 30.0, 0.0) / 10.0), rtol=1e-5)
    # what the bus says (AMB SPN 172) is the inlet temperature that scales the fuel
    np.testing.assert_allclose(on.signals["inlet_c"][::30], np.repeat(inlet, 30)[: len(on.t_s)][::30], atol=0.5)
    assert "inlet_c" not in base.truth


def test_auxiliary_load_burns_fuel_for_torque_eec3_reports_and_eec1_leaves_out(trip):
    base, on, m = pair(trip, "auxiliary_load")
    running = on.truth["auxiliary_torque_nm"] > 0
    assert 0.2 < running.mean() < 0.8
    np.testing.assert_array_equal(on.truth["torque_reported_pct"], base.truth["torque_reported_pct"])
    assert on.truth["torque_true_pct"][running].mean() > base.truth["torque_true_pct"][running].mean()
    assert on.truth["fuel_true"][running].mean() > base.truth["fuel_true"][running].mean() + 0.5
    far = np.convolve(running, np.ones(200), mode="same") == 0  # a minute away from any episode
    assert far.any() and np.abs(on.truth["fuel_true"] - base.truth["fuel_true"])[far].max() < 0.05
    aux = on.signals["aux_pct"]
    assert np.ptp(aux) > 0 and np.ptp(base.signals["aux_pct"]) == 0


def test_dpf_regeneration_adds_fuel_only_while_spn3700_is_active(trip):
    base, on, m = pair(trip, "dpf_regeneration")
    active = on.truth["dpf_active"] > 0
    assert active.any() and not active.all()
    assert np.all(on.signals["dpf_active"][::100] == on.signals["dpf_active"][::100].astype(bool))
    np.testing.assert_allclose(on.truth["fuel_true"][~active], base.truth["fuel_true"][~active])
    np.testing.assert_allclose(on.truth["fuel_true"][active], base.truth["fuel_true"][active] * (1 + m), rtol=1e-6)
    assert base.truth["dpf_active"].sum() == 0


def test_overrun_cutoff_gives_zero_fuel_only_when_motoring(trip):
    base, on, _ = pair(trip, "overrun_cutoff", cycle="rural", hilliness=1.8)
    motoring = on.truth["overrun"] > 0
    assert motoring.sum() > 20
    assert np.all(on.truth["fuel_true"][motoring] == 0.0)
    assert base.truth["fuel_true"][motoring].mean() > 0.0
    np.testing.assert_allclose(on.truth["fuel_true"][~motoring], base.truth["fuel_true"][~motoring])
    # Motoring on the bus: no torque and the pedal released.
    assert np.all(on.truth["torque_reported_pct"][motoring] <= 0.5)
    assert np.all(on.truth["pedal_pct"][motoring] == 0.0)


def test_cold_engine_enrichment_fades_as_the_coolant_warms(trip):
    base, on, m = pair(trip, "cold_engine", duration_s=1200.0, ambient_c=2.0)
    coolant = on.truth["coolant_c"]
    assert coolant[0] == pytest.approx(2.0, abs=1.5) and coolant[-1] > 80.0
    assert base.truth["coolant_c"].min() > 80.0
    ratio = on.truth["fuel_true"] / np.maximum(base.truth["fuel_true"], 1e-9)
    burning = base.truth["fuel_true"] > 1.0
    np.testing.assert_allclose(ratio[burning], (1 + m * np.clip((86.0 - coolant) / 70.0, 0, 1))[burning], rtol=1e-3)
    early, late = burning & (on.truth["t_s"] < 120), burning & (coolant >= 85.9)
    assert ratio[early].mean() > 1.1 and ratio[late].mean() == pytest.approx(1.0, abs=1e-3)


def test_fuel_delay_shifts_the_cross_correlation_peak(trip):
    base, on, _ = pair(trip, "fuel_delay", 0.4)
    a, b = base.signals["fuel_rate_l_h"], on.signals["fuel_rate_l_h"]
    a, b = a - a.mean(), b - b.mean()
    lags = np.arange(-100, 101)
    xc = [np.dot(a[100:-100], np.roll(b, -lag)[100:-100]) for lag in lags]
    assert lags[int(np.argmax(xc))] * on.config.dt_s == pytest.approx(0.4, abs=0.011)


@pytest.mark.parametrize("engine, magnitude", [("paper", None), ("paper", 5.0), ("map", None)])
def test_inertia_hides_j_domega_dt_from_the_reported_torque_only(trip, engine, magnitude):
    """The engine keeps its own inertia (paper 3.2 kg·m², VECTO 325 kW 5.15 kg·m², reported in EC1): the drive
    and the fuel are those of the trip without the effect; only the bus torque is net of J dω/dt, J the
    magnitude."""
    truth = dict(truth="map") if engine == "map" else {}
    base, on, m = pair(trip, "inertia", magnitude, cycle="urban", **truth)
    np.testing.assert_array_equal(on.signals["engine_speed_rpm"], base.signals["engine_speed_rpm"])
    np.testing.assert_allclose(on.truth["fuel_true"], base.truth["fuel_true"])
    np.testing.assert_allclose(on.truth["torque_true_pct"], base.truth["torque_true_pct"])
    J = on.summary["engine"]["inertia_kgm2"]
    assert J == base.summary["engine"]["inertia_kgm2"] == pytest.approx(5.1498 if engine == "map" else 3.2)
    j_dw = fx.inertia_torque_nm(m, on.signals["engine_speed_rpm"], on.config.dt_s)
    hidden = base.signals["torque_reported_pct"] - on.signals["torque_reported_pct"]
    reference_nm = on.summary["engine"]["reference_torque_nm"]
    np.testing.assert_allclose(hidden, 100.0 * j_dw / reference_nm, atol=1e-9)
    steady = np.abs(j_dw) < 1e-6
    assert steady.any() and np.abs(j_dw).max() > 50.0


def test_engine_fan_adds_fuel_not_torque_while_engaged(trip):
    base, on, _ = pair(trip, "engine_fan", cycle="rural", hilliness=1.8, ambient_c=28.0)
    fan = on.truth["fan_pct"] > 30.0
    assert fan.any() and (base.truth["fan_pct"] < 9.0).all()
    engaged = on.signals["fan_state"] == 4  # SPN 977: excessive coolant temperature
    assert on.signals["coolant_c"][engaged].mean() > 94.0 and on.signals["coolant_c"].max() >= 95.0
    np.testing.assert_allclose(on.truth["torque_reported_pct"], base.truth["torque_reported_pct"])
    diff = on.truth["fuel_true"] - base.truth["fuel_true"]
    far = np.convolve(fan, np.ones(200), mode="same") == 0  # a minute away from any engagement
    assert diff[fan].mean() > 0.5 and np.abs(diff[far]).max() < 0.05


def test_gear_shift_transient_only_just_after_shifts(trip):
    base, on, m = pair(trip, "gear_shift", cycle="urban")
    ratio = on.signals["fuel_rate_l_h"] / np.maximum(base.signals["fuel_rate_l_h"], 1e-9)
    s = on.signals
    shifted = np.zeros(len(ratio), bool)
    for i in np.flatnonzero(np.diff(s["current_gear"]) != 0):
        shifted[i:i + int(2.0 / on.config.dt_s)] = True  # clutch closes, 0.3 s ramp, 1.5 s transient
    burning = base.signals["fuel_rate_l_h"] > 0.5
    assert np.all(np.abs(ratio[~shifted & burning] - 1.0) < 1e-9)
    assert ratio[shifted & burning].max() == pytest.approx(1 + m, abs=0.02)


def test_ambient_air_density_scales_fuel(trip):
    base, on, m = pair(trip, "ambient", cycle="rural", hilliness=2.0, altitude_m=500.0, ambient_c=-2.0,
                       ambient_drift_c=18.0)
    rho = on.truth["air_density_kg_m3"]
    assert rho.max() - rho.min() > 0.05
    burning = base.truth["fuel_true"] > 1.0
    ratio = on.truth["fuel_true"][burning] / base.truth["fuel_true"][burning]
    np.testing.assert_allclose(ratio, 1 + m * (fx.AIR_DENSITY_REF_KG_M3 - rho[burning]) / fx.AIR_DENSITY_REF_KG_M3,
                               rtol=2e-3)


def test_power_nonlinearity_adds_speed_times_torque(trip):
    base, on, m = pair(trip, "power_nonlinearity")
    t = on.truth
    expected = np.maximum(t["fuel_model"] + m * (t["engine_speed_rpm"] - 600) / 1000 * t["torque_true_pct"] / 100, 0)
    np.testing.assert_allclose(t["fuel_true"], expected, atol=1e-3)


def test_several_effects_at_once(trip):
    t = trip(**BASE, effects=(("dpf_regeneration", 0.1), ("fuel_delay", 0.17), ("overrun_cutoff", 1.0)))
    names = [e["name"] for e in t.summary["effects"]]
    assert names == ["dpf_regeneration", "fuel_delay", "overrun_cutoff"]
    assert t.truth["fuel_true"].mean() > trip(**BASE).truth["fuel_true"].mean()
