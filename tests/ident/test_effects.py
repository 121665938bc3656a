"""ident.effects: the effect library, its regressors, the fuel shift and apply_effects."""
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


def test_held_fills_gaps_with_the_last_value():
    assert np.array_equal(fx.held([np.nan, 1, np.nan, np.nan, 3, np.nan]), [1, 1, 1, 1, 3, 3])


def test_fractional_shift_and_sweep_find_a_hidden_delay():
    """Seed 2's static model and ±1 s sweep: a 0.4 s fuel delay is found within ±0.1 s."""
    rng = np.random.default_rng(3)
    ts, n = 0.3, 6000
    t = np.arange(n) * ts
    speed = 600 + 1300 * np.abs(np.sin(t / 37)) + np.convolve(rng.normal(0, 60, n), np.ones(5) / 5, "same")
    torque = 800 + 700 * np.sin(t / 11 + 1) + np.convolve(rng.normal(0, 100, n), np.ones(3) / 3, "same")
    fuel = 2.5 + 0.002 * (speed - 600) + 0.03 * torque + 1e-5 * (speed - 600) * torque / 10
    measured = fx.shift_signal(fuel, -0.4 / ts) + rng.normal(0, 0.3, n)  # lags by 0.4 s

    def static_rmse(tau):
        y = fx.shift_signal(measured, tau / ts)
        X = np.column_stack([np.ones(n), speed, torque, speed * torque, speed**2, torque**2])
        r = y - X @ np.linalg.lstsq(X, y, rcond=None)[0]
        return float(np.sqrt(np.mean(r[10:-10] ** 2)))

    sweep = fx.sweep_fuel_shift(static_rmse)
    assert abs(sweep["best_s"] - 0.4) <= 0.1
    assert len(sweep["shifts_s"]) == 21


def test_apply_effects_gives_inputs_orders_and_structure():
    ds = hidden.make(None, n=2000)
    out = fx.apply_effects(ds, ["inertia", "dpf_regeneration", "fuel_delay=0.3"])
    assert out.u.shape == (2000, 4) and out.effects == ("inertia", "dpf_regeneration", "fuel_delay")
    assert out.parameters == {"fuel_delay": 0.3}
    s = out.extend(hidden.STRUCTURE)
    assert s.n_inputs == 6 and s.nb[2:] == (2, 1, 1, 1)
    assert np.allclose(out.y[5:-5], fx.shift_signal(ds.y, 1.0)[5:-5])
    with pytest.raises(ValueError, match="unknown effect"):
        fx.apply_effects(ds, ["warp_drive"])
    with pytest.raises(ValueError, match="fuel_delay needs"):
        fx.apply_effects(ds, ["fuel_delay"])
