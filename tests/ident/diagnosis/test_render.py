"""ident.diagnosis.render: the words and the flags come from one typed status, so they cannot disagree — one case
per status."""
import math

import pytest

from fuelid.ident import effects as fx
from fuelid.ident.diagnosis import MapStatus, Reason, Settings, Status
from fuelid.ident.diagnosis.candidate import Candidate, EngineMap, HeldOut, Screening
from fuelid.ident.diagnosis.render import candidate_json, explanation, verdict

SCREENED = Screening(40.0, 2, 1e-8, -8.0, 1e-6, True, 12.0)
QUIET = Screening(1.0, 2, 0.6, -0.2, 1.0, False, 0.1)
GAIN = HeldOut(1.0, 0.8, 20.0, 2.0, 0.3, 0.05, 30, "blocks", True)
NO_GAIN = HeldOut(1.0, 0.99, 1.0, 0.5, 0.01, 0.05, 30, "blocks", False)

CASES = [
    (Status.RECOMMENDED, None, None, SCREENED, GAIN),
    *[(Status.NAMED_NOT_RECOMMENDED, reason, None, SCREENED, NO_GAIN if reason is Reason.NO_HELD_OUT_GAIN else None)
      for reason in Reason],
    (Status.EXPLAINED_BY, None, "dpf_regeneration", QUIET, None),
    (Status.NOT_SIGNIFICANT, None, None, QUIET, None),
    (Status.TOO_SMALL, None, None, SCREENED, None),
    (Status.NOT_TESTABLE, None, None, None, None),
    (Status.ALREADY_IN_MODEL, None, None, None, None),
]


def test_every_status_has_a_case():
    assert {c[0] for c in CASES} == set(Status)


@pytest.mark.parametrize("status, reason, by, screening, held", CASES, ids=lambda v: getattr(v, "name", None))
def test_the_verdict_and_the_flag_agree(status, reason, by, screening, held):
    c = Candidate(fx.EFFECTS["cold_engine"], screening=screening, held_out=held, spec="cold_engine")
    c.decide(status, reason, by)
    row = candidate_json(c)
    said = verdict([c], EngineMap(MapStatus.NOT_NEEDED), Settings())
    recommends = "add cold_engine (" in said
    assert row["recommended"] is recommends is (status is Status.RECOMMENDED)
    assert ("cold_engine is named by the screening but not recommended" in said) is \
        (status is Status.NAMED_NOT_RECOMMENDED)
    assert ("no missing effect recommended" in said) is (status is not Status.RECOMMENDED)
    assert row["status"] == status.value and explanation(c).startswith(status.value)
    assert row["significant"] is (status in (Status.RECOMMENDED, Status.NAMED_NOT_RECOMMENDED))
    if reason is not None:
        assert reason.value in said and row["reason"] == reason.name.lower()
    if by is not None:
        assert row["explained_by"] == by and by in explanation(c)


@pytest.mark.parametrize("status", list(MapStatus))
def test_the_engine_map_is_advice_only_when_advised(status):
    said = verdict([], EngineMap(status, SCREENED, GAIN), Settings())
    assert ("identify the engine model" in said) is (status is MapStatus.ADVISED)
    assert ("no missing effect recommended" in said) is (status is not MapStatus.ADVISED)


def test_the_gain_is_said_in_the_standard_errors_of_the_mean_that_carried_it():
    """A candidate that passed on the trimmed mean says so, with that mean's standard errors; the JSON keeps both."""
    trimmed = HeldOut(1.0, 0.8, 20.0, 2.0, 0.3, 0.2, 40, "blocks", True, 0.25, 0.05)
    c = Candidate(fx.EFFECTS["cold_engine"], screening=SCREENED, held_out=trimmed, spec="cold_engine")
    c.decide(Status.RECOMMENDED)
    assert "trimmed mean paired gain 5.0 standard errors over 40 blocks" in explanation(c)
    assert candidate_json(c)["held_out"]["gain_in_se"] == pytest.approx(1.5)
    c.held_out = GAIN
    assert "(-20.0 %, paired gain 6.0 standard errors" in explanation(c)


def test_a_gain_measured_against_its_placebo_says_so():
    """A gain in a few blocks that passed beyond its placebo's (ident.diagnosis.yardstick.placebo) is said in the
    standard errors of that difference; without a placebo the JSON has null for it."""
    beyond = HeldOut(1.0, 0.5, 50.0, 3.0, 0.6, 0.4, 40, "blocks", True, 0.01, 0.05, True, -0.1, 0.05)
    c = Candidate(fx.EFFECTS["cold_engine"], screening=SCREENED, held_out=beyond, spec="cold_engine")
    c.decide(Status.RECOMMENDED)
    assert "paired gain 9.9 standard errors beyond a placebo's" in explanation(c)
    assert candidate_json(c)["held_out"]["beyond_null_in_se"] == pytest.approx(0.7 / (2 ** 0.5 * 0.05))
    c.held_out = GAIN
    assert "placebo" not in explanation(c)
    assert not math.isfinite(candidate_json(c)["held_out"]["beyond_null_in_se"])


def test_a_recommendation_the_data_cannot_tell_from_another_names_it():
    c = Candidate(fx.EFFECTS["cold_engine"], screening=SCREENED, held_out=GAIN, spec="cold_engine",
                  alternatives=("scales:ET1.EngOilTemp1",))
    c.decide(Status.RECOMMENDED)
    said = "these data do not tell it apart from scales:ET1.EngOilTemp1"
    assert said in explanation(c) and said in verdict([c], EngineMap(MapStatus.NOT_NEEDED), Settings())
    assert candidate_json(c)["alternatives"] == ["scales:ET1.EngOilTemp1"]
    alone = Candidate(fx.EFFECTS["cold_engine"], screening=SCREENED, held_out=GAIN, spec="cold_engine")
    alone.decide(Status.RECOMMENDED)
    assert "tell it apart" not in explanation(alone) and candidate_json(alone)["alternatives"] == []
