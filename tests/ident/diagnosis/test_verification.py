"""ident.diagnosis.verification: the held-out refit, leaving out one block or one trip, against plain least squares."""
import numpy as np

from fuelid.ident.diagnosis import statistics as st
from fuelid.ident.diagnosis.verification import block_cv, block_cv_beside, block_folds, trip_cv, trip_folds


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


def test_block_cv_beside_the_models_own_columns_is_block_cv():
    """What every candidate's held-out refit on one run shares — the model's own columns G and, per left-out
    window, I − G_SᵀG_S — kept once (block_folds): block_cv_beside on [G U] is block_cv on [G U], for no candidate
    columns, a column non-zero inside one window only (I − Q_SᵀQ_S singular there: the pseudo-inverse's case), and
    beside it columns that vary everywhere; the samples not a whole number of blocks."""
    rng = np.random.default_rng(6)
    n = 1030
    Z = rng.normal(size=(n, 5))
    Z[130:150] = 0.0  # so that the column on there alone stays there once orthogonal to G
    local = np.zeros((n, 1))
    local[130:150] = 1.0
    Q = np.linalg.qr(np.column_stack([Z, local, rng.normal(size=(n, 2))]))[0]
    assert np.allclose(Q[:130, 5], 0.0) and np.allclose(Q[150:, 5], 0.0)
    G = Q[:, :5]
    r = rng.normal(size=n)
    r -= G @ (G.T @ r)
    for block, buffer in ((60, 20), (60, 0)):
        folds = block_folds(G, block, buffer)
        for k in (0, 1, 3):
            expected = block_cv(r, st.NuisanceBasis(Q[:, :5 + k]), block, buffer)
            assert np.allclose(block_cv_beside(r, folds, Q[:, 5:5 + k]), expected, atol=1e-12)


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
