"""ident.diagnosis.size: a recommended effect's size in the model built with it matches the size hidden in the data,
in the units its form states, and an engineer's explanation template is filled with it."""
import re
import warnings
from pathlib import Path

import pytest

from fuelid.ident import diagnosis as dg
from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.size import EffectSize, against_physics, effect_size
from fuelid.ident.effectfile import read_effects_file
from fuelid.ident.identify import identify_model
from tests.ident import hidden

EXAMPLE = Path(__file__).resolve().parents[3] / "docs" / "effects-example.toml"


def built(effect: str, spec: str, seed: int):
    ds = hidden.make(effect, n=4000, seed=seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return identify_model(ds, hidden.STRUCTURE, [spec]), ds


@pytest.mark.parametrize("effect, spec, form, unit, truth, tol", [
    ("dpf_regeneration", "dpf_regeneration", "state", "L/h", 11.0, 2.5),  # +11 % while on: percent
    ("inertia", "inertia", "torque", "Nm per Nm", 1.0, 0.25),  # J = J_bus: 1 N·m of torque per N·m of J_bus dω/dt
    ("fuel_delay", "fuel_delay=0.4", "shift", "s", 0.4, 1e-9),  # τ as the model carries it
])
def test_the_size_of_an_effect_is_the_size_hidden_in_the_data(effect, spec, form, unit, truth, tol):
    model, ds = built(effect, spec, seed=21)
    z = effect_size(model, ds, fx.EFFECTS[effect])
    assert z.form == form and z.value_unit == unit and z.unit == "L/h" and z.rms > 0
    assert (z.percent if form == "state" else z.value) == pytest.approx(truth, abs=tol)


def test_a_model_without_the_effect_has_no_size():
    model, ds = built("dpf_regeneration", "dpf_regeneration", seed=22)
    assert effect_size(model, ds, fx.EFFECTS["cold_engine"]) is None


def test_a_recommended_effect_says_its_size_and_a_defined_one_fills_its_template():
    defined = read_effects_file(EXAMPLE)
    regen = next(e for e in defined if e.id == "regen_from_file")
    ds = hidden.make("dpf_regeneration", n=4000, seed=13)
    d = dg.diagnose(hidden.fitted(ds), ds, effects=defined, candidates=[regen, fx.EFFECTS["cold_engine"]])
    top = d.to_json()["candidates"][0]
    assert top["recommended"] and top["size"]["form"] == "state" and 8 < top["size"]["percent"] < 14
    said = re.search(r"fuel is \+(\d+) % while the DPF regenerates \(DPFC1.DPFActiveRegenStatus \(SPN 3700\)\)",
                     top["explanation"])
    assert said and abs(int(said[1]) - top["size"]["percent"]) <= 0.5
    assert all(c["size"] is None for c in d.to_json()["candidates"][1:])


def _sizes(values, baseline=None):
    base = baseline or [10.0] * len(values)
    return [EffectSize("state", v, "L/h", v / b, 100 * v / b, 1.0, "L/h", "1", b) for v, b in zip(values, base)]


def test_against_its_physics_only_when_the_folds_agree_beyond_their_spread():
    gear_shift, cutoff = fx.EFFECTS["gear_shift"], fx.EFFECTS["overrun_cutoff"]  # more fuel; scales it to less
    assert against_physics(gear_shift, _sizes([-0.50, -0.52, -0.49, -0.51, -0.50]), margin=2.0)
    assert not against_physics(gear_shift, _sizes([-0.5, 0.4, -0.6, 0.5, -0.3]), margin=2.0)  # within the spread
    assert not against_physics(gear_shift, _sizes([0.50, 0.52, 0.49, 0.51, 0.50]), margin=2.0)
    # a scaling effect by the direction of its relative change: lifting a negative fuel to 0 adds fuel but scales it
    # down; adding fuel to a fuel near 0 is no cut-off, however large the ratio's spread
    assert not against_physics(cutoff, _sizes([0.3, 0.31, 0.29, 0.3, 0.3], baseline=[-0.3] * 5), margin=2.0)
    assert against_physics(cutoff, _sizes([0.3, 0.31, 0.29, 0.3, 0.3], baseline=[0.01, 0.05, 0.002, 0.03, 0.02]),
                           margin=2.0)
    assert not against_physics(fx.EFFECTS["idle_fuelling"], _sizes([-1.0] * 5), margin=2.0)  # sign 0: either way
