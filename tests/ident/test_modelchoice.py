import numpy as np
import pytest

from fuelid.errors import InputError
from fuelid.ident.modelchoice import ModelChoice, ModelKind, Reason, identify_chosen, paired_improvement
from tests.ident import engine_data
from tests.ident.hidden import STRUCTURE


def test_auto_keeps_the_linear_model_on_a_linear_engine():
    model = identify_chosen(engine_data.trip(k=0.0), STRUCTURE, min_segment_s=30.0)
    choice = ModelChoice.from_json(model.info["model_choice"])
    assert choice.kind is ModelKind.LINEAR and choice.reason is Reason.NOT_BETTER, choice
    assert "engine_map" not in model.effects and len(choice.held_out.d) >= 3


def test_auto_keeps_the_engine_model_on_a_curved_engine_and_says_why():
    model = identify_chosen(engine_data.trip(k=1.0), STRUCTURE, min_segment_s=30.0)
    choice = ModelChoice.from_json(model.info["model_choice"])
    assert choice.kind is ModelKind.ENGINE and choice.reason is Reason.BETTER
    assert model.effects == ("engine_map",)
    assert choice.held_out.better  # the mean clears the t margin and the floor
    assert "engine model" in choice.line("L/h") and "held-out" in choice.line("L/h")


def test_asked_for_models_are_built_without_the_held_out_choice():
    ds = engine_data.trip(k=1.0, n=4000)
    linear = identify_chosen(ds, STRUCTURE, kind=ModelKind.LINEAR, min_segment_s=30.0)
    assert linear.effects == () and linear.info["model_choice"]["held_out"] is None
    engine = identify_chosen(ds, STRUCTURE, ["engine_map"], min_segment_s=30.0)
    assert engine.effects == ("engine_map",) and engine.info["model_choice"]["asked"] == "engine"
    with pytest.raises(InputError, match="engine_map"):
        identify_chosen(ds, STRUCTURE, ["engine_map"], kind=ModelKind.LINEAR, min_segment_s=30.0)


def test_too_short_a_trip_keeps_the_linear_model():
    model = identify_chosen(engine_data.trip(k=1.0, n=2000), STRUCTURE, min_segment_s=30.0)
    assert model.info["model_choice"]["reason"] == "too_short"


@pytest.mark.parametrize("t_stat, better", [(2.5, False), (3.0, True)])
def test_the_margin_is_students_t_for_the_blocks_held_out(t_stat, better):
    """Over 5 blocks the margin is t_0.975(4) = 2.776 standard errors, not 2: a mean improvement of 2.5 SE is not
    enough, 3 SE is."""
    x = np.array([-1.0, -0.5, 0.0, 0.5, 1.0])
    d = 0.2 + x * (0.2 / t_stat) / (x.std(ddof=1) / np.sqrt(5))  # mean 0.2, mean/SE = t_stat
    e_base = np.full(5, 2.0)
    p = paired_improvement(e_base, e_base * (1.0 - d))
    assert p.se_factor == pytest.approx(2.776, abs=1e-3)
    assert p.mean / p.se == pytest.approx(t_stat) and p.better is better


def test_fewer_than_two_blocks_never_decide_and_state_no_figures():
    p = paired_improvement([2.0], [1.0])
    assert not p.better and p.mean is None and p.se is None
