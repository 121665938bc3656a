"""ident.diagnosis.delay: a fuel-signal delay named with its size, admitted from one sample on, and verified beyond the
fuelling effects' budget."""
from fuelid.ident import diagnosis as dg
from fuelid.ident.diagnosis.entries import ENTRIES
from tests.ident import hidden


def test_a_fuel_signal_delay_is_named_with_its_size_though_the_model_absorbs_it():
    """A 0.4 s delay, tested on seed 2's reference model, which cannot absorb it; the model's own taps absorb part
    of it (with the paper's five torque taps, all: tests/ident/diagnosis/test_hidden_effects.py)."""
    ds = hidden.make("fuel_delay", seed=1, delay_s=0.4)
    top = dg.diagnose(hidden.fitted(ds), ds).candidates[0]
    v = top.verification
    assert top.effect == "fuel_delay" and top.significant and top.tests is not None
    assert abs(top.size["delay_s"] - 0.4) <= 0.1 and top.spec == f"fuel_delay={top.size['delay_s']:.2f}"
    assert v["reference"]["rmse_drop_percent"] > max(5, v["rmse_drop_percent"]) and v["direction"] == 1
    assert "lags speed and torque" in top.explanation


def test_a_fuel_delay_shorter_than_one_sample_is_not_a_missing_effect():
    """0.2 s at Ts = 0.3 s: the reference model fits better with it, but the model's own input taps hold a
    sub-sample delay (to first order a two-tap filter), so it is evidence, not advice."""
    ds = hidden.make("fuel_delay", seed=1, delay_s=0.2, noise=0.1)
    delay = next(c for c in dg.diagnose(hidden.fitted(ds), ds).candidates if c.effect == "fuel_delay")
    v = delay.verification
    assert delay.test_significant and 0.1 < v["reference"]["delay_s"] < 0.3 and v["within_one_sample"]
    assert v["reference"]["rmse_drop_percent"] > 2.0  # relevant on the reference: only its length keeps it out
    assert not delay.significant and not delay.recommended
    assert "shorter than one sample period (0.3 s)" in delay.explanation


def test_a_fuel_delay_is_admitted_when_a_sample_or_longer_and_the_model_itself_absorbs_it():
    """What the model absorbs is a delay; a shift that makes the model itself much worse held out is the reference
    model's misfit (on a null trip of the map engine, 0.5 s: +114 %), not a delay of the fuel signal."""
    shift = ENTRIES["shift"]
    v = {"within_one_sample": False, "rmse_drop_percent": -0.14, "sample_period_s": 0.3}  # a true 0.4 s delay
    assert shift.why_not_admitted(v, 2.0) is None
    assert "shorter than one sample period (0.3 s)" in shift.why_not_admitted({**v, "within_one_sample": True}, 2.0)
    assert "own held-out RMS error by +114 %" in shift.why_not_admitted({**v, "rmse_drop_percent": -114.0}, 2.0)
    assert ENTRIES["additive"].why_not_admitted(v, 2.0) is None


def test_the_fuel_delay_is_verified_beyond_the_budget_of_the_fuelling_effects():
    """One verification (`--verify 1`) goes to the regeneration, the largest estimated drop; the delay, a family of
    its own (the signal path, verified on its reference model), is verified and recommended all the same."""
    ds = hidden.make(("fuel_delay", "dpf_regeneration"), seed=1)
    out = dg.diagnose(hidden.fitted(ds), ds, n_verify=1)
    delay = next(c for c in out.candidates if c.effect == "fuel_delay")
    larger = [c for c in out.candidates
              if c.test_significant and c.estimated_drop_percent > delay.estimated_drop_percent]
    assert len(larger) >= 2 and delay.verification is not None and delay.significant and delay.recommended
