"""The fuel lag `fuelid identify --fuel-lag auto` keeps (ident.fuellag), on synthetic trips of an engine whose ECU
either averages its fuel over each 100 ms report period or samples it at the report."""
import dataclasses

import numpy as np
import pytest

from fuelid.ident.dataset import Dataset
from fuelid.ident.fuellag import LagChoice, LagReason, at_times, candidate_lag_s, identify_lag_chosen
from fuelid.ident.modelchoice import ModelKind
from tests.ident import engine_data
from tests.ident.hidden import STRUCTURE, _held, _lag

TS, REPORT = 0.3, 0.1  # [s] the dataset's bins, the ECU's report period
PER_BIN = round(TS / REPORT)


def recording(averaging: bool, bins: int = 6000, seed: int = 0):
    """build(lag) of a trip: speed [rpm] and torque [Nm] and the fuel rate [L/h] reported every 100 ms, the fuel
    (the curved engine's steady state, tests.ident.engine_data, with 0.3 L/h of report noise) that of the report
    period before each report when `averaging`, else that at the report; a bin holds the reports logged in it,
    or with the lag those of one report earlier."""
    rng = np.random.default_rng(seed)
    n = bins * PER_BIN + PER_BIN
    speed = np.clip(600 + _lag(_held(n, rng, 0, 1300), 6.0) + _lag(rng.normal(0, 30, n), 3.0), 550, 2000)
    torque = np.clip(112 + _lag(_held(n, rng, -90, 1550), 1.0) + rng.normal(0, 150, n), 20, 1700)
    fuel = engine_data.steady_state(speed, torque) + rng.normal(0, 0.3, n)
    report = np.r_[fuel[0], fuel[:-1]] if averaging else fuel  # report j: the fuel of [j − 1, j] or of j

    def bin_means(x: np.ndarray, shift: int) -> np.ndarray:
        return x[shift:shift + bins * PER_BIN].reshape(bins, PER_BIN).mean(axis=1)

    def build(lag: float) -> Dataset:
        u = np.column_stack([bin_means(speed, 0), bin_means(torque, 0)])
        return Dataset(Ts=TS, t=np.arange(bins) * TS, u=u, y=bin_means(report, round(lag / REPORT)),
                       input_names=("EEC1.EngSpeed", "EngTorque"), input_units=("rpm", "Nm"),
                       output_name="LFE1.EngFuelRate", output_unit="L/h", u0=np.array([600.0, 112.0]),
                       y0=float(engine_data.steady_state(600.0, 112.0)), valid=np.ones(bins, bool),
                       cycle=(np.arange(bins) // int(600 / TS)).astype(np.int64), fuel_lag_s=lag,
                       fuel_period_s=REPORT)
    return build


@pytest.mark.parametrize("averaging", [True, False])
def test_the_lag_is_kept_exactly_when_the_ecu_averages_its_fuel(averaging):
    model, ds = identify_lag_chosen(recording(averaging), STRUCTURE, min_segment_s=30.0)
    choice = LagChoice.from_json(model.info["fuel_lag_choice"])
    assert choice.candidate_s == REPORT and len(choice.held_out.d) >= 3
    if averaging:
        assert choice.reason is LagReason.BETTER and choice.lag_s == REPORT == ds.fuel_lag_s == model.fuel_lag_s
        assert choice.held_out.better  # the mean clears the t margin and the floor
    else:
        assert choice.reason is LagReason.NOT_BETTER and choice.lag_s == 0.0 == model.fuel_lag_s
        assert choice.held_out.mean < 0  # the lag misaligns a sampling ECU's fuel: worse, not merely no better
    assert model.info["model_choice"]["chosen"] == "engine"  # the curved engine, decided on the fuel as logged
    assert "held-out" in choice.line("L/h") and LagChoice.from_json(choice.to_json()) == choice


def test_the_kind_is_decided_on_the_fuel_as_logged_and_the_lag_judged_for_it(monkeypatch):
    """The held-out stage decides the kind once (AUTO, as logged); at the lag only the kept kind is fitted."""
    from fuelid.ident import fuellag
    asked = []

    def spy(ds, masks, structure, effects, kind, **fit):
        asked.append((ds.fuel_lag_s, kind))
        return held_out_choice(ds, masks, structure, effects, kind, **fit)

    held_out_choice = fuellag.held_out_choice
    monkeypatch.setattr(fuellag, "held_out_choice", spy)
    model, _ = identify_lag_chosen(recording(True), STRUCTURE, min_segment_s=30.0)
    assert asked == [(0.0, ModelKind.AUTO), (REPORT, ModelKind.ENGINE)]
    assert model.info["model_choice"]["chosen"] == "engine" and model.info["model_choice"]["reason"] == "better"


def test_a_kind_that_cannot_be_identified_at_the_lag_keeps_the_fuel_as_logged(monkeypatch):
    from fuelid.errors import InputError
    from fuelid.ident import fuellag
    held_out_choice = fuellag.held_out_choice

    def failing_at_the_lag(ds, *args, **fit):
        if ds.fuel_lag_s:
            raise InputError("no map at this lag")
        return held_out_choice(ds, *args, **fit)

    monkeypatch.setattr(fuellag, "held_out_choice", failing_at_the_lag)
    model, ds = identify_lag_chosen(recording(True, bins=3000), STRUCTURE, kind=ModelKind.LINEAR, min_segment_s=30.0)
    choice = LagChoice.from_json(model.info["fuel_lag_choice"])
    assert choice.reason is LagReason.FAILED and choice.lag_s == 0.0 == ds.fuel_lag_s == model.fuel_lag_s
    assert choice.held_out.mean is None and "could not be identified" in choice.line("L/h")


def test_no_candidate_or_too_little_data_keeps_the_fuel_as_logged():
    build = recording(True, bins=3000)
    no_period = identify_lag_chosen(lambda lag: dataclasses.replace(build(lag), fuel_period_s=TS), STRUCTURE,
                                    kind=ModelKind.LINEAR, min_segment_s=30.0)[0]
    assert no_period.info["fuel_lag_choice"]["reason"] == "no_candidate" and no_period.fuel_lag_s == 0.0
    short = identify_lag_chosen(recording(True, bins=1000), STRUCTURE, kind=ModelKind.LINEAR, min_segment_s=30.0)[0]
    assert short.info["fuel_lag_choice"]["reason"] == "too_short" and short.fuel_lag_s == 0.0


def test_the_candidate_is_a_report_period_below_ts():
    ds = engine_data.trip(n=100)
    assert candidate_lag_s(dataclasses.replace(ds, fuel_period_s=0.1)) == 0.1
    assert candidate_lag_s(dataclasses.replace(ds, fuel_period_s=0.100000256)) == 0.1  # a logger clock's jitter
    for period in (0.0, 0.3, 1.0):
        assert candidate_lag_s(dataclasses.replace(ds, fuel_period_s=period)) is None


def test_blocks_are_the_same_bins_on_a_grid_that_starts_elsewhere():
    ds = engine_data.trip(n=100)
    later = dataclasses.replace(ds, t=ds.t[3:], valid=ds.valid[3:], y=ds.y[3:], u=ds.u[3:])
    block = ds.t[10:20]
    np.testing.assert_array_equal(later.t[at_times(later, block)], block)
    assert not at_times(later, ds.t[:3]).any()  # bins the other grid does not have
