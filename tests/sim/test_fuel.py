import json
from pathlib import Path

import numpy as np
import pytest

from fuelid.sim import fuel

PAPER_JSON = Path(__file__).resolve().parents[3] / "shared" / "design" / "paper_models.json"


def test_embedded_coefficients_match_the_design_json():
    if not PAPER_JSON.exists():
        pytest.skip(f"{PAPER_JSON} not available")
    printed = json.loads(PAPER_JSON.read_text())
    for name, key in fuel.PAPER_JSON_KEYS.items():
        for part in ("Gw", "GT", "H"):
            assert {k: v for k, v in fuel.PAPER_MODELS[name][part].items()} == printed[key][part], (name, part)


def test_printed_diesel_noise_model_is_unstable_and_the_simulated_one_is_not():
    d_printed = fuel.PAPER_MODELS["diesel_p320"]["H"]["D"]
    assert np.max(np.abs(np.roots(d_printed))) == pytest.approx(1.033, abs=0.001)
    for truth in fuel.TRUTHS.values():
        c, d = fuel.noise_polynomials(truth)
        assert np.max(np.abs(np.roots(d))) < 1.0 and np.max(np.abs(np.roots(c))) <= 1.0
        assert c[0] == pytest.approx(1.0) and d[0] == pytest.approx(1.0)


def test_gains_are_plausible_in_percent_and_litres_per_hour():
    """Full load (100 % of 1600 Nm) at 1200 rpm is ~200 kW: ~48 L/h of diesel at 200 g/kWh."""
    truth = fuel.TRUTHS["diesel_p320"]
    y = fuel.deterministic_fuel(truth, np.full(2000, 1200.0), np.full(2000, 100.0))
    assert 42.0 < y[-1] < 54.0
    idle = fuel.deterministic_fuel(truth, np.full(200, 600.0), np.full(200, 7.0))
    assert idle[-1] == pytest.approx(truth.idle_fuel)


def test_noise_has_the_chosen_standard_deviation():
    truth = fuel.TRUTHS["diesel_p320"]
    v = fuel.fuel_noise(truth, 200000, np.random.default_rng(0))
    assert v.std() == pytest.approx(truth.noise_std, rel=0.1)
