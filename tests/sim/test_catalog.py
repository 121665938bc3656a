"""The catalog of shipped trips on another engine set, and the identification / validation pair of two days."""
import pytest

from fuelid.errors import InputError
from fuelid.sim import catalog
from fuelid.sim.catalog import CATALOG, SECOND_TRIP_SEED, on_engine, validation_pair


def test_a_diesel_entry_on_an_engine_set_is_the_map_truth_on_the_same_route():
    cfg = on_engine(CATALOG["effect_cold_engine_20min"], "vecto_325kW", 0.5)
    original = CATALOG["effect_cold_engine_20min"]
    assert (cfg.truth, cfg.engine, cfg.noise) == ("map", "vecto_325kW", 0.5)
    assert (cfg.cycle, cfg.seed, cfg.effects, cfg.ambient_c) == (original.cycle, original.seed, original.effects,
                                                                 original.ambient_c)
    assert on_engine(original) is original


def test_the_gas_truck_has_no_engine_set():
    with pytest.raises(InputError, match="gas truck"):
        on_engine(CATALOG["gas_ident_60min"], "vecto_325kW")


def test_the_validation_trip_is_another_day_of_the_same_truck():
    ident, valid = validation_pair(7, "map", "vecto_325kW", 0.5)
    assert valid.seed == 7 + SECOND_TRIP_SEED and valid.start_unix_s > ident.start_unix_s + ident.duration_s
    assert (ident.engine, valid.engine, ident.noise, valid.noise) == ("vecto_325kW",) * 2 + (0.5,) * 2
    assert valid.vehicle_id == ident.vehicle_id
    assert ident.duration_s == 3600.0 and valid.duration_s == 1800.0 and valid.mass_kg > ident.mass_kg


def test_the_command_line_names_the_noise_when_set(monkeypatch):
    monkeypatch.setitem(CATALOG, "x", on_engine(CATALOG["map_valid_40min"], noise=0.5))
    assert "--noise 0.5" in catalog.command_line("x") and "--noise" not in catalog.command_line("map_valid_40min")
