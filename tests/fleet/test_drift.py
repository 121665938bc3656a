"""fleet.drift: steady-state fuel at reference points against the simulated steady state, its standard error
against the Monte-Carlo spread of the parameters, drift of a known size flagged and noise not flagged; on the
shipped map-engine trip (the README's front door), the identified model's steady fuel against the fuel measured
near the points, and two fits of the same truck on the same data within their error bars."""
from pathlib import Path

import numpy as np
import pytest

from fuelid.cli import main
from fuelid.ident.dataset import build_dataset
from fuelid.ident.identify import MIN_SEGMENT_S, identify_model
from fuelid.ident.diagnosis import diagnose, effects_to_add
from fuelid.ident.fuellag import identify_lag_chosen
from fuelid.ident.modelchoice import ModelKind, identify_chosen
from fuelid.ident.polymodel import Structure, parse_orders
from fuelid.ident.steady import data_reference

from fuelid.fleet.drift import DEFAULT_POINTS, SteadyFuel, drift, fleet_median, parse_points, steady_fuel, versus_median
from fuelid.ident.polymodel import PolyModel, from_theta, simulate

POINTS = parse_points("1000x600Nm,1400x1800Nm")


def engine_model(gain=1.0, cov_scale=1e-12, na=0):
    """Fuel [L/h] from speed [rpm] and torque [N·m] about idle (600 rpm, 0 N·m, 2 L/h); B scaled by gain."""
    A = [1.0, -0.2][: na + 1]
    m = PolyModel(A=A, B=[[0, gain * 0.004, gain * 0.002], [gain * 0.01, gain * 0.004]], F=[[1, -0.5], [1, -0.3]],
                  C=[1, 0.2], D=[1, -0.7], Ts=0.3, nk=(1, 0), input_units=("rpm", "Nm"), output_unit="L/h",
                  u0=(600.0, 0.0), y0=2.0)
    n = m.structure.n_params
    m.covariance = cov_scale * (np.eye(n) + 0.3 * np.ones((n, n)))
    return m


@pytest.mark.parametrize("na", [0, 1])
def test_steady_fuel_is_the_settled_simulation(na):
    m = engine_model(na=na)
    sf = steady_fuel(m, POINTS)
    for p, value in zip(POINTS, sf.per_point):
        y = simulate(m, np.tile([p.speed_rpm, p.torque], (400, 1)))
        assert value == pytest.approx(y[-1], rel=1e-12)
    assert sf.mean == pytest.approx(np.mean(sf.per_point)) and sf.unit == "L/h"


@pytest.mark.parametrize("na", [0, 1])
def test_standard_error_matches_monte_carlo(na):
    m = engine_model(cov_scale=1e-8, na=na)
    rng = np.random.default_rng(0)
    draws = rng.multivariate_normal(m.theta, m.covariance, size=4000)
    means = [steady_fuel(from_theta(t, m.structure, m.Ts, u0=m.u0, y0=m.y0, input_units=m.input_units),
                         POINTS).mean for t in draws]
    assert steady_fuel(m, POINTS).std_error == pytest.approx(np.std(means), rel=0.08)


def test_known_drift_is_flagged_and_noise_is_not():
    first, worn = steady_fuel(engine_model(), POINTS), steady_fuel(engine_model(gain=1.08), POINTS)
    d = drift(worn, first)
    # the +8 % is on the gains only; y0 (idle fuel) stays, so S grows by 8 % of its part above idle
    assert d.percent == pytest.approx(8.0 * (first.mean - 2.0) / first.mean, rel=1e-9)
    assert d.alert and d.std_error_percent < 0.1
    noisy = steady_fuel(engine_model(gain=1.08, cov_scale=1e-6), POINTS)
    assert noisy.mean == worn.mean and not drift(noisy, steady_fuel(engine_model(cov_scale=1e-6), POINTS)).alert
    assert not drift(steady_fuel(engine_model(gain=1.02), POINTS), first).alert  # under the 5 % threshold
    unknown = SteadyFuel(worn.per_point, worn.mean, None, "L/h")
    assert drift(unknown, first).alert and drift(unknown, first).std_error_percent is None


def test_points_and_units():
    assert [str(p) for p in DEFAULT_POINTS] == ["1000x600Nm", "1200x1200Nm", "1400x1800Nm"]
    assert parse_points(" 900 x 50% ,1200x75%")[1].torque_unit == "%"
    for bad in ["1000x600", "1000x600Nm,1200x50%", "x600Nm", "1000x600Nm;1200x1Nm", "0x600Nm", "9" * 390 + "x600Nm"]:
        with pytest.raises(ValueError):
            parse_points(bad)
    with pytest.raises(ValueError, match="rpm and %"):
        steady_fuel(engine_model(), parse_points("1000x50%"))
    assert versus_median(11.0, fleet_median([10.0, 9.0, 11.0])) == pytest.approx(10.0)
    assert fleet_median([]) is None and versus_median(1.0, None) is None


TRIP = Path(__file__).resolve().parents[2] / "replay_logs" / "map_effect_dpf_regeneration_20min.log.gz"
NEAREST = 100  # samples: the fuel measured near a point is their mean (a standard error that does not depend on
#               how often the trip passes the point)


def fuel_measured_near(ds, point, samples: int = NEAREST) -> float:
    """The mean fuel [fuel unit] of the `samples` valid samples nearest the point, in distances of 100 rpm and
    150 N·m, without a DPF regeneration (the steady state's reference condition)."""
    regenerating = ds.extra.get("DPFC1.DPFActiveRegenStatus", np.zeros(len(ds.y))) == 1
    d = np.hypot((ds.u[:, 0] - point.speed_rpm) / 100.0, (ds.u[:, 1] - point.torque) / 150.0)
    d[~ds.valid | regenerating | ~np.isfinite(ds.y)] = np.inf
    return float(ds.y[np.argsort(d)[:samples]].mean())


@pytest.fixture(scope="module")
def front_door(tmp_path_factory):
    """The trip's dataset and the front door's model: `fuelid identify`'s default model identified again with the
    effects its diagnosis recommends (`identify --effects-from`: the regeneration first), with the
    reference values a fleet job records."""
    mcap = tmp_path_factory.mktemp("drift") / "trip.mcap"
    assert main(["convert", str(TRIP), "-o", str(mcap), "--json"]) == 0
    structure = Structure(**parse_orders("paper"))
    before, ds = identify_lag_chosen(lambda lag: build_dataset([mcap], fuel_lag_s=lag), structure,
                                     min_segment_s=MIN_SEGMENT_S)
    effects = effects_to_add(diagnose(before, ds).to_json())
    model = identify_chosen(ds, structure, effects, kind=ModelKind(before.info["model_choice"]["chosen"]),
                            min_segment_s=MIN_SEGMENT_S, base=before)
    model.info["steady_reference"] = data_reference(model, ds)
    return ds, model


def test_front_door_steady_fuel_is_the_fuel_measured_near_the_points(front_door):
    """The engine model's steady fuel at the default points against the fuel measured near each: within 15 % at
    each and 10 % on their mean."""
    ds, model = front_door
    assert model.effects[:2] == ("engine_map", "dpf_regeneration") and model.info["model_choice"]["chosen"] == "engine"
    sf = steady_fuel(model, DEFAULT_POINTS)
    assert sf.reference["DPFC1.DPFActiveRegenStatus"] == "no DPF regeneration"
    measured = [fuel_measured_near(ds, p) for p in DEFAULT_POINTS]
    assert np.allclose(sf.per_point, measured, rtol=0.15), (sf.per_point, measured)
    assert sf.mean == pytest.approx(np.mean(measured), rel=0.10)


def test_two_fits_of_the_same_truck_on_the_same_data_do_not_drift(front_door):
    """The same model identified again with PEM started from the first: the drift is within its error bars."""
    ds, model = front_door
    again = identify_model(ds, Structure(**parse_orders("paper")), list(model.effects), init=model)
    again.info["steady_reference"] = data_reference(again, ds)
    d = drift(steady_fuel(again, DEFAULT_POINTS), steady_fuel(model, DEFAULT_POINTS))
    assert abs(d.percent) < 2 * d.std_error_percent and not d.alert
