"""ident.diagnosis on synthetic data from a known Box-Jenkins model with one hidden physical effect: the score
test names it first, refitting with it lowers the held-out error, and with no hidden effect nothing is flagged."""
import dataclasses
import warnings
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.linalg import block_diag, solve_toeplitz
from scipy.signal import lfilter
from scipy.stats import chi2, kstest
from threadpoolctl import threadpool_limits

from fuelid.ident import diagnosis as dg
from fuelid.ident import effects as fx
from fuelid.ident.diagnosis import builds, recommendation, selection
from fuelid.ident.diagnosis import statistics as st
from fuelid.ident.diagnosis.entries import ENTRIES
from fuelid.ident.diagnosis.verification import block_cv, trip_cv, trip_folds
from fuelid.ident.modelrun import run_model
from fuelid.ident.pem import pem
from tests.ident import hidden


# RMS [L/h] of hidden.make's noise C/D e, e of std 0.5/1.3 (measured without the effect: 0.58)
NOISE_FLOOR = 0.5 / 1.3 * float(np.linalg.norm(lfilter(hidden.TRUE.C, hidden.TRUE.D, np.r_[1.0, np.zeros(200)])))


def fitted(ds):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = pem(ds.u, ds.y, hidden.STRUCTURE, ds.Ts, u0=ds.u0, y0=ds.y0)
    return dataclasses.replace(m, input_names=ds.input_names, input_units=ds.input_units,
                               output_name=ds.output_name, output_unit=ds.output_unit)


def test_score_test_is_n_r2_for_white_noise_and_holm_is_step_down():
    rng = np.random.default_rng(0)
    e, X = rng.normal(size=5000), rng.normal(size=(5000, 2))
    e2 = e + 0.1 * X[:, 0]
    res = st.score_test(e2, X, hac_lags=0)
    r2 = 1 - np.sum((e2 - X @ np.linalg.lstsq(X, e2, rcond=None)[0]) ** 2) / np.sum(e2**2)
    assert res.df == 2 and res.statistic == pytest.approx(5000 * r2, rel=0.05)
    assert res.p_value == pytest.approx(chi2.sf(res.statistic, 2))
    adj, rej = st.holm([0.01, 0.04, 0.03, 0.5], 0.05)
    assert np.allclose(adj, [0.04, 0.09, 0.09, 0.5]) and rej.tolist() == [True, False, False, False]
    assert st.score_test(e, X[:, :1], Q=st.nuisance_basis(X[:, :1])).df == 0  # nothing left to test


def test_level_test_whitens_coloured_noise_under_the_alternative():
    """A level shift in strongly coloured noise (AR pole 0.98) is found by the simulation-error test; with no
    shift a regressor as slow as the noise (the hardest case: a spurious regression without whitening) is
    flagged at 5 % in at most 12 % of 100 trials (measured 9 % over 200)."""
    n, p_null = 6000, []
    Q = st.nuisance_basis(np.ones((n, 1)))
    for seed in range(100):
        noise = lfilter([1.0], [1.0, -0.98], np.random.default_rng(seed).normal(size=n))
        x = lfilter([1.0], [1.0, -0.98], np.random.default_rng(1000 + seed).normal(size=n))[:, None]
        p_null.append(st.level_test(noise - noise.mean(), x - x.mean(), [n], Q)[0].p_value)
    assert np.mean(np.array(p_null) < 0.05) <= 0.12
    step = (np.arange(n) > n // 2).astype(float)[:, None]
    shifted = lfilter([1.0], [1.0, -0.98], np.random.default_rng(1).normal(size=n)) + 6.0 * step[:, 0]
    found, left = st.level_test(shifted - shifted.mean(), step - step.mean(), [n], Q)  # noise std 5
    assert found.p_value < 1e-6 and left < 0.9


def test_nuisance_basis_keeps_each_segments_initial_states_on_its_own_rows():
    """Segments' free-response columns are zero outside their segment: the basis projects out exactly what the
    dense QR of [Z, blockdiag(IC_1 … IC_S)] does, stores N·(p_Z + p_s) numbers however many segments there are,
    and block_cv on it equals block_cv on the dense basis."""
    rng = np.random.default_rng(5)
    lens = [300, 200, 250, 250]
    ICs = [lfilter([1.0], [1.0, -0.95], np.eye(n, 2), axis=0) for n in lens]  # two free responses per segment
    Z = rng.normal(size=(sum(lens), 3))
    X = rng.normal(size=(sum(lens), 2))
    basis = st.nuisance_basis(Z, ICs)
    dense = np.linalg.qr(np.column_stack([Z, block_diag(*ICs)]))[0]
    assert np.allclose(basis.project_out(X), X - dense @ (dense.T @ X))
    assert basis.dense.shape == (sum(lens), 3) and [b.shape for b in basis.blocks] == [(n, 2) for n in lens]
    r = Z @ [1.0, 0.5, -1.0] + rng.normal(size=sum(lens))
    assert np.allclose(block_cv(r, basis, 60, buffer=20), block_cv(r, st.NuisanceBasis(dense), 60, buffer=20))
    wider = basis.extended(X)
    assert np.allclose(wider.project_out(X), 0.0, atol=1e-10) and wider.dense.shape[1] == 5


def test_a_nuisance_column_already_in_the_span_adds_nothing():
    """An offset next to the trips' levels (an exact dependence) adds no direction: a plain QR would add one made
    of rounding errors, and project it out of everything."""
    levels = np.zeros((400, 2))
    levels[:250, 0], levels[250:, 1] = 1.0, 1.0
    basis = st.nuisance_basis(np.column_stack([levels, np.ones(400)]))
    assert basis.dense.shape[1] == 2
    assert basis.extended(levels @ [2.0, -1.0]) is basis


def test_block_cv_is_exact_leave_one_block_out_least_squares():
    """The block-deletion formula gives what refitting without each block gives, and held-out errors exceed the
    in-sample residuals (a fit scored on its own data looks better than it is)."""
    rng = np.random.default_rng(3)
    Z = rng.normal(size=(500, 4))
    r = Z @ [1.0, -2.0, 0.5, 0.0] + rng.normal(size=500)
    out = block_cv(r, st.nuisance_basis(Z), 60)
    for a in range(0, 500, 60):
        fit = np.r_[0:a, a + 60:500]
        coef = np.linalg.lstsq(Z[fit], r[fit], rcond=None)[0]
        assert np.allclose(out[a:a + 60], r[a:a + 60] - Z[a:a + 60] @ coef)
    in_sample = r - Z @ np.linalg.lstsq(Z, r, rcond=None)[0]
    assert np.sum(out**2) > np.sum(in_sample**2)
    h_block = block_cv(r, st.nuisance_basis(Z), 60, buffer=20)  # each block fitted without it and 20 either side
    for a in range(0, 500, 60):
        fit = np.r_[0:max(a - 20, 0), min(a + 80, 500):500]
        coef = np.linalg.lstsq(Z[fit], r[fit], rcond=None)[0]
        assert np.allclose(h_block[a:a + 60], r[a:a + 60] - Z[a:a + 60] @ coef)


def test_block_cv_keeps_the_full_data_coefficient_of_a_direction_only_the_left_out_block_determines():
    """A column non-zero only inside one block (an effect on there alone, a short segment's initial state): with
    that block left out nothing determines its coefficient, and I − Q_Sᵀ Q_S is singular. The deletion formula
    (its pseudo-inverse) then refits what the other blocks determine and keeps the full-data coefficient of the
    direction they do not; every other block is the plain refit without it."""
    rng = np.random.default_rng(4)
    Z = np.column_stack([rng.normal(size=(500, 3)), np.zeros(500)])
    Z[130:150, 3] = 1.0  # inside the block 120 … 179
    r = Z @ [1.0, -2.0, 0.5, 3.0] + rng.normal(size=500)
    Q = st.nuisance_basis(Z).dense
    out = block_cv(r, st.NuisanceBasis(Q), 60)
    for a in range(0, 500, 60):
        fit = np.r_[0:a, a + 60:500]
        M_pinv = np.linalg.pinv(Q[fit].T @ Q[fit], rcond=1e-10)
        undetermined = np.eye(4) - M_pinv @ (Q[fit].T @ Q[fit])  # the projector on what the other blocks leave open
        coef = M_pinv @ Q[fit].T @ r[fit] + undetermined @ (Q.T @ r)
        assert np.allclose(out[a:a + 60], r[a:a + 60] - Q[a:a + 60] @ coef)
        assert np.allclose(undetermined, 0.0, atol=1e-8) == (a != 120)


def test_trip_cv_fits_what_the_other_trips_determine_and_leaves_the_rest_at_zero():
    """Three trips; the model's own column g (a gain: the fuel itself) and a candidate x. Where x varies within every
    trip, each trip left out is predicted by the plain least-squares fit on the other two. Where x is one constant
    per trip (an ambient condition) it is g times a per-trip factor: fitted on two trips it is determined (they
    differ), but the third trip alone would leave it confounded with g, so a fit on one trip must not extrapolate
    it. With two trips each fold has one and nothing is determined: scored exactly as without the candidate."""
    rng = np.random.default_rng(5)
    n = 300
    trips = [np.arange(k * n, (k + 1) * n) for k in range(3)]
    g = 20.0 + 5.0 * np.sin(np.arange(3 * n) / 40.0)
    G = (g / np.linalg.norm(g))[:, None]
    level = np.repeat([0.0, 0.3, 0.15], n)
    varying = rng.normal(size=3 * n)
    for x in (varying * g, level * g):
        r = 0.5 * x + 0.2 * rng.normal(size=3 * n)
        r -= G @ (G.T @ r)  # the model fitted on all the data: its residual is orthogonal to its own columns
        out, determined = trip_cv(r, trip_folds(G, trips), x[:, None])
        assert determined == [True, True, True]
        for t in trips:
            fit = np.setdiff1d(np.arange(3 * n), t)
            Z = np.column_stack([G, x])
            coef = np.linalg.lstsq(Z[fit], r[fit], rcond=None)[0]
            assert np.allclose(out[t], r[t] - Z[t] @ coef)
    two = trips[:2]
    x = (level * g)[: 2 * n]
    r = 0.5 * x + 0.2 * rng.normal(size=2 * n)
    r -= G[: 2 * n] @ np.linalg.lstsq(G[: 2 * n], r, rcond=None)[0]
    G2 = G[: 2 * n] / np.linalg.norm(G[: 2 * n])
    out, determined = trip_cv(r, trip_folds(G2, two), x[:, None])
    without, _ = trip_cv(r, trip_folds(G2, two), np.zeros((2 * n, 0)))
    assert determined == [False, False] and np.array_equal(out, without)


def test_trip_cv_leaves_a_direction_of_the_model_only_the_trip_left_out_holds_at_zero():
    """A model parameter only one trip excites (an input that is zero on the others, as a regeneration seen on one
    day): fitted on the other trips its direction is not determined, and it stays where the model fitted on all the
    data has it — the minimum-norm fit in the model's orthonormal columns — instead of being extrapolated."""
    rng = np.random.default_rng(7)
    n = 200
    trips = [np.arange(k * n, (k + 1) * n) for k in range(3)]
    h = np.zeros(3 * n)
    h[:n] = rng.normal(size=n)  # only the first trip holds it
    G = np.linalg.qr(np.column_stack([20.0 + np.sin(np.arange(3 * n) / 30.0), h]))[0]
    r = rng.normal(size=3 * n)
    r -= G @ (G.T @ r)
    out, _ = trip_cv(r, trip_folds(G, trips), np.zeros((3 * n, 0)))
    for t in trips:
        fit = np.setdiff1d(np.arange(3 * n), t)
        assert np.linalg.matrix_rank(G[fit]) == (1 if t is trips[0] else 2)
        coef = np.linalg.lstsq(G[fit], r[fit], rcond=None)[0]  # minimum norm where the other trips leave it open
        assert np.allclose(out[t], r[t] - G[t] @ coef)


def test_free_responses_span_any_initial_state():
    """A filter started from zero state differs from one started anywhere else by a combination of the columns."""
    F = np.array([1.0, -1.5, 0.7])
    x = np.random.default_rng(4).normal(size=300)
    started = lfilter([1.0], F, x, zi=[0.8, -0.3])[0]
    diff = started - lfilter([1.0], F, x)
    cols = st.free_responses([F], 300)
    assert cols.shape == (300, 2)
    assert np.allclose(cols @ np.linalg.lstsq(cols, diff, rcond=None)[0], diff)


@pytest.mark.parametrize("effect, check", [
    ("dpf_regeneration", lambda r: 8 < r.size["percent_change_when_on"] < 14),
    ("inertia", lambda r: abs(r.size["inertia_kgm2"] - hidden.J) < 0.2 * hidden.J),
])
def test_hidden_effect_is_found_first_explained_and_verified(effect, check):
    ds = hidden.make(effect, seed=1)
    out = dg.diagnose(fitted(ds), ds)
    top = out.candidates[0]
    assert top.effect == effect and top.significant
    assert top.p_value < 1e-3 and top.estimated_drop_percent > 5
    v = top.verification  # the held-out error falls by ≥ 25 % or to the noise floor (+5 %)
    assert v["rmse_drop_percent"] > 25 or (v["rmse_drop_percent"] > 5 and v["rmse_with"] < 1.05 * NOISE_FLOOR), v
    assert check(top), top.size
    assert f"add effect {effect}" in top.explanation and out.verdict.startswith("Missing effect")
    for key in ("effect", "signals", "spns", "statistic", "p_value", "significant", "rmse_drop_percent",
                "explanation", "p_holm", "test_significant", "estimated_drop_percent", "verification", "tests"):
        assert key in top.to_json()  # what `fuelid diagnose --json` lists


def test_an_effect_nobody_listed_is_found_and_named_by_its_bus_signal():
    """Fuel 1.5 L/h higher while an unknown ECU state is 2: found as that signal's state (as its indicators, or as
    a regime off its most frequent value), by its DBC name."""
    ds = hidden.make("unlisted", seed=1)
    out = dg.diagnose(fitted(ds), ds)
    top = out.candidates[0]
    assert top.effect in ("state:XX.UnknownState", "scales:XX.UnknownState") and top.significant, out.verdict
    assert top.verification["rmse_drop_percent"] > 5 and "XX.UnknownState" in top.explanation


def _built_with_the_regeneration_simulates(ratio: float, monkeypatch) -> None:
    """Make the model identify builds with the DPF regeneration simulate the data with `ratio` times the RMS error
    of the one built without it (builds.BuiltCheck)."""
    rmse = builds.BuiltCheck._rmse

    def scaled_with_the_regeneration(built, specs):
        without = rmse(built, [s for s in specs if s != "dpf_regeneration"])
        return ratio * without if "dpf_regeneration" in specs else without

    monkeypatch.setattr(builds.BuiltCheck, "_rmse", scaled_with_the_regeneration)


def test_an_effect_the_built_model_simulates_worse_with_is_named_not_recommended(monkeypatch):
    """The last check before an effect is recommended is on the model `fuelid identify --effects-from` builds
    (builds.BuiltCheck): when that model simulates the data worse with it — made so here: 10 % worse than without
    it — the effect is named, not recommended, and the explanation says why and by how much."""
    _built_with_the_regeneration_simulates(1.1, monkeypatch)
    ds = hidden.make("dpf_regeneration", seed=1)
    out = dg.diagnose(fitted(ds), ds)
    top = out.candidates[0]
    assert top.effect == "dpf_regeneration" and top.significant and not top.recommended
    built = top.refit["built"]
    assert built["rmse_with"] > built["rmse_without"] and not top.refit["verified"]
    assert "add effect" not in top.explanation
    assert f"builds with it (PEM from its own initialisation) simulates these data worse (RMS error " \
           f"{built['rmse_without']:.3f} → {built['rmse_with']:.3f}): not recommended" in top.explanation


def _warm_refit_worse_with_the_regeneration(monkeypatch) -> None:
    """Make forward selection's warm-started refit with the DPF regeneration simulate 10 % worse (selection._refit)."""
    refit = selection._refit

    def warm_refit_worse(c, *args):
        out = refit(c, *args)
        if c.effect != "dpf_regeneration":
            return out
        c.refit.update(rmse_with=1.1 * c.refit["rmse_without"], verified=False)
        return None

    monkeypatch.setattr(selection, "_refit", warm_refit_worse)


def test_an_effect_only_the_warm_started_refit_simulates_worse_with_is_decided_by_the_built_model(monkeypatch):
    """Forward selection's warm-started refit can end far from the minimum `fuelid identify` reaches (made so here:
    it simulates 10 % worse with the regeneration): an effect with its physics is then recommended when the model
    identify builds simulates the data at least min_drop_percent (2 %) better with it, and the explanation says
    both; a generic bus signal is not (its trip checks run only on a verified refit)."""
    _warm_refit_worse_with_the_regeneration(monkeypatch)
    ds = hidden.make("dpf_regeneration", seed=1)
    out = dg.diagnose(fitted(ds), ds)
    top = out.candidates[0]
    assert top.effect == "dpf_regeneration" and top.recommended and top.refit["verified"], top.explanation
    built = top.refit["built"]
    assert built["rmse_with"] <= 0.98 * built["rmse_without"] and built["min_gain_percent"] == 2
    assert f"warm-started refit with it simulated these data worse, RMS error {top.refit['rmse_without']:.3f} → " \
           f"{top.refit['rmse_with']:.3f}" in top.explanation and "add effect dpf_regeneration" in top.explanation
    generic = SimpleNamespace(effect="level:XX.Unknown", refit={**top.refit, "verified": False},
                              verification=top.verification)
    assert not recommendation.only_the_warm_refit_worse(generic)


def test_an_effect_only_the_warm_started_refit_simulates_worse_with_needs_a_relevant_gain_when_built(monkeypatch):
    """Where the warm-started refit simulated worse, a model identify builds that is only as good with the effect
    (made so here: 1 % better, less than min_drop_percent) is a tie within the fits' reproducibility, not evidence:
    on the map engine such a tie recommended the friction, and another day's error rose (README). Named, not
    recommended, and the explanation says by how much it fell short."""
    _warm_refit_worse_with_the_regeneration(monkeypatch)
    _built_with_the_regeneration_simulates(0.99, monkeypatch)
    ds = hidden.make("dpf_regeneration", seed=1)
    top = dg.diagnose(fitted(ds), ds).candidates[0]
    assert top.effect == "dpf_regeneration" and top.significant and not top.recommended, top.explanation
    built = top.refit["built"]
    assert "add effect" not in top.explanation and not top.refit["verified"]
    assert f"lowers their RMS error by less than 2 % ({built['rmse_without']:.3f} → {built['rmse_with']:.3f}): " \
           "not recommended" in top.explanation


def test_a_fuel_signal_delay_is_named_with_its_size_though_the_model_absorbs_it():
    """A 0.4 s delay, tested on seed 2's reference model, which cannot absorb it; the model's own taps absorb part
    of it (with the paper's five torque taps, all: tests/ident/test_hidden_effects.py)."""
    ds = hidden.make("fuel_delay", seed=1, delay_s=0.4)
    top = dg.diagnose(fitted(ds), ds).candidates[0]
    v = top.verification
    assert top.effect == "fuel_delay" and top.significant and top.tests is not None
    assert abs(top.size["delay_s"] - 0.4) <= 0.1 and top.spec == f"fuel_delay={top.size['delay_s']:.2f}"
    assert v["reference"]["rmse_drop_percent"] > max(5, v["rmse_drop_percent"]) and v["direction"] == 1
    assert "lags speed and torque" in top.explanation


def test_a_fuel_delay_shorter_than_one_sample_is_not_a_missing_effect():
    """0.2 s at Ts = 0.3 s: the reference model fits better with it, but the model's own input taps hold a
    sub-sample delay (to first order a two-tap filter), so it is evidence, not advice."""
    ds = hidden.make("fuel_delay", seed=1, delay_s=0.2, noise=0.1)
    delay = next(c for c in dg.diagnose(fitted(ds), ds).candidates if c.effect == "fuel_delay")
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
    out = dg.diagnose(fitted(ds), ds, n_verify=1)
    delay = next(c for c in out.candidates if c.effect == "fuel_delay")
    larger = [c for c in out.candidates
              if c.test_significant and c.estimated_drop_percent > delay.estimated_drop_percent]
    assert len(larger) >= 2 and delay.verification is not None and delay.significant and delay.recommended


def test_an_effect_named_by_its_tests_alone_is_not_recommended_and_says_why():
    """With no verification budget (`fuelid diagnose --verify 0`) the delay is still named by its tests, but what
    was never verified is no advice to add it."""
    ds = hidden.make("fuel_delay", seed=1, delay_s=0.4)
    top = dg.diagnose(fitted(ds), ds, n_verify=0).candidates[0]
    assert top.effect == "fuel_delay" and top.significant and top.verification is None
    assert not top.recommended and "add effect" not in top.explanation
    assert top.explanation.endswith(" — not verified (`fuelid diagnose --verify 0`): not recommended")


def test_a_candidate_fitted_against_its_physics_is_not_confirmed():
    """Fuel 11 % lower while SPN 3700 says 'regenerating' is something, but not a DPF regeneration."""
    ds = hidden.make("dpf_regeneration", seed=1, size=-0.11)
    out = dg.diagnose(fitted(ds), ds)
    row = next(r for r in out.candidates if r.effect == "dpf_regeneration")
    assert row.test_significant and row.verification["rmse_drop_percent"] > 5
    assert row.verification["direction"] == -1 and not row.significant
    assert "the other way" in row.explanation


def test_no_hidden_effect_no_significant_candidate_and_calibrated_p_values():
    """Family-wise false alarms of the tests over 12 seeds (Holm at 5 %), and each test's p-values (the two tests of
    every candidate, the fuel delay's on its reference model) are uniform."""
    alarms, p_values = 0, {}
    for seed in range(12):
        ds = hidden.make(None, n=4000, seed=100 + seed)
        m = fitted(ds)
        rows = [r for r in dg.rank_candidates(m, ds, dg.run_gradients(run_model(m, ds))) if r.testable]
        alarms += any(r.test_significant for r in rows)
        for r in rows:
            for test, result in r.tests.items():
                p_values.setdefault(test, []).append(result["p_value"])
    assert alarms <= 1
    for p in p_values.values():
        assert kstest(p, "uniform").pvalue > 0.01


def test_a_curved_engine_map_is_the_engines_own_term_and_the_hidden_effect_is_found_on_top_of_it():
    """The synthetic engine made curved (fuel + 10 L/h per krpm·kNm of ñ·T̃ and + 8 L/h per kNm² of T̃²: efficiency
    varying over speed × torque, the largest thing the linear model misses, as on the VECTO engine) and hiding a
    DPF regeneration: the map is named first as the engine's own term, not a missing effect, and the regeneration
    is the missing effect found on the model with it; the product term is explained by the map. With a weaker
    curvature (4 and 3) the regeneration explains more than the map: the map's columns would absorb part of it, so
    no map term is named first. On the linear engine no map term is named."""
    def curved(a, b):
        ds = hidden.make("dpf_regeneration", seed=1)
        n, T = (d / 1000.0 for d in fx.deviations(ds))
        ds = dataclasses.replace(ds, y=ds.y + a * n * T + b * T * T)
        return dg.diagnose(fitted(ds), ds)

    out = curved(10.0, 8.0)
    term = out.engine_map
    assert term is out.candidates[0] and term.effect == "engine_map" and term.role == "engine map", out.verdict
    assert term.recommended and term.rmse_drop_percent >= 25.0, term.verification
    assert [c.effect for c in out.missing_effects][:1] == ["dpf_regeneration"], out.verdict
    dpf = out.missing_effects[0]
    assert dpf.conditional["given"] == ["engine_map"] and dpf.recommended
    product = next(c for c in out.candidates if c.effect == "power_nonlinearity")
    assert not product.significant and product.explained_by.startswith("engine_map")
    js = out.to_json()
    assert js["engine_map"] == "engine_map" and js["missing_effects"][0] == "dpf_regeneration"
    assert js["verdict"].startswith("Engine map: the engine's fuel map is curved") and "Missing effect" in js["verdict"]
    assert dg.confirmed_effects(js["candidates"])[:2] == ["engine_map", "dpf_regeneration"]

    weak = curved(4.0, 3.0)
    assert weak.engine_map is None and "dpf_regeneration" in [c.effect for c in weak.missing_effects], weak.verdict
    assert "not named as the engine's map" in next(c for c in weak.candidates if c.effect == "engine_map").explanation
    linear = dg.diagnose(fitted(hidden.make("dpf_regeneration", seed=1)), hidden.make("dpf_regeneration", seed=1))
    assert linear.engine_map is None and linear.to_json()["engine_map"] is None


def test_where_it_fails_sections():
    ds = hidden.make("dpf_regeneration", n=4000, seed=2)
    out = dg.diagnose(fitted(ds), ds, n_verify=0)
    worst = out.where_it_fails["worst_segments"]
    assert worst and "DPF active regeneration" in worst[0]["context"]
    emap = out.where_it_fails["error_map"]
    assert np.array(emap["count"]).sum() > 3000 and len(emap["speed_edges_rpm"]) == 9
    white, compared = out.where_it_fails["whiteness"], out.compare["whiteness"]
    assert not white["autocorr_pass"]  # the regeneration is left in the residual
    assert white["autocorr_pass"] == compared["autocorr_pass"]  # one settling rule: the report never says both
    assert white["crosscorr_pass"] == compared["crosscorr_pass"]
    assert out.compare["fit_percent"]["simulation"] > 50


def test_every_effect_enters_the_model_one_known_way():
    """Each catalogue effect's entry kind is one of ident.diagnosis.entries.ENTRIES (the one place a new kind goes)."""
    ds = hidden.make(None, n=500)
    assert {e.enters for e in list(fx.EFFECTS.values()) + fx.generic_effects(ds)} <= set(ENTRIES)
    assert fx.EFFECTS["fuel_delay"].enters == "shift" and fx.EFFECTS["engine_fan"].enters == "torque"


def test_an_untested_candidate_lists_only_what_was_found():
    """A candidate whose bus signals are not logged serialises without test results (as `fuelid diagnose --json`)."""
    c = dg.Candidate("pto", "power take-off", "regime", ["CCVS1.PTOGovernorState"], [976], "…", "not testable")
    assert list(c.to_json()) == ["effect", "name", "form", "signals", "spns", "testable", "statistic", "df",
                                 "p_value", "significant", "test_significant", "estimated_drop_percent",
                                 "explanation", "rmse_drop_percent", "verification", "conditional", "explained_by"]


def test_an_effect_accepted_given_a_signal_not_added_is_recommended_only_if_verified_given_those_added_before_it():
    """Forward selection accepted the overrun cut-off given two bus signals that are not added; its first round had
    found and verified it given the map term alone. With the regeneration recommended before it, that round did
    not verify it on the model `fuelid identify --effects-from` builds (map term and regeneration): not recommended
    (on the map engine's DPF trip, seed 3000, with the fuel × (1 + 1e-13), it raised another day's error); with the
    map term alone recommended before it, that round did."""
    c = dg.Candidate("overrun_cutoff", "overrun fuel cut-off", "state", [], [], "…", "…")
    signals = ["scales:EEC3.EngDesiredOperatingSpeed", "level:EEC1.EngDemandPercentTorque"]
    c.conditional = {"given": ["engine_map", "dpf_regeneration", *signals],
                     "found_given": [["engine_map"], ["engine_map", "dpf_regeneration", *signals]]}
    assert recommendation.found_given_added(c, {"engine_map", "dpf_regeneration"}) is None
    assert recommendation.given_not_added(c, {"engine_map", "dpf_regeneration"}) == signals
    c.conditional["given"] = ["engine_map", *signals]
    c.conditional["found_given"] = [["engine_map"], ["engine_map", *signals]]
    assert recommendation.found_given_added(c, {"engine_map"}) == ["engine_map"]
    assert recommendation.given_not_added(c, {"engine_map"}) == []


def test_forward_selection_stops_once_nothing_a_later_round_could_accept_can_be_recommended():
    """On one trip a bus signal fuelid knows no physics for is never added (recommendation.ONE_TRIP_ONLY). Once the search
    is built on one, whatever a later round finds is found given it and not recommended: it stops — unless a
    candidate that may be added was found in an earlier round given no such signal (recommendation.found_given_added)."""
    ds = hidden.make("dpf_regeneration", seed=1)
    run = dg.run_gradients(run_model(fitted(ds), ds))  # one trip
    generic = {e.id: e for e in fx.generic_effects(ds)}

    def candidate(effect: str, **records) -> dg.Candidate:
        return dg.Candidate(effect, effect, "…", [], [], "…", "…", definition=generic.get(effect), **records)

    signal = candidate("scales:ET1.EngOilTemp1", refit={"verified": True}, verification={"rmse_drop_percent": 5.0})
    twin = candidate("level:ET1.EngOilTemp1", conditional={"found_given": [["engine_map"]]})
    overrun = candidate("overrun_cutoff", conditional={"found_given": [["engine_map"]]})

    def stops(named, pool) -> bool:
        return selection._nothing_left_to_recommend(named, pool, ds, run)

    assert recommendation.why_never_added(signal, ds) == recommendation.ONE_TRIP_ONLY
    assert not stops([], [overrun, twin])  # not built on such a signal: the next round may find one to add
    assert not stops([signal], [overrun, twin])  # found given the map term alone: may be recommended after it
    assert stops([signal], [twin])  # on one trip a generic signal is never added, whatever round found it
    overrun.conditional["found_given"] = [["engine_map", signal.effect]]
    assert stops([signal], [overrun, twin])  # found given the signal only
    signal.refit["verified"] = False  # its refit not verified: the search was not built on it
    assert not stops([signal], [overrun, twin])
    said = selection.why_left_at_the_stop(signal.effect)  # what one found beside it says: not "explained by" it
    assert said.startswith(" — found beside scales:ET1.EngOilTemp1, but forward selection accepted that one and "
                           "stopped")


@pytest.mark.parametrize("n", [2989, 11989])  # 2n − 1 and 2n with a large prime factor (11989 = 19 · 631)
def test_the_whitener_is_yule_walker_on_the_linear_autocovariances(n):
    """ar_whitener's FFT autocovariances are the biased linear ones (no circular wrap-around), so its a(q) is the
    Yule–Walker AR fit: for an AR(2) series it recovers the coefficients and whitens the series."""
    rng = np.random.default_rng(n)
    v = lfilter([1.0], [1.0, -1.2, 0.5], rng.standard_normal(n))
    order = 100
    d = v - v.mean()
    acov = np.array([d[: n - k] @ d[k:] for k in range(order + 1)]) / n
    a = st.ar_whitener(v, order)
    np.testing.assert_allclose(a, np.r_[1.0, -solve_toeplitz(acov[:order], acov[1:])], rtol=0, atol=1e-9)
    np.testing.assert_allclose(a[1:3], [-1.2, 0.5], atol=0.06)


def test_the_diagnosis_does_not_depend_on_the_number_of_blas_threads():
    """The same diagnosis, to the bit, whether BLAS may use one thread or several (a laptop's `fuelid diagnose`
    and a fleet worker's, which runs one thread: fleet.jobs)."""
    ds = hidden.make("dpf_regeneration", n=18000, seed=2)
    model = fitted(ds)
    said = []
    for threads in (1, 2):
        with threadpool_limits(limits=threads, user_api="blas"):
            said.append(dg.diagnose(model, ds).to_json())
    assert said[0] == said[1]
