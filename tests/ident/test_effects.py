"""ident.effects: the effect library and its regressors."""
import numpy as np
import pytest

from fuelid.ident import effects as fx
from fuelid.ident.enginemap import EngineMap
from fuelid.ident.modeldata import apply_effects
from tests.ident import hidden


def test_builtin_effects_are_documented_with_signals_and_spns():
    required = {"inertia", "fuel_delay", "overrun_cutoff", "power_nonlinearity", "idle_fuelling", "gear_shift",
                "dpf_regeneration", "cold_engine", "ambient", "engine_fan", "retarder", "pto", "friction"}
    assert required <= set(fx.EFFECTS)
    for e in fx.EFFECTS.values():
        assert e.physics and e.signals and len(e.spns) == len(e.signals)
        assert all(fx.spn_of(s) == p for s, p in zip(e.signals, e.spns)), e.id
        assert e.form in ("input", "nonlinearity", "regime", "shift")


def test_effect_ids_match_the_simulator():
    sim_effects = pytest.importorskip("fuelid.sim.effects")
    assert set(sim_effects.EFFECTS) <= set(fx.EFFECTS)


def test_generic_candidates_name_every_other_signal_and_never_the_fuel():
    ds = hidden.make(None, n=2000)
    ds.extra["LFE1.EngInstantaneousFuelEconomy"] = np.random.default_rng(0).normal(size=len(ds.t))
    ids = {e.id for e in fx.generic_effects(ds)}
    assert {"level:ET1.EngOilTemp1", "rate:ET1.EngOilTemp1", "level:XX.UnknownSignal",
            "state:XX.UnknownState"} <= ids
    assert not any("LFE1" in i or "DPFC1" in i for i in ids)  # output-derived, or claimed by dpf_regeneration
    assert "level:AMB.BarometricPress" not in ids  # constant
    oil = next(e for e in fx.generic_effects(ds) if e.id == "level:ET1.EngOilTemp1")
    assert oil.spns == (175,)


def test_generic_candidates_take_every_form_that_can_apply_to_their_signal():
    """A quantity (DBC unit) as level, rate and scaling the fuel, even when sent in whole units with few values
    (intake air in whole °C); a percent torque also as a torque through the torque path; an enumeration (no unit,
    whole steps) as its states; never a torque form for a temperature."""
    ds = hidden.make(None, n=2000)
    ds.extra["AMB.EngAirInletTemp"] = np.round(35 + 5 * np.sin(ds.t / 60.0))
    ds.extra["EEC3.EstEngParasiticLossesPercentTorque"] = np.where(np.sin(ds.t / 90.0) > 0, 5.0, 0.0)
    ds.extra["CCVS1.CruiseCtrlActive"] = (np.sin(ds.t / 120.0) > 0.5).astype(float)
    forms = {}
    for e in fx.generic_effects(ds):
        form, sig = e.id.split(":", 1)
        forms.setdefault(sig, set()).add(form)
    assert forms["AMB.EngAirInletTemp"] == {"level", "rate", "scales"}
    assert forms["EEC3.EstEngParasiticLossesPercentTorque"] == {"level", "rate", "scales", "torque"}
    assert forms["CCVS1.CruiseCtrlActive"] == {"state"}
    assert forms["XX.UnknownState"] == {"state"}  # not in the DBC: a few whole values
    parasitic = fx.get_effect("torque:EEC3.EstEngParasiticLossesPercentTorque", ds)
    reg = parasitic.build(ds)
    assert reg.units == ("Nm",) and reg.x.max() == 5.0 * 1600.0 / 100.0  # % of the 1600 Nm reference torque
    assert parasitic.enters == "torque" and fx.get_effect("scales:AMB.EngAirInletTemp", ds).enters == "scales_fuel"


def test_a_raw_signal_scaling_the_fuel_is_centred_alike_on_other_data():
    """scales:SIG is centred on the identification data's median, kept with the model for other data."""
    ds = hidden.make(None, n=2000)
    ds.extra["AMB.EngAirInletTemp"] = np.round(35 + 5 * np.sin(ds.t / 60.0))
    first = apply_effects(ds, ["scales:AMB.EngAirInletTemp"])
    ref = float(np.median(ds.extra["AMB.EngAirInletTemp"]))
    assert first.parameters == {"scales:AMB.EngAirInletTemp": ref}
    assert np.allclose(first.u[:, 0], ds.extra["AMB.EngAirInletTemp"] - ref)
    ds.extra["AMB.EngAirInletTemp"] = ds.extra["AMB.EngAirInletTemp"] + 10.0  # a hotter day
    other = apply_effects(ds, ["scales:AMB.EngAirInletTemp"], first.parameters)
    assert np.allclose(other.u[:, 0], first.u[:, 0] + 10.0)


def test_share_beyond_inputs_is_what_a_static_map_of_speed_and_torque_leaves_of_a_signal():
    """A desired speed that is the engine speed but in a few neutral stretches, a demand torque that is a curved
    function of speed and torque, an oil temperature that moves on its own: what a quadratic map of speed and
    torque leaves of each [share of variance]."""
    ds = hidden.make(None, n=4000)
    speed, torque = ds.u[:, 0], ds.u[:, 1]
    neutral = (np.arange(len(ds.t)) % 1000) < 20
    ds.extra["EEC3.EngDesiredOperatingSpeed"] = np.where(neutral, 900.0, speed)
    ds.extra["EEC1.EngDemandPercentTorque"] = 100.0 * (torque / 2000.0) ** 2 + 1e-3 * speed
    ds.extra["EEC1.EngDemandPercentTorque"][::7] = np.nan  # not known on every sample: left out of the fit
    assert fx.share_beyond_inputs(ds, "EEC1.EngDemandPercentTorque") < 1e-6
    assert 0.0 < fx.share_beyond_inputs(ds, "EEC3.EngDesiredOperatingSpeed") < 0.1
    assert fx.share_beyond_inputs(ds, "ET1.EngOilTemp1") > 0.5
    ds.extra["AMB.BarometricPress"][:] = 101.0
    assert fx.share_beyond_inputs(ds, "AMB.BarometricPress") == 0.0


def test_regressors_units_and_physics():
    ds = hidden.make(None, n=2000)
    reg = fx.EFFECTS["inertia"].build(ds)
    assert reg.units == ("Nm",)  # J from EC1 × dω/dt
    omega = ds.u[:, 0] * 2 * np.pi / 60
    assert np.allclose(reg.x[:, 0], 3.2 * np.gradient(omega, ds.t))
    regen = fx.EFFECTS["dpf_regeneration"].build(ds)
    assert regen.x.shape[1] == 3 and set(np.unique(regen.x[:, 0])) == {0.0, 1.0}
    del ds.extra["DPFC1.DPFActiveRegenStatus"]
    assert fx.EFFECTS["dpf_regeneration"].build(ds) is None


def test_engine_map_is_the_maps_part_beyond_its_plane_and_the_torque_rise():
    """engine_map: x_map = m(n, T), the static map fitted on the data beyond its plane (ident.enginemap), and the
    transient fuelling's torque rise r = max(dT/dt, 0) [kNm/s] and r·s(n, T)/f_scale; x_map through B/F with one pole,
    the rise columns through a first-order lag; a map given (a model's) is the one used."""
    ds = hidden.make(None, n=2000)
    rise = np.maximum(np.gradient(ds.u[:, 1], ds.t), 0.0) / 1000.0
    reg = fx.EFFECTS["engine_map"].build(ds)
    assert reg.units == ("L/h", "kNm/s", "kNm/s") and reg.names[0] == "map beyond the plane"
    assert reg.orders == (fx.MAP_ORDERS, fx.RISE_ORDERS, fx.RISE_ORDERS)
    emap = EngineMap.from_dict(fx.static_engine_map(ds))
    n, T = ds.u.T
    assert np.allclose(reg.x, np.column_stack([emap.beyond_plane(n, T), rise, rise * emap(n, T) / emap.fuel_scale]))
    # beyond the plane: no speed- or torque-linear part over the data it was fitted on (all but the few samples the
    # fuel's alignment leaves out); its level above the fuel at the operating point
    P = np.column_stack([np.ones_like(n), n - n.mean(), T - T.mean()])
    coef = np.linalg.lstsq(P, reg.x[:, 0], rcond=None)[0]
    assert np.abs(coef[1:] * [n.std(), T.std()]).max() < 1e-2 * reg.x[:, 0].std()
    assert emap.plane[0] == ds.y0
    flat = emap.with_coefficients(np.zeros(emap.coef.size), (0.0, 0.0, 0.0)).to_dict()
    given = fx.EFFECTS["engine_map"].bind(fx.EFFECTS["engine_map"], flat).build(ds)
    assert np.allclose(given.x[:, [0, 2]], 0.0) and np.allclose(given.x[:, 1], rise)


def test_torque_rise_is_the_held_torques_central_difference():
    """r_k = max((T_k+1 − T_k−1)/(t_k+1 − t_k−1), 0) of the torque held over a missing sample (one-sided at the ends);
    units: kNm/s for N·m, 100 %/s for %. Sample k needs only samples up to k + 1 (the online estimator runs one
    sample late)."""
    t = 0.5 * np.arange(6)
    T = np.array([100.0, 300.0, np.nan, 200.0, 700.0, 600.0])
    assert np.allclose(fx.torque_rise(T, t, "Nm"), [0.4, 0.2, 0, 0.4, 0.4, 0])
    assert np.allclose(fx.torque_rise(T, t, "%"), [4.0, 2.0, 0, 4.0, 4.0, 0])
    later = T.copy()
    later[5:] = 5000.0
    assert np.array_equal(fx.torque_rise(later, t, "Nm")[:4], fx.torque_rise(T, t, "Nm")[:4])


def test_held_fills_gaps_with_the_last_value():
    assert np.array_equal(fx.held([np.nan, 1, np.nan, np.nan, 3, np.nan]), [1, 1, 1, 1, 3, 3])
