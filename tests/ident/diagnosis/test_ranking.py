"""ident.diagnosis.ranking: calibrated tests with nothing hidden, and what a candidate that cannot be tested lists."""
import pytest
from scipy.stats import kstest

from fuelid.ident import diagnosis as dg
from fuelid.ident.diagnosis import ranking
from fuelid.ident.modelrun import run_model
from tests.ident import hidden


def test_no_hidden_effect_no_significant_candidate_and_calibrated_p_values():
    """Family-wise false alarms of the tests over 12 seeds (Holm at 5 %), and each test's p-values (the two tests of
    every candidate, the fuel delay's on its reference model) are uniform."""
    alarms, p_values = 0, {}
    for seed in range(12):
        ds = hidden.make(None, n=4000, seed=100 + seed)
        m = hidden.fitted(ds)
        rows = [r for r in dg.rank_candidates(m, ds, dg.run_gradients(run_model(m, ds))) if r.testable]
        alarms += any(r.test_significant for r in rows)
        for r in rows:
            for test, result in r.tests.items():
                p_values.setdefault(test, []).append(result["p_value"])
    assert alarms <= 1
    for p in p_values.values():
        assert kstest(p, "uniform").pvalue > 0.01


def test_an_untested_candidate_lists_only_what_was_found():
    """A candidate whose bus signals are not logged serialises without test results (as `fuelid diagnose --json`)."""
    c = dg.Candidate("pto", "power take-off", "regime", ["CCVS1.PTOGovernorState"], [976], "…", "not testable")
    assert list(c.to_json()) == ["effect", "name", "form", "signals", "spns", "testable", "statistic", "df",
                                 "p_value", "significant", "test_significant", "estimated_drop_percent",
                                 "explanation", "rmse_drop_percent", "verification", "conditional", "explained_by"]


def test_a_candidate_tested_among_many_is_tested_as_alone(monkeypatch):
    """rank_candidates projects the nuisance columns out of many candidates' columns at once
    (entries.projected_columns): each candidate's tests are those it has tested alone, to the rounding of a wider
    product — all of them in one product, as on these 4000 samples, or a few in each (PROJECTED_TOGETHER, which
    bounds the memory on long data)."""
    ds = hidden.make("dpf_regeneration", n=4000, seed=7)
    m = hidden.fitted(ds)
    run = dg.run_gradients(run_model(m, ds))
    at_once = {r.effect: r for r in dg.rank_candidates(m, ds, run) if r.testable}
    monkeypatch.setattr(ranking, "PROJECTED_TOGETHER", 5 * 4000)
    in_groups = {r.effect: r for r in dg.rank_candidates(m, ds, run) if r.testable}
    assert in_groups.keys() == at_once.keys()
    for effect in ("dpf_regeneration", "scales:ET1.EngOilTemp1", "engine_fan"):
        alone = dg.rank_candidates(m, ds, run, [at_once[effect].definition])[0]
        for together in (at_once[effect], in_groups[effect]):
            for name, test in alone.tests.items():
                assert test["df"] == together.tests[name]["df"]
                assert test["statistic"] == pytest.approx(together.tests[name]["statistic"], rel=1e-9)
            assert alone.estimated_drop_percent == pytest.approx(together.estimated_drop_percent, rel=1e-9)
