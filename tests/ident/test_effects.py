"""ident.effects: the effect library and its regressors."""
import numpy as np
import pytest

from fuelid.ident import effects as fx
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


def test_engine_map_is_a_quadratic_surface_of_the_models_inputs_and_the_relative_load():
    """engine_map: ñ·T̃, ñ², T̃² in krpm and kNm (deviations from the operating point), and the relative load
    (EEC2 SPN 92, as a fraction) when the engine reports it."""
    ds = hidden.make(None, n=2000)
    n, T = (ds.u - ds.u0).T / 1000.0
    reg = fx.EFFECTS["engine_map"].build(ds)
    assert reg.units == ("krpm.kNm", "krpm2", "kNm2") and reg.names[0] == "speed x torque"
    assert np.allclose(reg.x, np.column_stack([n * T, n * n, T * T]))
    ds.extra["EEC2.EngPercentLoadAtCurrentSpeed"] = np.clip(ds.u[:, 1] / 20.0, 0, 100)
    reg = fx.EFFECTS["engine_map"].build(ds)
    assert reg.units[-1] == "1" and np.allclose(reg.x[:, 3], np.clip(ds.u[:, 1] / 20.0, 0, 100) / 100.0)


def test_held_fills_gaps_with_the_last_value():
    assert np.array_equal(fx.held([np.nan, 1, np.nan, np.nan, 3, np.nan]), [1, 1, 1, 1, 3, 3])
