"""Identification with effects (ident.identify): the model with an effect the diagnosis recommends is never worse
than the model without it — on its own identification data (its loss V) and on another day's trip."""
import re
from types import SimpleNamespace

import numpy as np
import pytest

from fuelid.errors import InputError
from fuelid.ident import pem as pem_module
from fuelid.ident.dataset import Dataset
from fuelid.ident.identify import FitMemo, identify_model, kept_fit, refit_with_effects, with_inputs
from fuelid.ident.polymodel import Structure, simulate
from fuelid.ident.validation import evaluate
from tests.ident import hidden


def test_a_model_without_an_input_is_the_same_model_with_its_coefficients_at_zero():
    model = hidden.TRUE
    extended = with_inputs(model, Structure(nb=(1, 2, 2), nf=(1, 1, 1), nk=(2, 0, 0), nc=1, nd=1))
    u = np.random.default_rng(0).normal(size=(200, 3)) + [600.0, 112.0, 0.0]
    assert np.allclose(simulate(extended, u), simulate(model, u[:, :2]))


def test_a_model_built_through_a_memo_of_the_fits_before_it_is_the_same_to_the_bit():
    """The diagnosis builds the model with effects E, then with E and one more (ident.diagnosis.selection.built):
    the second build's effects added in turn are the first's fits again, and a FitMemo serves them instead of fitting
    them anew."""
    ds, _, _ = hidden.simulated("dpf_regeneration", 3000)
    memo = FitMemo()
    identify_model(ds, hidden.PAPER, ["dpf_regeneration"], memo=memo)
    assert len(memo) == 3  # the model without the effect, and the one with it from both starts
    served = identify_model(ds, hidden.PAPER, ["dpf_regeneration", "gear_shift"], memo=memo)
    assert len(memo) == 3 + 2  # only the two fits of the whole structure are new
    fitted = identify_model(ds, hidden.PAPER, ["dpf_regeneration", "gear_shift"])
    assert np.array_equal(served.theta, fitted.theta)
    assert served.info["starts"] == fitted.info["starts"]
    assert served.validation == fitted.validation


def test_a_memo_serves_a_copy_so_a_caller_cannot_change_the_next_fit():
    u = hidden.TRUE.u0 + np.random.default_rng(1).normal(size=(3000, 2)) * [100.0, 300.0]  # [rpm, N·m]
    y = simulate(hidden.TRUE, u) + np.random.default_rng(2).normal(0.0, 0.1, 3000)  # [L/h]
    memo, whole, halves = FitMemo(), [slice(0, 3000)], [slice(0, 1500), slice(1500, 3000)]
    first = memo.pem(u, y, hidden.STRUCTURE, hidden.TS, segments=whole, u0=hidden.TRUE.u0, y0=hidden.TRUE.y0)
    first.info["loss_V"] = -1.0
    again = memo.pem(u, y, hidden.STRUCTURE, hidden.TS, segments=whole, u0=hidden.TRUE.u0, y0=hidden.TRUE.y0)
    assert len(memo) == 1 and again.info["loss_V"] > 0.0
    memo.pem(u, y, hidden.STRUCTURE, hidden.TS, segments=halves, u0=hidden.TRUE.u0, y0=hidden.TRUE.y0)
    assert len(memo) == 2  # other segments: another fit


def test_a_memo_continues_a_fit_stopped_at_fewer_iterations_to_the_same_model_as_a_fit_from_scratch():
    """A warm-started refit stopped at its limit (3 iterations) and the model identify builds from the same model with
    the effect added in turn (100) start alike: the memo continues the first instead of starting the second again,
    the same to the bit."""
    ds, _, _ = hidden.simulated("dpf_regeneration", 3000)
    base = identify_model(ds, hidden.PAPER)
    memo = FitMemo()
    warm = refit_with_effects(base, ds, ["dpf_regeneration"], max_iter=3, memo=memo)
    assert len(memo) == 1 and warm.info["stop_reason"] == "max_iterations"
    served = identify_model(ds, hidden.PAPER, ["dpf_regeneration"], base=base, memo=memo)
    fitted = identify_model(ds, hidden.PAPER, ["dpf_regeneration"], base=base)
    assert len(memo) == 3  # the 3-iteration refit, then the whole structure from both starts
    assert np.array_equal(served.theta, fitted.theta)
    assert served.info["starts"] == fitted.info["starts"]
    assert served.info["starts"]["loss_V"]["effects added in turn"] <= warm.info["loss_V"]  # continued from it


def test_a_memo_serves_a_fit_that_stopped_short_of_its_limit_for_any_limit_above_its_iterations():
    """Levenberg–Marquardt's iterates do not depend on the limit: a fit that converged serves a longer one, the same
    to the bit as a fit made alone."""
    ds, _, _ = hidden.simulated("dpf_regeneration", 3000)
    base = identify_model(ds, hidden.PAPER)
    memo = FitMemo()
    converged = refit_with_effects(base, ds, ["dpf_regeneration"], max_iter=100, memo=memo)
    assert converged.info["stop_reason"] != "max_iterations"
    limit = converged.info["iterations"] + 1
    served = refit_with_effects(base, ds, ["dpf_regeneration"], max_iter=limit, memo=memo)
    alone = refit_with_effects(base, ds, ["dpf_regeneration"], max_iter=limit)
    assert memo.made == 1 and np.array_equal(served.theta, alone.theta)
    assert served.info["stopping"] == alone.info["stopping"]
    assert served.info["loss_history"] == alone.info["loss_history"]


# The initialisation's OE start as it is, and by LM alone (OE_LM_ITERATIONS = INIT_MAX_ITER: no variable projection),
# which on the map engine's inertia trip below falls into a poor local minimum: the second start is what keeps it out.
OE_STARTS = pytest.mark.parametrize("lm_only", [False, True], ids=["oe_start", "oe_start_lm_only"])


@OE_STARTS
def test_the_inertia_the_diagnosis_recommends_does_not_make_the_model_worse_on_another_day(lm_only, monkeypatch):
    """The simulator's trip hiding the crankshaft's inertia (seed 3000, the acceptance benchmark's). The model with
    the J dω/dt input is identified from the usual initialisation and from the model without it; the lower loss is
    kept, never above the model's without the input, and better on another day's trip too, with the OE start as it
    is and by LM alone."""
    if lm_only:
        monkeypatch.setattr(pem_module, "OE_LM_ITERATIONS", pem_module.INIT_MAX_ITER)
    ds, _, _ = hidden.simulated("inertia", 3000)
    other_day, _, _ = hidden.simulated("inertia", 3050)
    base = identify_model(ds, hidden.PAPER)
    model = identify_model(ds, hidden.PAPER, ["inertia"], base=base)
    starts = model.info["starts"]
    assert starts["kept"] == min(starts["loss_V"], key=starts["loss_V"].get), starts
    assert model.info["loss_V"] <= base.info["loss_V"], (model.info["loss_V"], base.info["loss_V"])
    rmse = {name: evaluate(m, other_day)["rmse"]["simulation"] for name, m in (("base", base), ("with", model))}
    assert rmse["with"] < rmse["base"], rmse


def test_a_warm_started_refit_never_raises_the_loss_and_carries_the_models_own_effects():
    ds, _, _ = hidden.simulated("dpf_regeneration", 3000)
    base = identify_model(ds, hidden.PAPER, ["fuel_delay=0.3"])
    refit = refit_with_effects(base, ds, ["dpf_regeneration"], max_iter=5)
    assert refit.effects == ("fuel_delay", "dpf_regeneration")
    assert refit.info["effect_parameters"]["fuel_delay"] == 0.3
    assert refit.info["loss_V"] <= base.info["loss_V"]
    assert refit.info["iterations"] <= 5


@OE_STARTS
def test_effects_are_added_in_turn_so_each_one_added_never_raises_the_loss(lm_only, monkeypatch):
    """On the VECTO map engine's trip hiding the inertia (seed 3000), the diagnosis recommends the engine's map
    term, then the inertia. Identified from the usual initialisation, the seven inputs (four of them the map term's
    collinear products) start far off, and from the model without any effect the fit stalled at V ≈ 2700, above the
    map term's own model (876): the inertia recommended then doubled another day's error. So the effects are also
    added in turn — the map term's model, then the inertia on it — and the model with both has a lower loss than the
    map term's own, and simulates another day's trip better, with either OE start."""
    if lm_only:
        monkeypatch.setattr(pem_module, "OE_LM_ITERATIONS", pem_module.INIT_MAX_ITER)
    ds, _, _ = hidden.simulated("inertia", 3000, truth="map")
    other_day, _, _ = hidden.simulated("inertia", 3050, truth="map")
    map_only = identify_model(ds, hidden.PAPER, ["engine_map"])
    both = identify_model(ds, hidden.PAPER, ["engine_map", "inertia"])
    stages, starts = both.info["starts"]["stages"], both.info["starts"]
    assert [s["effects"] for s in stages] == [["engine_map"]]
    # the same fits, the same one kept (map_only then refined jointly with its map: ident.hammerstein)
    assert stages[0]["loss_V"] == pytest.approx(map_only.info["joint"]["starts"]["given"]["loss_V"], rel=1e-9)
    assert starts["kept"] == min(starts["loss_V"], key=starts["loss_V"].get), starts
    assert both.info["loss_V"] <= map_only.info["loss_V"]
    rmse = {name: evaluate(m, other_day)["rmse"]["simulation"] for name, m in (("map", map_only), ("both", both))}
    assert rmse["both"] < rmse["map"], rmse


def test_the_engine_model_with_the_effects_a_diagnosis_recommended_keeps_a_start_by_the_rule_and_refines_its_map():
    """The map engine's trip hiding a cold engine and a regeneration (seed 3000), identified with the engine map and
    the four effects the diagnosis recommended: of the two starts the one `kept_fit` picks is kept (lower V unless
    another simulates grossly better), the joint rounds with the map lower V (ident.hammerstein), and another day's
    trip is simulated within 2.3 L/h RMS (2.03 measured; the engine's fuel spans 0–75 L/h)."""
    pair = ("cold_engine", "dpf_regeneration")
    ds, _, _ = hidden.simulated(pair, 3000, truth="map")
    other_day, _, _ = hidden.simulated(pair, 3050, truth="map")
    model = identify_model(ds, hidden.PAPER, ["engine_map", "dpf_regeneration", "cold_engine", "overrun_cutoff",
                                               "gear_shift"])
    starts = model.info["starts"]
    names = list(starts["loss_V"])
    fits = [SimpleNamespace(info={"loss_V": starts["loss_V"][k]}) for k in names]
    assert names[kept_fit(fits, [starts["simulation_rmse"][k] for k in names])] == starts["kept"], starts
    history = model.info["joint"]["loss_V"]
    assert history[-1] < 0.8 * history[0], history
    assert evaluate(model, other_day)["rmse"]["simulation"] < 2.3


def test_the_lower_loss_is_kept_unless_another_fit_simulates_grossly_better():
    fits = [SimpleNamespace(info={"loss_V": 318.0}), SimpleNamespace(info={"loss_V": 347.0})]
    assert kept_fit(fits, [1.69, 0.50]) == 1  # 3.4× better in simulation [L/h RMS]: the noise model carried the rest
    assert kept_fit(fits, [1.646, 1.636]) == 0  # alike in simulation: PEM's own criterion decides


@pytest.mark.parametrize("still, message", [("fuel", "the fuel flow never varies in these data (2.5 L/h over 300 s)"),
                                            ("engine", "engine speed and torque never vary in these data (650 rpm, "
                                                       "80 Nm over 300 s)")])
def test_data_that_cannot_identify_anything_are_refused_in_one_line(still, message):
    """A fuel signal stuck at one value, or an engine held at one speed and torque throughout: an InputError naming
    what never varies, not a fit of NaNs."""
    rng = np.random.default_rng(0)
    n = 1000
    u = np.column_stack([650 + rng.normal(0, 50, n), 80 + rng.normal(0, 30, n)])
    y = 2.5 + 0.01 * (u[:, 0] - 650) + rng.normal(0, 0.1, n)
    if still == "fuel":
        y[:] = 2.5
    else:
        u[:] = [650.0, 80.0]
    ds = Dataset(Ts=0.3, t=np.arange(n) * 0.3, u=u, y=y, input_names=("EEC1.EngSpeed", "EngTorque"),
                 input_units=("rpm", "Nm"), output_name="LFE1.EngFuelRate", output_unit="L/h",
                 u0=np.array([650.0, 80.0]), y0=2.5, valid=np.ones(n, bool), cycle=np.zeros(n, np.int64))
    with pytest.raises(InputError, match=re.escape(message)):
        identify_model(ds, hidden.STRUCTURE, min_segment_s=30.0)
