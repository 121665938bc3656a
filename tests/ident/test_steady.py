"""ident.steady: the whole model's steady state at a point — the settled simulation of the inputs the model's own
effects build (the engine map's included) — its standard error against sampling the parameters, the reference
condition it states, and the reference values it learns from a truck's data."""
import numpy as np
import pytest

from fuelid.errors import InputError
from fuelid.ident.dataset import Dataset
from fuelid.ident.enginemap import EngineMap, fit_map
from fuelid.ident.hammerstein import MAP_COLUMN, RISE_COLUMN, RISE_MAP_COLUMN
from fuelid.ident.polymodel import PolyModel, from_theta, simulate
from fuelid.ident.steady import data_reference, steady_fuel, steady_inputs

LOAD = "EEC2.EngPercentLoadAtCurrentSpeed"
REGEN = "DPFC1.DPFActiveRegenStatus"


def fitted_map() -> dict:
    """An engine map (ident.enginemap) fitted to a curved fuel surface [L/h] over 600–1900 rpm × 0–2400 N·m about idle
    (600 rpm, 0 N·m, 2 L/h): 2 + 4 ñ + 20 T̃ + 0.5 ñT̃ + 0.3 ñ² + 0.8 T̃², ñ, T̃ in krpm and kNm."""
    rng = np.random.default_rng(5)
    n, T = rng.uniform(600, 1900, 4000), rng.uniform(0, 2400, 4000)
    dn, dT = (n - 600.0) / 1000.0, T / 1000.0
    fuel = 2.0 + 4.0 * dn + 20.0 * dT + 0.5 * dn * dT + 0.3 * dn ** 2 + 0.8 * dT ** 2
    return fit_map(n, T, fuel, (600.0, 0.0), 2.0, ("rpm", "Nm", "L/h")).to_dict()


MAP = fitted_map()


def map_model(map_gain=1.0, cov_scale=1e-10):
    """Fuel [L/h] from speed [rpm], torque [N·m], the engine map's three columns (the map beyond its plane, of unit
    static gain times map_gain, and the torque rise's two), the engine's relative load as a bus-signal level (what a
    truck's data show, L = 40 %/kNm · T) and a DPF regeneration's four (it scales the fuel: x, x·ñ, x·T̃, x·m),
    about idle (600 rpm, 0 N·m, 2 L/h)."""
    B = [[0, 0.004, 0.002], [0.01, 0.004], [map_gain], [0.01], [0.001], [0.02], [3.0], [0.001], [0.002], [0.1]]
    F = [[1, -0.5], [1, -0.3]] + [[1.0]] * 4 + [[1, -0.2]] * 4
    names = ("speed", "torque", MAP_COLUMN, RISE_COLUMN, RISE_MAP_COLUMN, LOAD) + tuple(f"regeneration {k}"
                                                                                       for k in (1, 2, 3, 4))
    m = PolyModel(A=[1.0, -0.2], B=B, F=F, C=[1, 0.2], D=[1, -0.7], Ts=0.3, nk=(1,) + (0,) * 9, input_names=names,
                  input_units=("rpm", "Nm") + ("1",) * 8, output_unit="L/h", u0=(600.0, 0.0) + (0.0,) * 8, y0=2.0,
                  effects=("engine_map", f"level:{LOAD}", "dpf_regeneration"),
                  info={"effect_parameters": {"engine_map": MAP},
                        "steady_reference": {LOAD: {"surface": [0, 0, 40.0, 0, 0, 0, 0]}}})
    n = m.structure.n_params
    m.covariance = cov_scale * (np.eye(n) + 0.3 * np.ones((n, n)))
    return m


def settled_simulation(model, speed, torque, n=2000):
    """The model simulated to rest [L/h] on its inputs held at the point's values (ident.steady.steady_inputs)."""
    du, _ = steady_inputs(model, speed, torque)
    return simulate(model, np.tile(np.asarray(model.u0, float) + du, (n, 1)))[-1]


def held(model, speed, torque, n=600, **signals):
    """A dataset of n samples with speed [rpm] and torque [N·m] held and the given bus signals constant."""
    return Dataset(Ts=0.3, t=0.3 * np.arange(n), u=np.tile([speed, torque], (n, 1)).astype(float), y=np.zeros(n),
                   input_names=("speed", "torque"), input_units=("rpm", "Nm"), output_name="fuel", output_unit="L/h",
                   u0=np.array(model.u0[:2]), y0=model.y0, valid=np.ones(n, bool), cycle=np.full(n, -1),
                   extra={k: np.full(n, float(v)) for k, v in signals.items()})


@pytest.mark.parametrize("point", [(1000, 600), (1400, 1800), (800, 100)])
def test_steady_fuel_is_the_settled_simulation_of_the_models_own_inputs(point):
    m = map_model()
    s = steady_fuel(m, *point)
    settled = settled_simulation(m, *point)
    assert s.value == pytest.approx(settled, rel=1e-9) and s.unit == "L/h"
    assert s.reference[REGEN] == "no DPF regeneration" and "data" in s.reference[LOAD]


def test_the_engine_map_changes_the_steady_state_by_its_static_curvature():
    n, T = 1400.0, 1800.0
    with_map, plane = steady_fuel(map_model(), n, T).value, steady_fuel(map_model(map_gain=0.0), n, T).value
    curvature = EngineMap.from_dict(MAP).beyond_plane(np.array([n]), np.array([T]))[0]  # no rise when held
    assert with_map - plane == pytest.approx(curvature / 0.8, rel=1e-9) and abs(curvature) > 0.1  # through 1/A(1)


def test_a_regenerating_reference_burns_more():
    m = map_model()
    assert steady_fuel(m, 1200, 1200, reference={REGEN: 1}).value > steady_fuel(m, 1200, 1200).value + 2.5


def test_standard_error_matches_sampling_the_parameters():
    m = map_model(cov_scale=1e-8)
    draws = np.random.default_rng(0).multivariate_normal(m.theta, m.covariance, size=2000)
    values = [steady_fuel(from_theta(t, m.structure, m.Ts, u0=m.u0, y0=m.y0, input_names=m.input_names,
                                     input_units=m.input_units, effects=m.effects, info=m.info), 1200, 1200).value
              for t in draws]
    assert steady_fuel(m, 1200, 1200).std_error == pytest.approx(np.std(values), rel=0.08)


def test_the_maps_coefficient_uncertainty_adds_to_the_standard_error_as_sampling_both_says():
    """θ and the map's coefficients c drawn from their covariances (independent): the spread of the steady state is
    σ = √(gᵀPg + φᵀCφ)."""
    m = map_model(cov_scale=1e-8)
    k = np.asarray(MAP["coefficients"]).size
    cov_c = np.eye(k) + 0.5 * np.ones((k, k))  # [(L/h)²]
    m.info = {**m.info, "effect_parameters": {"engine_map": {**MAP, "covariance": cov_c.tolist()}}}
    rng = np.random.default_rng(1)
    thetas = rng.multivariate_normal(m.theta, m.covariance, size=1500)
    coefs = rng.multivariate_normal(np.ravel(MAP["coefficients"]), cov_c, size=1500)
    values = [steady_fuel(from_theta(t, m.structure, m.Ts, u0=m.u0, y0=m.y0, input_names=m.input_names,
                                     input_units=m.input_units, effects=m.effects,
                                     info={**m.info, "effect_parameters": {"engine_map": {
                                         **MAP, "coefficients": c.reshape(np.shape(MAP["coefficients"])).tolist()}}}),
                          1200, 1200).value for t, c in zip(thetas, coefs)]
    sigma = steady_fuel(m, 1200, 1200).std_error
    assert sigma == pytest.approx(np.std(values), rel=0.08)
    assert sigma > 1.5 * steady_fuel(map_model(cov_scale=1e-8), 1200, 1200).std_error


def test_a_signal_without_a_reference_value_is_named():
    m = map_model()
    m.info = {}
    with pytest.raises(InputError, match=LOAD):
        steady_fuel(m, 1200, 1200)


def test_data_reference_fits_what_the_point_decides_and_takes_the_median_of_the_rest():
    m = map_model()
    rng = np.random.default_rng(1)
    ds = held(m, 0, 0, n=3000)
    ds.u = np.column_stack([rng.uniform(700, 1800, 3000), rng.uniform(0, 2400, 3000)])
    ds.extra = {LOAD: 100.0 * ds.u[:, 1] / (2600.0 - 0.3 * ds.u[:, 0]), REGEN: rng.uniform(0, 1, 3000) < 0.1}
    ds.extra[REGEN] = ds.extra[REGEN].astype(float)
    ref = data_reference(m, ds)
    assert set(ref) == {LOAD} and "surface" in ref[LOAD]  # the regeneration state has its stated reference
    m.info = {**m.info, "steady_reference": ref}
    assert steady_fuel(m, 1200, 1500).value == pytest.approx(settled_simulation(m, 1200, 1500), abs=1e-6)
    load = 100.0 * 1500 / (2600.0 - 360.0)  # the relative load the data show at the point [%]
    assert steady_fuel(m, 1200, 1500, reference={LOAD: load}).value == pytest.approx(
        steady_fuel(m, 1200, 1500).value, abs=0.5)


def test_an_effect_on_a_bus_signal_is_held_at_its_reference():
    """A generic effect (scales:SIG, centred on the level the model carries) at that level adds nothing; a level:SIG
    effect at the value the truck's data show (its median) adds its gain times that value."""
    base = map_model(map_gain=0.0)
    sig = "ET1.EngOilTemp1"
    for spec, extra_info, B, expected in [
            (f"scales:{sig}", {"effect_parameters": {f"scales:{sig}": 95.0}}, [[0.1], [0.01], [0.02], [0.05]], 0.0),
            (f"level:{sig}", {"steady_reference": {sig: {"median": 90.0}}}, [[0.1]], 0.1 * 90.0 / 0.8)]:
        m = PolyModel(A=base.A, B=base.B + B, F=base.F + [[1.0]] * len(B), C=base.C, D=base.D, Ts=0.3,
                      nk=base.nk + (0,) * len(B), input_names=base.input_names + (spec,) * len(B), input_units=base.input_units + ("1",) * len(B), output_unit="L/h",
                      u0=base.u0 + (0.0,) * len(B), y0=2.0, effects=base.effects + (spec,),
                      info={**base.info, **extra_info,
                            "effect_parameters": {**base.info["effect_parameters"],
                                                  **extra_info.get("effect_parameters", {})},
                            "steady_reference": {**base.info["steady_reference"], **extra_info.get("steady_reference", {})}})
        s = steady_fuel(m, 1200, 1200)
        assert s.value - steady_fuel(base, 1200, 1200).value == pytest.approx(expected, abs=1e-9), spec
        assert sig in s.reference


def test_the_fuel_signals_delay_leaves_the_steady_state_as_it_is():
    """A shift of the fuel signal (fuel_delay) has no input: held for ever, a delayed constant is the constant, and
    the fuel signal it names needs no reference value."""
    m = map_model()
    delayed = PolyModel(A=m.A, B=m.B, F=m.F, C=m.C, D=m.D, Ts=m.Ts, nk=m.nk, input_names=m.input_names,
                        input_units=m.input_units, output_unit="L/h", u0=m.u0, y0=m.y0,
                        effects=m.effects + ("fuel_delay",), covariance=m.covariance,
                        info={**m.info, "effect_parameters": {**m.info["effect_parameters"], "fuel_delay": 0.6}})
    s = steady_fuel(delayed, 1200, 1200)
    assert s.value == pytest.approx(steady_fuel(m, 1200, 1200).value, rel=1e-12)
    assert "LFE1.EngFuelRate" not in s.reference
