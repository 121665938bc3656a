"""ident.diagnosis.yardstick: folds, refits on each, and the paired per-block comparison with its margin."""
import numpy as np
import pytest

from fuelid.ident.diagnosis import Settings
from fuelid.ident.diagnosis.yardstick import Folds, Scored, compare, long_run_se, make_folds, placebo, refits, \
    trimmed_mean
from fuelid.parallel import jobs
from tests.ident import hidden
from tests.ident.diagnosis.trips import joined

S = Settings()


def test_one_trip_is_folded_into_interleaved_blocks_and_several_trips_by_trip():
    ds = hidden.make(None, n=3000, seed=1)
    folds = make_folds(ds, S)
    held = np.array(folds.held)
    assert folds.kind == "blocks" and len(held) == S.folds
    assert (held.sum(axis=0) == ds.valid).all()  # every valid sample held out exactly once
    chunks = np.floor((ds.t - ds.t[0]) / S.chunk_s).astype(int)
    assert len({c % S.folds for c in chunks[held[1]]}) == 1 and S.chunk_s % S.block_s == 0
    two = make_folds(joined(ds, hidden.make(None, n=3000, seed=2)), S)
    assert two.kind == "trips" and [h.sum() for h in two.held] == [3000, 3000]


@pytest.fixture(scope="module")
def regeneration():
    ds = hidden.make("dpf_regeneration", n=4000, seed=3)
    model = hidden.fitted(ds)
    folds = make_folds(ds, S)
    return ds, folds, refits(model, ds, folds, [], S)


def test_the_true_effect_passes_the_margin_and_a_random_walk_does_not(regeneration):
    ds, folds, base = regeneration
    true = compare(base, refits(list(base.models), ds, folds, ["dpf_regeneration"], S), folds, S)
    assert true.passes and true.drop_percent > 30 and true.mean_gain > S.margin_se * true.gain_se
    assert true.n_blocks >= 15 and true.rmse_with < true.rmse_without
    walk = compare(base, refits(list(base.models), ds, folds, ["level:XX.UnknownSignal"], S), folds, S)
    assert not walk.passes and walk.drop_percent < 5


def test_the_folds_refitted_side_by_side_in_a_worker_are_the_folds_refitted_here(regeneration):
    ds, folds, base = regeneration
    with jobs(2):
        side = refits(list(base.models), ds, folds, ["dpf_regeneration"], S)
    here = refits(list(base.models), ds, folds, ["dpf_regeneration"], S)
    assert np.array_equal(side.ysim, here.ysim, equal_nan=True)
    assert all(np.array_equal(a.theta, b.theta) for a, b in zip(side.models, here.models))


def test_a_margin_no_fit_can_reach_rejects_even_the_true_effect(regeneration):
    ds, folds, base = regeneration
    strict = Settings(margin_se=1e6)
    assert not compare(base, refits(list(base.models), ds, folds, ["dpf_regeneration"], strict), folds, strict).passes


def test_the_fuel_floor_is_the_rms_of_the_explained_fuel_over_the_mean_fuel(regeneration):
    """The regeneration's extra fuel, √(RMSE_without² − RMSE_with²), as a share of the mean fuel: the same passing
    gain is refused when the floor asks for more of the fuel than it explains."""
    ds, folds, base = regeneration
    with_ = refits(list(base.models), ds, folds, ["dpf_regeneration"], S)
    true = compare(base, with_, folds, S)
    held = np.isfinite(base.ysim) & np.isfinite(with_.ysim) & np.isfinite(base.y)
    fuel = np.mean(base.y[held])
    assert true.fuel_percent == pytest.approx(100 * np.sqrt(true.rmse_without ** 2 - true.rmse_with ** 2) / fuel,
                                              rel=0.05)
    assert true.passes and true.fuel_percent > S.min_fuel_percent
    above = Settings(min_fuel_percent=1.1 * true.fuel_percent)
    assert not compare(base, with_, folds, above).passes


def test_a_placebo_shifts_the_candidates_signals_together_by_half_the_data(regeneration):
    ds = regeneration[0]
    sigs = ("AMB.AmbientAirTemp", "AMB.BarometricPress")
    shifted = placebo(ds, sigs)
    half = len(ds.t) // 2
    for s in sigs:
        assert np.array_equal(shifted.extra[s], np.roll(ds.extra[s], half), equal_nan=True)
    assert shifted.extra["ET1.EngCoolantTemp"] is ds.extra["ET1.EngCoolantTemp"]
    assert np.array_equal(shifted.y, ds.y, equal_nan=True) and np.array_equal(shifted.u, ds.u, equal_nan=True)
    assert placebo(ds, ("EEC1.EngSpeed", "EC1.EngMomentOfInertia")) is None  # speed is the model's own input
    assert placebo(ds, ("EC1.EngMomentOfInertia",)) is None  # a constant: the placebo is the candidate itself
    assert placebo(ds, ()) is None


def test_the_true_effect_beats_its_placebo_and_a_random_walk_does_not(regeneration):
    """The regeneration built on its status shifted by half the trip (a placebo of its own shape) gains less than half
    of what the true one does, and the true one's gain beyond it clears the margin; a random walk's does not."""
    ds, folds, base = regeneration

    def judged(spec, signal):
        with_ = refits(list(base.models), ds, folds, [spec], S)
        null = refits(list(base.models), placebo(ds, (signal,)), folds, [spec], S)
        return compare(base, with_, folds, S, null)

    true = judged("dpf_regeneration", "DPFC1.DPFActiveRegenStatus")
    assert true.passes and true.beyond_null_in_se > S.margin_se and true.null_gain < 0.5 * true.mean_gain
    walk = judged("level:XX.UnknownSignal", "XX.UnknownSignal")
    assert not walk.passes and not walk.beyond_null_in_se > S.margin_se


def _scored(ysim: np.ndarray) -> Scored:
    return Scored((), ysim, np.zeros_like(ysim))


def test_a_gain_in_three_blocks_of_forty_passes_beyond_its_placebo_where_the_block_spread_hides_it():
    """A warm-up's gain in the first 3 of 40 blocks decides the blocks' own spread: the mean's t is under √3 whatever
    its size, and the trimmed mean trims it away. Against the spread of a placebo's gains (the same candidate on its
    signal shifted in time: noise on every block) it is many standard errors."""
    rng = np.random.default_rng(5)
    n_b, B = 10, 40
    block = np.repeat(np.arange(B), n_b)
    folds = Folds((np.ones(B * n_b, bool),), block, "blocks")
    base = rng.normal(0.0, 1.0, B * n_b) + np.where(block < 3, 6.0, 0.0)  # the error the effect leaves: 3 blocks
    with_ = base - np.where(block < 3, 6.0, 0.0) + rng.normal(0.0, 0.1, B * n_b)
    null = base + rng.normal(0.0, 0.1, B * n_b)
    h = compare(_scored(base), _scored(with_), folds, S, _scored(null))
    assert h.gain_in_se < np.sqrt(3) and h.trimmed_in_se < S.margin_se
    assert h.beyond_null_in_se > 5 * S.margin_se and h.passes
    assert not compare(_scored(base), _scored(with_), folds, S).passes  # without the placebo: the block spread


def test_a_fuel_delay_is_scored_against_the_fuel_the_bus_reported_not_the_smoother_shifted_one(regeneration):
    """A model fitted to the fuel advanced by τ: its held-out simulation is delayed back by τ and scored against the
    measured fuel, as the base is; a delay the truth does not have (none here) does not pass."""
    from fuelid.ident.fueldelay import shift_signal

    ds, folds, base = regeneration
    delayed = refits(list(base.models), ds, folds, ["fuel_delay=0.45"], S)
    assert np.array_equal(delayed.y, base.y, equal_nan=True)  # both against the measured fuel
    assert not compare(base, delayed, folds, S).passes
    shifted = shift_signal(ds.y, 0.45 / ds.Ts, ds.segments())  # what the model was fitted to: smoother than y
    assert np.nanstd(np.diff(shifted)) < np.nanstd(np.diff(ds.y))


def ar1(rng, n_series: int, B: int, rho: float) -> np.ndarray:
    """n_series AR(1) series of B blocks with mean 0 and unit innovations (the stationary start)."""
    d = np.empty((n_series, B))
    d[:, 0] = rng.normal(size=n_series) / np.sqrt(1 - rho ** 2)
    for b in range(1, B):
        d[:, b] = rho * d[:, b - 1] + rng.normal(size=n_series)
    return d


@pytest.mark.parametrize("rho", [0.0, 0.4])
def test_the_long_run_standard_error_keeps_the_margin_on_correlated_blocks(rho):
    """With no gain at all, 40 block gains correlated as neighbouring blocks are (AR(1), ρ = 0.4) clear 2 standard
    errors on about 11 % of trips when the SE assumes independent blocks (2.3 % for a normal mean); Newey–West's
    about halves that (its bandwidth, 3 blocks, under-corrects a little at B = 40). On independent blocks the two
    agree."""
    d = ar1(np.random.default_rng(3), 4000, 40, rho)
    iid = d.std(axis=1, ddof=1) / np.sqrt(40)
    nw = np.array([long_run_se(x) for x in d])
    rate_iid, rate_nw = (np.mean(d.mean(axis=1) > 2 * se) for se in (iid, nw))
    if rho:
        assert rate_iid > 0.08 and rate_nw < 0.08 and rate_iid > 1.5 * rate_nw
    else:
        assert rate_nw < 0.05 and np.median(nw / iid) == pytest.approx(1.0, abs=0.1)


def test_the_trimmed_mean_is_yuens_with_the_long_run_spread_of_the_winsorised_gains():
    """d̄_γ is scipy's trimmed mean; on independent blocks its standard error is Yuen's, s_w / ((1 − 2γ) √B)."""
    from scipy.stats import trim_mean
    from scipy.stats.mstats import winsorize

    d = np.random.default_rng(7).standard_t(3, size=400)
    mean, se = trimmed_mean(d, 0.2)
    assert mean == pytest.approx(trim_mean(d, 0.2), rel=1e-12)
    yuen = np.asarray(winsorize(d, limits=(0.2, 0.2))).std(ddof=1) / (0.6 * np.sqrt(400))
    assert se == pytest.approx(yuen, rel=0.15)


def test_a_gain_on_every_block_but_two_large_ones_is_carried_by_the_trimmed_mean():
    """Two transient blocks hold most of the squared error (a cold start's first minutes): they decide the plain mean's
    spread, so its t stays under the margin although 38 of 40 blocks gain; the trimmed mean's does not."""
    d = np.r_[20.0, 14.0, np.random.default_rng(1).uniform(0.1, 0.9, 38)]
    t_mean = d.mean() / long_run_se(d)
    mean, se = trimmed_mean(d, S.trim)
    assert t_mean < S.margin_se < mean / se


@pytest.mark.parametrize("rho", [0.0, 0.4])
def test_the_larger_of_the_two_t_statistics_keeps_the_margin_near_its_level(rho):
    """With no gain, the larger of the mean's and the trimmed mean's t clears 2 on at most about 8 % of 40 AR(1)
    blocks (the mean's alone on about 6 %)."""
    d = ar1(np.random.default_rng(4), 2000, 40, rho)
    t = np.array([max(x.mean() / long_run_se(x), np.divide(*trimmed_mean(x, S.trim))) for x in d])
    assert np.mean(t > 2) < (0.1 if rho else 0.065)


@pytest.mark.parametrize("rho", [0.0, 0.4])
def test_the_largest_of_the_three_t_statistics_keeps_the_margin_near_its_level(rho):
    """With no gain, the placebo's gains drawn like the candidate's, (d̄ − d̄_p) / (√2 SE(d̄_p)) clears 2 on about 3 %
    of 40 independent blocks and 6 % of AR(1) ones (ρ = 0.4), and the largest of the three t on about 8 % and 12 %."""
    rng = np.random.default_rng(4)
    d, p = ar1(rng, 2000, 40, rho), ar1(rng, 2000, 40, rho)
    two = np.array([max(x.mean() / long_run_se(x), np.divide(*trimmed_mean(x, S.trim))) for x in d])
    beyond = np.array([(x.mean() - y.mean()) / (np.sqrt(2) * long_run_se(y)) for x, y in zip(d, p)])
    assert np.mean(beyond > 2) < (0.07 if rho else 0.045)
    assert np.mean(np.maximum(two, beyond) > 2) < (0.14 if rho else 0.1)
