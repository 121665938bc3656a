"""ident.effectfile: effects the engineer defines in a TOML file, tested and added like the built-in ones."""
import dataclasses
import textwrap
from pathlib import Path

import numpy as np
import pytest

from fuelid.errors import InputError
from fuelid.ident import effects as fx
from fuelid.ident.effectfile import defined_effects, effects_of_model, read_effects_file
from fuelid.ident.modeldata import apply_effects, model_data
from tests.ident import hidden

EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "effects-example.toml"

DPF = """
[[effect]]
id = "regen"
name = "DPF regeneration"
enters = "scales_fuel"
unit = "1"
sign = 1
x = { state = "DPFC1.DPFActiveRegenStatus", on = [1] }
explanation = "fuel is {percent:+.0f} % while the DPF regenerates ({signals})"
"""


def write(tmp_path, text, name="fx.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def test_the_shipped_example_reads_and_names_its_signals_and_spns():
    effects = {e.id: e for e in read_effects_file(EXAMPLE)}
    assert set(effects) == {"regen_from_file", "hot_intake_air", "parasitic_torque"}
    hot = effects["hot_intake_air"]
    assert hot.signals == ("AMB.EngAirInletTemp",) and hot.spns == (172,) and hot.enters == "scales_fuel"
    assert effects["parasitic_torque"].enters == "torque" and effects["parasitic_torque"].spns == (2978,)
    assert effects["regen_from_file"].form == "regime" and hot.form == "input"


def test_an_on_off_state_scaling_the_fuel_reproduces_the_builtin_dpf_regeneration_exactly(tmp_path):
    ds = hidden.make("dpf_regeneration", n=3000)
    (regen,) = read_effects_file(write(tmp_path, DPF))
    mine, builtin = regen.build(ds), fx.EFFECTS["dpf_regeneration"].build(ds)
    assert np.array_equal(mine.x, builtin.x) and mine.units == builtin.units
    assert (regen.enters, regen.form, regen.lags, regen.orders, regen.sign) == \
        tuple(getattr(fx.EFFECTS["dpf_regeneration"], k) for k in ("enters", "form", "lags", "orders", "sign"))
    a, b = apply_effects(ds, ["regen"], defined=[regen]), apply_effects(ds, ["dpf_regeneration"])
    assert np.array_equal(a.u, b.u) and a.orders == b.orders and a.effects == ("regen",)


def test_transforms_compose(tmp_path):
    ds = hidden.make(None, n=1000)
    path = write(tmp_path, """
        [[effect]]
        id = "cold_oil_while_fast"
        name = "cold oil at speed"
        enters = "additive"
        unit = "K.rpm"
        x = { product = [ { deficit = "ET1.EngOilTemp1", below = 90.0 }, "EEC1.EngSpeed" ] }
        [[effect]]
        id = "gear_rate"
        name = "gear changes"
        enters = "torque"
        unit = "1/s"
        x = { rate = { state = "ETC2.TransCurrentGear", between = [3, 6] } }
        """)
    cold, gear = read_effects_file(path)
    oil = fx.held(ds.extra["ET1.EngOilTemp1"])
    assert np.allclose(cold.build(ds).x[:, 0], np.maximum(90.0 - oil, 0.0) * ds.u[:, 0])
    g = ds.extra["ETC2.TransCurrentGear"]
    assert np.allclose(gear.build(ds).x[:, 0], np.gradient(((g >= 3) & (g <= 6)).astype(float), ds.t))
    assert cold.lags == (0, 1, 2) and gear.lags == (0,) and cold.build(ds).x.shape == (1000, 1)


@pytest.mark.parametrize("change, message", [
    ("id = \"Bad Id\"", "effect 'Bad Id': id: 'Bad Id' must be lower-case"),
    ("id = \"dpf_regeneration\"", "effect 'dpf_regeneration': id: 'dpf_regeneration' is a built-in effect"),
    ("enters = \"sideways\"", "effect 'regen': enters: 'sideways' is not one of additive, scales_fuel, torque, shift"),
    ("unit = 3", "effect 'regen': unit: must be a string"),
    ("sign = 2", "effect 'regen': sign: must be +1"),
    ("x = { state = \"DPFC1.NoSuchSignal\", on = [1] }", "effect 'regen': x.state: 'DPFC1.NoSuchSignal' is not a "
                                                         "signal of the DBC"),
    ("x = { state = \"DPFC1.DPFActiveRegenStatus\" }", "effect 'regen': x: a state needs exactly one of on"),
    ("x = { deficit = \"ET1.EngCoolantTemp\" }", "effect 'regen': x.below: missing"),
    ("x = { deficit = \"ET1.EngCoolantTemp\", below = \"warm\" }", "effect 'regen': x.below: must be a number"),
    ("x = { product = [\"ET1.EngCoolantTemp\"] }", "effect 'regen': x.product: must be a list of at least two"),
    ("x = { rate = \"ET1.EngCoolantTemp\", window = 3 }", "effect 'regen': x.window: unknown parameter of rate"),
    ("x = { integral = \"ET1.EngCoolantTemp\" }", "effect 'regen': x: needs exactly one of signal, state"),
    ("explanation = \"fuel is {pct} higher\"", "effect 'regen': explanation: unknown field {pct}"),
    ("explanation = \"fuel is {percent:q} higher\"", "effect 'regen': explanation: not a valid template"),
    ("colour = \"red\"", "effect 'regen': colour: unknown field"),
    ("orders = [0, 1, 0]", "effect 'regen': orders: must be [nb ≥ 1"),
])
def test_each_bad_field_is_one_line_naming_the_file_the_effect_and_the_field(tmp_path, change, message):
    key = change.split(" =")[0]
    lines = [ln for ln in DPF.strip().splitlines() if not ln.startswith(key + " =")] + [change]
    path = write(tmp_path, "\n".join(lines) + "\n")
    with pytest.raises(InputError) as err:
        read_effects_file(path)
    text = str(err.value)
    assert text.startswith(f"{path}: ") and message in text and "\n" not in text, text


@pytest.mark.parametrize("text, message", [
    ("[[effect]\nid = 1", "not TOML"),
    ("title = 'x'\n", "unknown top-level field 'title'"),
    ("", "no [[effect]] table"),
    ("[[effect]]\nname = 'a'\n", "effect: id: missing"),
    (DPF + DPF, "effect 'regen': id: defined twice"),
    ("[[effect]]\nid = 'lag'\nname = 'meter lag'\nenters = 'shift'\nx = 'LFE1.EngFuelRate'\n",
     "effect 'lag': x: a shift (the fuel signal's delay) has no transform"),
])
def test_bad_files_are_one_line_errors(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(InputError, match=None) as err:
        read_effects_file(path)
    assert message in str(err.value) and str(err.value).startswith(str(path)), err.value
    with pytest.raises(InputError, match="cannot read"):
        read_effects_file(tmp_path / "missing.toml")


def test_an_id_defined_in_two_files_is_refused(tmp_path):
    a, b = write(tmp_path, DPF, "a.toml"), write(tmp_path, DPF, "b.toml")
    with pytest.raises(InputError, match="effect 'regen' is defined twice"):
        defined_effects([a, b])


def test_a_model_identified_with_a_defined_effect_carries_it_and_runs_without_the_file(tmp_path):
    ds = hidden.make("dpf_regeneration", n=3000)
    (regen,) = read_effects_file(write(tmp_path, DPF))
    model = hidden.identify(ds, hidden.STRUCTURE, ["regen"], defined=[regen])
    assert model.effects == ("regen",) and model.info["effect_definitions"]["regen"]["enters"] == "scales_fuel"
    (again,) = effects_of_model(model)
    assert again.id == "regen" and again.signals == regen.signals
    u, y = model_data(model, ds)
    assert np.array_equal(u[:, 2:], fx.EFFECTS["dpf_regeneration"].build(
        dataclasses.replace(ds, u0=np.asarray(model.u0[:2]))).x)


def test_a_shift_defined_in_a_file_advances_the_fuel_like_the_builtin_delay(tmp_path):
    ds = hidden.make("fuel_delay", n=1000)
    (lag,) = read_effects_file(write(tmp_path, """
        [[effect]]
        id = "meter_lag"
        name = "flow meter lag"
        enters = "shift"
        """))
    mine, builtin = apply_effects(ds, ["meter_lag=0.3"], defined=[lag]), apply_effects(ds, ["fuel_delay=0.3"])
    assert np.array_equal(mine.y, builtin.y) and mine.parameters == {"meter_lag": 0.3}
    assert lag.signals == ("LFE1.EngFuelRate",) and lag.spns == (183,) and lag.sign == 1


def test_python_plugins_add_effects_through_the_entry_point_group(monkeypatch):
    mine = dataclasses.replace(fx.EFFECTS["pto"], id="my_pto", source="")

    class EntryPoint:
        name, value = "mine", "pkg.module:EFFECTS"

        def load(self):
            return [mine]

    monkeypatch.setattr(fx.importlib.metadata, "entry_points",
                        lambda group: [EntryPoint()] if group == fx.PLUGIN_GROUP else [])
    fx.plugin_effects.cache_clear()
    try:
        assert fx.get_effect("my_pto").source == "plug-in mine"
        assert [e.id for e in defined_effects()] == ["my_pto"]
        EntryPoint.load = lambda self: "not an effect"
        fx.plugin_effects.cache_clear()
        with pytest.raises(InputError, match=r"effect plug-in mine \(pkg.module:EFFECTS\): not an Effect"):
            fx.plugin_effects()
    finally:
        fx.plugin_effects.cache_clear()
