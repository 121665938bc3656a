"""Verification of a candidate: a linearised refit scored on held-out blocks.

4. Verification (practical relevance) by a linearised refit scored on held-out blocks. With many samples a
   test detects effects too small to matter, and a slow bus signal can follow the slow wander of the noise by
   chance. So every candidate that passes the tests and explains at least min_effect_percent (at most n_verify
   of them, default 10, by estimated drop) is added to the model and the RMS simulation error of the model with
   and without it is measured on data not used for fitting.
   The refit is one Gauss–Newton step from the fitted θ̂ rather than PEM from scratch: with the effect entering
   as ŷ(t) + Σ_l β_l x(t − l), the simulation-domain error w (Run) of the extended model is, to first order in
   (δ, β) around (θ̂, 0),
       w(t; θ̂ + δ, β) ≈ w(t) − G(t) δ − X(t) β,
   G = [∂ŷ_sim/∂θ_G, 1] the simulation gradient of the model's own parameters and an offset (QG spans it), X the
   candidate's lagged columns in the same domain (A x; for a regressor in the torque unit also its image
   through the model's torque path, B_T/F_T x, the gradient of a torque T + κ x the fuel burns for and the bus
   does not report). (δ, β) minimise Σ w² over the fitting samples — linear least squares, exact for the
   linearised model, nothing re-estimated from scratch. The error is scored by h-block cross-validation in time
   (Burman, Chow & Nolan 1994) over blocks of BLOCK_S = 60 s, each fitted without itself and BUFFER_S = 15 s
   either side (the errors are correlated over seconds; neighbours left in the fit would carry the block's own
   noise into its prediction): with Q an orthonormal basis of [G, X] and e = w − Q Qᵀ w the full-data residual,
   the error on block b of the fit without the samples S ⊇ b is exactly
       e_(S) = e_S + Q_S (I − Q_Sᵀ Q_S)⁺ Q_Sᵀ e_S        (deletion, Woodbury), taken on b,
   so every sample is held out once and no least-squares problem is solved more than once (cost N p² + K p³
   for N samples, p columns, K blocks: milliseconds). Every candidate verified on one run shares the model's own
   columns and their part of each I − Q_Sᵀ Q_S (`block_folds`): each candidate adds only its own columns'
   products (`block_cv_beside`). The segments' initial states are fitted on all the data
   and not refitted per block. The held-out simulation is ŷ = y − e_(b) (through 1/A when A ≠ 1), scored by its
   RMS error and cycle fuel error (eq. 20): rmse_drop_percent = 100 (1 − RMSE_with / RMSE_without). Short
   blocks are possible because nothing is refitted per block, so an effect that lasts minutes (a cold engine
   warming up, a regeneration) is in many fitting blocks and scored on its own.
   A candidate is confirmed when the drop is at least min_drop_percent and the refit moves the fuel the way
   the effect's physics does (Effect.sign: more fuel during a regeneration, none on overrun; on trips with
   nothing hidden the bus's clipping of negative fuel at 0 makes "overrun" look like *more* fuel): the change
   adding it makes to the held-out simulated fuel covaries with the effect's first regressor x with that sign,
   or with x·ŷ for an effect that scales the fuel (Effect.enters == "scales_fuel": air density is nearly constant within
   a trip, and a trip's fuel level is not told apart from its estimated initial state).
   Blocks within one trip do not test what matters for a signal that is nearly constant per trip (an ambient
   condition): whether the effect carries over to another day. So, when the data hold several trips (the run's
   segments grouped at breaks of the log of at least TRIP_BREAK_S, `trip_groups`: other files, other days), the
   refit is also scored leaving one trip out at a time (`leave_one_trip_out`: fitted by least squares on the other
   trips, the model's own directions by minimum norm, the candidate's only in the directions the other trips
   determine beside them, `fold_directions`), and a candidate is confirmed only if the RMS error over the held-out
   trips (pooled) does not rise with it. The candidate's coefficient is not extrapolated from trips that hardly
   determine it: an ambient condition nearly constant on each trip is, on one trip, a change of the model's own
   gains, and a fit on that trip alone puts an arbitrary size on it (on two trips in different weather each fold
   has one trip, so the check needs three: each fold then holds two weathers). A candidate no fold determines
   changes no held-out trip (`determined` False on every trip): its carry-over is untested. And a candidate whose
   coefficient these data cannot determine is reported as not identifiable from these data instead of confirmed
   (`identifiability` below 1/√10, a variance inflation factor above 10): the share of its decisive column (x;
   x·ŷ for an effect that scales the fuel) that the signal's variation makes, (x − x̄) or (x − x̄)·ŷ, left after
   projecting out an offset and the segments' initial states. An effect that scales the fuel with x nearly
   constant is a change of the model's own gains; a signal that moves only with the trip's start is told apart
   from its initial state by nothing. For a bus signal whose physics is not known (a generic candidate,
   Effect.zero False) each trip's level and slow drifts over it are projected out too (`slow_drifts`): a signal
   that differs between days only in its level, or only warms up with the trip, is confounded with everything else
   that differs between days or drifts, and its origin (0 °C) is arbitrary, so it is measured against its own
   deviation (x − x̄)·ŷ.
   Linearising is sound here because the effect enters at β = 0 and the base model is at its optimum: a full PEM
   refit would move θ by δ ~ the effect's size, where the first-order model is accurate; it is also stabler,
   since a refit of the 30+ parameters on half the data adds its own noise to the comparison. A full refit is
   done only where the effect is finally added: `fuelid identify --effect` (PEM with the effect's own dynamics
   B_x/F_x and noise model), which `fuelid compare` and the report then score.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.linalg import cho_solve, cholesky, lstsq, svd
from scipy.linalg.lapack import dpocon

from fuelid.blas import one_blas_thread
from fuelid.ident.diagnosis.run import Run
from fuelid.ident.diagnosis.statistics import NuisanceBasis
from fuelid.ident.filters import lfilter
from fuelid.ident.polymodel import PolyModel
from fuelid.ident.validation import cycle_fuel_error, error_table

BLOCK_S = 60.0  # [s] the blocks left out one at a time when scoring the linearised refit
TRIP_BREAK_S = 600.0  # [s] a break of the log at least this long starts another trip (an engine-off stop, another
#   file, another day): the engine has cooled and the weather and load may differ
MIN_IDENTIFIABILITY = 1.0 / np.sqrt(10.0)  # share of a column not explained by the nuisance columns: VIF ≤ 10
BUFFER_S = 15.0  # [s] also left out of the fit on either side of the scored block (h-block cross-validation):
#   about twice the slowest time constant of the simulated noise H (≈ 9 s), past which the errors decorrelate


def block_cv(r: np.ndarray, Q: NuisanceBasis, block: int, buffer: int = 0) -> np.ndarray:
    """Leave-one-block-out errors of the least-squares fit of r (N) on the orthonormal columns of Q: for
    each block b of `block` consecutive samples, r − Q δ_(−S) on b, δ_(−S) fitted without S = b and `buffer`
    samples either side (h-block cross-validation, Burman, Chow & Nolan 1994: the errors are correlated over
    seconds, and neighbours left in the fit would carry b's own noise into its prediction). Exact, without
    refitting (module docstring, 4): e_(S) = e_S + Q_S (I − Q_Sᵀ Q_S)⁺ Q_Sᵀ e_S, e = r − Q Qᵀ r."""
    e = Q.project_out(r)
    out = e.copy()
    block = max(block, 1)
    for a in range(0, r.size, block):
        lo, hi = max(a - buffer, 0), min(a + block + buffer, r.size)
        Qs, es = Q.rows(lo, hi), e[lo:hi]
        left_out = es + Qs @ _deletion_solve(np.eye(Qs.shape[1]) - Qs.T @ Qs, Qs.T @ es)
        out[a:a + block] = left_out[a - lo:a - lo + block]
    return out


MIN_RCOND = 1e-8  # I − Q_Sᵀ Q_S is solved by Cholesky when its reciprocal condition number is at least this


def _deletion_solve(M: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x = M⁺ b for M = I − Q_Sᵀ Q_S (positive semidefinite: Q has orthonormal columns). Where M is well
    conditioned, as for almost every block, by Cholesky (a tenth of the time of a least-squares solve), its
    condition estimated from the factor (LAPACK dpocon, 1-norm): at ≥ MIN_RCOND no singular value is near the
    1e-10 cut below, and both solve the same system. Where a column of Q lies nearly all inside S (a short
    segment's initial state, an effect on only there) M is nearly singular: its minimum-norm least-squares
    solution, singular values below 1e-10 of the largest cut."""
    try:
        L = cholesky(M, lower=True, check_finite=False)
        rcond, info = dpocon(L, np.abs(M).sum(axis=0).max(), uplo="L")
    except np.linalg.LinAlgError:
        rcond, info = 0.0, 1
    if info == 0 and rcond >= MIN_RCOND:
        return cho_solve((L, True), b, check_finite=False)
    return lstsq(M, b, cond=1e-10, check_finite=False)[0]


class BlockFolds(NamedTuple):
    """What every candidate's held-out-block refit on one run shares (`block_cv_beside`; made by `block_folds`): the
    model's own columns G (N × q, orthonormal), the block, the chunk of rows the windows are made of (gcd(block,
    buffer)), each window's bounds in chunks (K × 2: the rows left out of the fit, a block and `buffer` either side)
    and I − G_SᵀG_S of each window S (K × q × q). Beyond G, which the run holds, q² numbers per window."""

    G: np.ndarray
    block: int
    chunk: int
    bounds: np.ndarray
    outside: np.ndarray


def block_folds(G: np.ndarray, block: int, buffer: int = 0) -> BlockFolds:
    """The BlockFolds of the model's orthonormal columns G (N × q) for blocks of `block` samples left out with
    `buffer` samples either side."""
    n, block = G.shape[0], max(block, 1)
    chunk = math.gcd(block, buffer)
    starts = np.arange(0, n, block)
    bounds = np.column_stack([np.maximum(starts - buffer, 0) // chunk,
                              -(-np.minimum(starts + block + buffer, n) // chunk)])
    # window by window, not `_window_sums`: its products of every chunk would take as much memory as G itself
    outside = np.stack([np.eye(G.shape[1]) - G[lo:hi].T @ G[lo:hi] for lo, hi in np.minimum(bounds * chunk, n)])
    return BlockFolds(G, block, chunk, bounds, outside)


def _window_sums(folds: BlockFolds, A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A_SᵀB_S for each window S of folds (K × a × b; A: N × a, B: N × b): the products over each chunk of rows,
    summed over the window's chunks."""
    c = folds.chunk
    whole = A.shape[0] // c
    sums = np.empty((-(-A.shape[0] // c), A.shape[1], B.shape[1]))
    sums[:whole] = A[:whole * c].reshape(whole, c, -1).transpose(0, 2, 1) @ B[:whole * c].reshape(whole, c, -1)
    if whole < sums.shape[0]:  # the last rows, fewer than a chunk
        sums[whole] = A[whole * c:].T @ B[whole * c:]
    np.cumsum(sums, axis=0, out=sums)  # sums[j]: over the chunks up to j
    lo, hi = folds.bounds.T
    return sums[hi - 1] - np.where((lo > 0)[:, None, None], sums[lo - 1], 0.0)


def block_cv_beside(r: np.ndarray, folds: BlockFolds, U: np.ndarray) -> np.ndarray:
    """`block_cv` of r (N) on the columns Q = [G U]: the model's own G (folds) and U (N × k, orthonormal and
    orthogonal to G; k may be 0). With M_G = I − G_SᵀG_S of each window (folds.outside), shared by every U,
        I − Q_SᵀQ_S = [[M_G, −G_SᵀU_S], [−U_SᵀG_S, I − U_SᵀU_S]],
    each product over the window a sum of products over its chunks of rows: every window at once, in N (q + k)(k + 1)
    multiplications beyond the folds' instead of N (q + k)² over the windows' rows."""
    G, block = folds.G, folds.block
    e = r - G @ (G.T @ r) - U @ (U.T @ r)
    GU, UU = _window_sums(folds, G, U), _window_sums(folds, U, U)
    M = np.block([[folds.outside, -GU], [-GU.transpose(0, 2, 1), np.eye(U.shape[1]) - UU]])
    b = np.concatenate([_window_sums(folds, G, e[:, None]), _window_sums(folds, U, e[:, None])], axis=1)
    x = _deletion_solves(M, b)[..., 0]  # K × (q + k): window j's coefficients, for its block j
    q, whole = G.shape[1], r.size // block
    change = np.empty(r.size)
    change[:whole * block] = (G[:whole * block].reshape(whole, block, q) @ x[:whole, :q, None]
                              + U[:whole * block].reshape(whole, block, -1) @ x[:whole, q:, None]).ravel()
    if whole < x.shape[0]:  # the last block, shorter
        change[whole * block:] = G[whole * block:] @ x[whole, :q] + U[whole * block:] @ x[whole, q:]
    return e + change


def _deletion_solves(M: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`_deletion_solve` of each of a stack of M_j (K × p × p) and b_j (K × p × m): where M_j is well conditioned
    (its Cholesky factor's condition estimate, as there) by numpy's solve of the whole stack at once (LU: numpy has
    no stacked triangular solve), else its minimum-norm least-squares solution."""
    try:
        L = np.linalg.cholesky(M)
    except np.linalg.LinAlgError:  # one of them is not positive definite: each on its own
        return np.stack([_deletion_solve(Mj, bj) for Mj, bj in zip(M, b)])
    direct = np.array([dpocon(Lj, np.abs(Mj).sum(axis=0).max(), uplo="L") for Lj, Mj in zip(L, M)]).reshape(-1, 2)
    well = (direct[:, 1] == 0) & (direct[:, 0] >= MIN_RCOND)
    x = np.empty(b.shape)
    x[well] = np.linalg.solve(M[well], b[well])
    for j in np.flatnonzero(~well):
        x[j] = lstsq(M[j], b[j], cond=1e-10, check_finite=False)[0]
    return x


def held_out(model: PolyModel, run: Run, X: np.ndarray, folds: BlockFolds | None = None) -> dict:
    """The linearised refit of `model` with the extra columns X (w domain, stacked like run.r; none: N × 0),
    scored block by block on data it was not fitted on (block_cv_beside, blocks of BLOCK_S [s] with BUFFER_S [s]
    either side also left out; folds: `run_block_folds` of run, when the caller keeps them): ysim (N on the dataset
    grid, the held-out simulation, NaN outside the run), y (the fuel it is scored against) and beta (X's
    coefficients fitted on all the data, for the size of the effect)."""
    with one_blas_thread():
        folds = run_block_folds(model, run) if folds is None else folds
        Xt = run.QG.project_out(X)
        err = block_cv_beside(run.r, folds, _added_directions(Xt, X))
        beta = lstsq(Xt, run.r, cond=1e-10, check_finite=False)[0] if X.shape[1] else np.zeros(0)
    err = _through_1_over_A(model, run, err)  # the step is linear in w = A·(simulation error)
    ysim = np.full(len(run.y), np.nan)
    ysim[run.index] = run.y[run.index] - err
    return {"ysim": ysim, "y": run.y, "beta": beta}


def run_block_folds(model: PolyModel, run: Run) -> BlockFolds:
    """The BlockFolds of the model's own columns run.QG.dense for blocks of BLOCK_S [s] with BUFFER_S [s] either
    side (model.Ts [s] the sample period)."""
    with one_blas_thread():
        return block_folds(run.QG.dense, round(BLOCK_S / model.Ts), round(BUFFER_S / model.Ts))


def trips(ds, run: Run, break_s: float = TRIP_BREAK_S) -> list[list[int]]:
    """The indices into run.segs of each trip: the run's segments, grouped where the log breaks for at least
    break_s [s]."""
    groups = []
    for k, seg in enumerate(run.segs):
        if not groups or ds.t[seg.start] - ds.t[run.segs[k - 1].stop - 1] >= break_s:
            groups.append([])
        groups[-1].append(k)
    return groups


def trip_groups(ds, run: Run, break_s: float = TRIP_BREAK_S) -> list[np.ndarray]:
    """Positions in the stacked run (run.r) of each trip (`trips`)."""
    ends = np.cumsum(run.lens)
    return [np.concatenate([np.arange(ends[k] - run.lens[k], ends[k]) for k in trip])
            for trip in trips(ds, run, break_s)]


class TripFolds(NamedTuple):
    """What every candidate's leave-one-trip-out refit on one run shares (`trip_cv`; made by `trip_folds`): the
    model's own columns G (N × q, orthonormal over all samples), the positions `held` of each trip and the Gram
    matrix of G's rows outside each, I − G_gᵀG_g (q × q each: the folds cost q² each to keep, not N q)."""

    G: np.ndarray
    held: list[np.ndarray]
    outside: list[np.ndarray]


def trip_folds(G: np.ndarray, groups) -> TripFolds:
    """The TripFolds of the model's orthonormal columns G (N × q) and the trips' positions `groups` (trip_groups)."""
    return TripFolds(G, list(groups), [np.eye(G.shape[1]) - G[g].T @ G[g] for g in groups])


def trip_cv(r: np.ndarray, folds: TripFolds, X: np.ndarray) -> tuple[np.ndarray, list[bool]]:
    """Leave-one-trip-out errors of the least-squares fit of r (N) on the model's orthonormal columns G (folds.G,
    N × q) and the extra columns X (N × p): on each trip's positions g (folds.held), r − [G X] c_(−g), c_(−g) fitted on
    the samples outside g — X only in the directions those samples determine (`fold_directions`): a coefficient the
    other trips hardly determine (a signal nearly constant on each of them, confounded with the model's own gains)
    is not extrapolated to the trip left out, it stays at 0 as in the model without it. Also, per trip, whether the
    others determined any direction.

    With Z = [G, U V] (U an orthonormal basis of X's part beside G, V the directions kept: Z orthonormal over all
    samples) the fit without g is the deletion formula of `block_cv` on g: with e = r − Z Zᵀ r,
        e_(g) = e_g + Z_g (I − Z_gᵀ Z_g)⁺ Z_gᵀ e_g,
    made of the trip's own rows, and of I − G_gᵀG_g (folds.outside), which every candidate shares: no least-squares
    problem over the other trips' samples is solved. (I − G_gᵀG_g)⁺ is `_deletion_solve`'s: where a direction of G
    lies (nearly) inside g, the minimum-norm solution, which leaves it at 0."""
    G = folds.G
    U = _added_directions(X - G @ (G.T @ X), X)
    Gr, Ur = G.T @ r, U.T @ r
    out, determined = r.copy(), []
    for g, M_G in zip(folds.held, folds.outside):
        Gg, Ug = G[g], U[g]
        V = fold_directions(M_G, Gg.T @ Ug, np.eye(U.shape[1]) - Ug.T @ Ug)
        determined.append(V.shape[1] > 0)
        Bg = Ug @ V
        GB = Gg.T @ Bg
        M = np.block([[M_G, -GB], [-GB.T, np.eye(V.shape[1]) - Bg.T @ Bg]])
        Zg = np.column_stack([Gg, Bg])
        eg = r[g] - Zg @ np.concatenate([Gr, V.T @ Ur])
        out[g] = eg + Zg @ _deletion_solve(M, Zg.T @ eg)
    return out, determined


def _added_directions(Xt: np.ndarray, X: np.ndarray) -> np.ndarray:
    """An orthonormal basis of Xt, the part of the columns X that the model's columns do not explain, each scaled by
    its column of X first; directions below 10⁻⁴ of that dropped (the same rank rule as the tests)."""
    U, sig, _ = svd(Xt / np.maximum(np.linalg.norm(X, axis=0), 1e-300), full_matrices=False, check_finite=False)
    return U[:, sig > 1e-4]


def fold_directions(M_G: np.ndarray, C: np.ndarray, M_U: np.ndarray) -> np.ndarray:
    """The directions V (columns, orthonormal) of the extra columns U (orthonormal over all samples, ⊥ G) that the
    samples outside a trip g determine beside the model's own columns G: the eigenvectors of WᵀW, W = P⊥_G U on
    those samples, whose eigenvalue — the share of the direction's variation over all samples that these hold and G
    does not explain there — is at least MIN_IDENTIFIABILITY² (a variance inflation factor of at most 10, the rule
    `identifiability` applies to all the data). From g's rows alone: M_G = I − G_gᵀG_g, C = G_gᵀU_g (the other
    samples' G_fᵀU_f is −C, since GᵀU = 0), M_U = I − U_gᵀU_g; WᵀW = M_U − Cᵀ M_G⁺ C."""
    if C.shape[1] == 0:
        return np.zeros((0, 0))
    share, V = np.linalg.eigh(M_U - C.T @ _deletion_solve(M_G, C))
    return V[:, share >= MIN_IDENTIFIABILITY ** 2]


class TripScores(NamedTuple):
    """`leave_one_trip_out` per trip: the RMS simulation error [output unit], and whether the other trips determined
    any direction of the extra columns (False: they were left at 0, the trip scored as without them)."""

    rmse: list[float]
    determined: list[bool]


def leave_one_trip_out(model: PolyModel, run: Run, X: np.ndarray, folds: TripFolds) -> TripScores:
    """The linearised refit with the extra columns X (w domain, stacked like run.r) on each trip (folds: trip_folds
    of run.QG.dense), fitted on the other trips (trip_cv)."""
    with one_blas_thread():
        err, determined = trip_cv(run.r, folds, X)
    err = _through_1_over_A(model, run, err)
    return TripScores([float(np.sqrt(np.mean(err[g] ** 2))) for g in folds.held], determined)


def identifiability(run: Run, varying: np.ndarray, column: np.ndarray,
                    confounders: np.ndarray | None = None) -> float:
    """How much of an effect's decisive column (fuel domain, stacked like run.r) its signal's variation determines:
    ‖M varying‖ / ‖column − mean‖, M projecting out an offset, the segments' initial states (run.QG's free
    responses) and the confounders given (columns stacked like run.r: `slow_drifts`), `varying` the column made of
    the signal's deviation from its mean (module docstring, 4; with A = 1, as in a Box-Jenkins model, the same in
    the w domain)."""
    extra = np.zeros((varying.size, 0)) if confounders is None else confounders
    initial_states = NuisanceBasis(np.zeros((varying.size, 0)), run.QG.blocks)
    Z = initial_states.extended(np.column_stack([np.ones(varying.size), extra]))
    left = Z.project_out(varying)
    return float(np.linalg.norm(left) / max(np.linalg.norm(column - column.mean()), 1e-300))


def slow_drifts(ds, run: Run, carrier: np.ndarray, degree: int = 2) -> np.ndarray:
    """A level and a slow drift over each trip (trip_groups) of what `carrier` (stacked like run.r) stands for:
    P_k(τ)·carrier, P_k the Legendre polynomials of degree 0..degree in the trip's time τ ∈ [−1, 1], zero on the
    other trips. A bus signal whose physics is not known and that differs between trips only by its level, or moves
    within one only as slowly as these (an oil temperature warming up), is told apart from everything else that
    differs between days or drifts over a trip — the other temperatures warming with it, the weather, the tyres —
    by nothing."""
    t = ds.t[run.index]
    cols = []
    for g in trip_groups(ds, run):
        tau = np.interp(t[g], (t[g].min(), max(t[g].max(), t[g].min() + 1e-9)), (-1.0, 1.0))
        for k in range(degree + 1):
            col = np.zeros(t.size)
            col[g] = np.polynomial.legendre.Legendre.basis(k)(tau) * carrier[g]
            cols.append(col)
    return np.column_stack(cols)


def _through_1_over_A(model: PolyModel, run: Run, err: np.ndarray) -> np.ndarray:
    """Errors in w = A·(simulation error) back to simulation errors, segment by segment (the identity when A = 1)."""
    if model.A.size == 1:
        return err
    ends = np.cumsum(run.lens)
    return np.concatenate([lfilter([1.0], model.A, err[a:b]) for a, b in zip(ends - run.lens, ends)])


def held_out_scores(cv: dict, ds) -> dict:
    """RMS simulation error [output unit] and cycle fuel errors [%] (eq. 20; mean and RMS over the cycles) of a
    held_out result on its held-out blocks."""
    y, ysim = cv["y"], cv["ysim"]
    ok = np.isfinite(ysim) & np.isfinite(y)
    return {"rmse": float(np.sqrt(np.mean((ysim[ok] - y[ok]) ** 2))),
            "cycle_fuel_error_percent": error_table(cycle_fuel_error(np.where(ok, y, np.nan), ysim, ds.cycle, ds.Ts))}


@dataclass(eq=False)
class Baseline:
    """The model as it is, scored on data it was not fitted on: what every verification on its run measures a
    candidate against (`verify`; made by `baseline`). ysim: its held-out simulation block by block (`held_out`
    without extra columns; N on the dataset grid), scores: held_out_scores of it; groups: the run's positions of
    each trip (trip_groups); blocks: what every candidate's held_out on this run shares (`run_block_folds`)."""

    model: PolyModel
    run: Run
    groups: list[np.ndarray]
    blocks: BlockFolds
    ysim: np.ndarray
    scores: dict

    @functools.cached_property
    def folds(self) -> TripFolds:
        """The trips' folds of the model's own columns (trip_folds), which every candidate's leave_one_trip_out on
        this run shares: made once, when first read."""
        with one_blas_thread():
            return trip_folds(self.run.QG.dense, self.groups)

    @functools.cached_property
    def trips(self) -> TripScores:
        """Scored leaving one trip out (leave_one_trip_out without extra columns): every candidate verified on this
        run on several trips is compared with it, so it is made once, when first read."""
        return leave_one_trip_out(self.model, self.run, np.zeros((self.run.r.size, 0)), self.folds)


def baseline(model: PolyModel, run: Run, ds) -> Baseline:
    """The Baseline of `model`, whose Run on dataset ds is `run`."""
    blocks = run_block_folds(model, run)
    ysim = held_out(model, run, np.zeros((run.r.size, 0)), blocks)["ysim"]
    return Baseline(model, run, trip_groups(ds, run), blocks, ysim, held_out_scores({"y": run.y, "ysim": ysim}, ds))


def verify(base: Baseline, X: np.ndarray, ds) -> tuple[dict, np.ndarray, np.ndarray]:
    """The held-out scores with the candidate columns X (w domain, stacked like base.run.r) against the model as it
    is (`base`, its Baseline on its run): (`without_with`: RMS simulation error [output unit] and cycle fuel error [%]
    without and with, the drop [%]; β the candidate's coefficients fitted on all the data; the change of the held-out
    simulated fuel [output unit] that adding it makes, stacked like run.r)."""
    after = held_out_scores(cv := held_out(base.model, base.run, X, base.blocks), ds)
    return without_with(base.scores, after), cv["beta"], (cv["ysim"] - base.ysim)[base.run.index]


def without_with(before: dict, after: dict) -> dict:
    """Two held_out_scores side by side: RMS simulation error [output unit] and cycle fuel error [%] without and
    with, and the RMS error's drop [%]."""
    return {"rmse_without": before["rmse"], "rmse_with": after["rmse"],
            "rmse_drop_percent": 100.0 * (1.0 - after["rmse"] / before["rmse"]),
            "cycle_fuel_error_percent_without": before["cycle_fuel_error_percent"],
            "cycle_fuel_error_percent_with": after["cycle_fuel_error_percent"]}
