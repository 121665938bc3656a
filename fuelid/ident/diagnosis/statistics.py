"""The statistics of the diagnosis, plain functions over arrays: the two score tests of a candidate effect and
Holm's correction over many.

Which effect is missing — two score tests per candidate, Holm, then verification
--------------------------------------------------------------------------------
The model M gives one-step prediction errors ε = D/C (A ỹ − Σ_i B_i/F_i ũ_i) and simulation errors
r = ỹ − Σ_i B_i/(A F_i) ũ_i. If an effect with regressors x(t) (N × k, ident.effects, at a few lags) were
missing, y would contain Σ_l β_l x(t − l). The regressors follow how the effect enters the model
(ident.diagnosis.entries): an effect that scales the fuel, y (1 + m x), has x and x·ŷ (ŷ the model's simulated fuel:
the gradient at m = 0, with the model's dynamics); a torque the bus does not report, T + κ x, has the fuel the
model's torque path makes of it, B_T/(A F_T) x (the gradient at κ = 0, one column).

1. Prediction-error (score / Lagrange-multiplier) test. ε would contain ψ_x = D/C x (the gradient −∂ε/∂β at
   β = 0). With Z = [Ψ_θ, D/C·1, I_ε] (the PEM gradient at θ̂, an offset, and the free responses through which
   each segment's unknown initial state enters, `free_responses`: estimated, not waited out, so a cold start at
   the beginning of the log is tested too) and M_Z = I − Z Z⁺, the score is
   s = (M_Z ψ_x)ᵀ ε and LM = sᵀ Ω̂⁻¹ s ~ χ²(k_eff) under "no such effect", Ω̂ the Newey–West (Bartlett,
   L = ⌊4 (N/100)^{2/9}⌋ lags) long-run covariance of g_t = (M_Z ψ_x)(t) ε(t) (for white ε this is the textbook
   N R²; the robust form keeps the level when ε is not quite white or its variance changes with load,
   Wooldridge 1990). k_eff is the rank of M_Z ψ_x.

2. Simulation-error (level) test, generalised least squares with the noise estimated under the alternative.
   Test 1 is computed at the model fitted without the effect, and a slow effect — a 20-minute DPF
   regeneration, a cold start — is partly absorbed there by the noise model as low-frequency noise (C and D get
   roots near 1, D/C x of a step is two spikes): the test keeps its level but loses its power. So each
   candidate is also tested where a level shift is not whitened away, in r: with the simulation gradient
   Z_G = [∂ŷ_sim/∂θ_G, 1, I_w] (I_w the free responses of 1/F_i) projected out of r and x (x̃ = M_G x,
   r̃ = M_G r), the candidate's coefficient is estimated by least squares, β̂ = x̃⁺ r̃, and the noise
   v = r̃ − x̃ β̂ — the noise *under the alternative*, with the effect removed — is fitted by an AR(p) model
   a(q) (Yule–Walker, p = AR_ORDER = 100 samples, 30 s). Then
   a(q) r̃ and a(q) x̃ are whitened, and the score test of (1) without nuisance columns gives
   LM ~ χ²(k_eff) under "no such effect" (feasible GLS; the Newey–West covariance covers what the AR(p)
   leaves, Andrews & Monahan 1992). Under the null v is the noise and a(q) whitens it; under the alternative
   it is still the noise (the effect was taken out first), so a level shift is not absorbed.

   A candidate's p-value is min(1, 2 min(p₁, p₂)) (Bonferroni over its two tests: valid whatever their
   dependence). Its effect size is the share of the simulation error it explains, estimated_drop_percent =
   100 (1 − ‖v‖/‖r̃‖): how much the RMS simulation error would fall with it (before any refit).

3. Many candidates: Holm's step-down correction of those p-values (`p_holm`, `test_significant`). The user's
   requirement is that on data with no missing effect *no* candidate is flagged in ≥ 95 % of trips: the
   family-wise error rate, which Holm controls at α under any dependence between the tests (bus signals are
   strongly dependent: coolant and oil temperature, torque-like signals); Benjamini–Hochberg controls the
   false-discovery proportion instead, which needs positive dependence.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.fft import irfft, next_fast_len, rfft
from scipy.linalg import blas, lapack, qr, solve_toeplitz, svd
from scipy.special import chdtrc

from fuelid.ident.filters import lfilter

RANK_TOL = 1e-10  # a nuisance column independent of the others by less than this share of its norm adds nothing
WELL_INDEPENDENT = 10.0  # σ_min of the scaled nuisance columns, in RANK_TOL, from which no column is dependent:
#   a margin over the rounding of a pivoted QR's |R_jj| (about 1e-15 of these unit columns)
CHOLESKY_QR_ORTHOGONALITY = 0.5  # ‖Q₁ᵀQ₁ − I‖_F up to which a second Cholesky QR makes Q₁ orthonormal to rounding
AR_ORDER = 100  # samples of the AR whitener of the simulation-error test (30 s at 0.3 s)


@dataclass(frozen=True)
class ScoreTest:
    """LM statistic, its degrees of freedom k_eff, p-value (and log p, which does not underflow), and β̂ the
    coefficients of the candidate columns in the least-squares regression of ε on [Z, ψ_x]."""

    statistic: float
    df: int
    p_value: float
    log_p: float
    coef: np.ndarray


def _chi2_tail(statistic: float, k: int) -> tuple[float, float]:
    """(p, ln p): the χ²(k) upper tail at the statistic, as scipy.stats.chi2.sf and .logsf compute it (the
    regularised incomplete gamma function, from scipy.special: every command would pay for importing scipy.stats).
    A statistic below 0 (rounding of a quadratic form at 0) has p = 1."""
    p = float(chdtrc(k, max(statistic, 0.0)))
    with np.errstate(divide="ignore"):
        return p, float(np.log(p))


def newey_west_lags(n: int) -> int:
    """The Bartlett kernel's bandwidth L = ⌊4 (n/100)^{2/9}⌋ for n observations (Newey & West 1994)."""
    return int(4 * (n / 100.0) ** (2 / 9))


def newey_west(g: np.ndarray, lags: int) -> np.ndarray:
    """Long-run covariance Σ_{|l|≤L} (1 − |l|/(L+1)) Γ_l of the rows of g (N × k), Γ_l = Σ_t g_t g_{t−l}ᵀ."""
    omega = g.T @ g
    for lag in range(1, lags + 1):
        gamma = g[lag:].T @ g[:-lag]
        omega += (1.0 - lag / (lags + 1.0)) * (gamma + gamma.T)
    return omega


@dataclass(frozen=True)
class NuisanceBasis:
    """An orthonormal basis Q = [Q_1 … Q_S, Q_d] (N × p) of nuisance columns, so that M_Z x = x − Q Qᵀ x.

    Q_s spans columns that are zero outside segment s (its initial state's free responses, `free_responses`):
    Q is block-diagonal there, and each block is kept on its own rows (n_s × p_s, the segments' rows in order,
    covering all N). Q_d (N × p_d) spans the columns that run through every segment, made orthogonal to the
    blocks. Stored densely, Q would take N·(p_d + S·p_s) numbers, and a truck's week is a few hundred
    segments: quadratic in the data; stored this way it takes N·(p_d + p_s)."""

    dense: np.ndarray
    blocks: tuple[np.ndarray, ...] = ()

    @functools.cached_property
    def bounds(self) -> list[tuple[int, int]]:
        """Rows (start, stop) of each block."""
        ends = np.cumsum([b.shape[0] for b in self.blocks], dtype=int)
        return [(int(e - b.shape[0]), int(e)) for e, b in zip(ends, self.blocks)]

    def project_out(self, X: np.ndarray) -> np.ndarray:
        """M_Z X = X − Q Qᵀ X (X: N or N × k; Q_d is orthogonal to every block, so the parts subtract)."""
        X = np.asarray(X, float)
        out = X - self.dense @ (self.dense.T @ X)
        for (a, b), Qs in zip(self.bounds, self.blocks):
            out[a:b] -= Qs @ (Qs.T @ X[a:b])
        return out

    def extended(self, X: np.ndarray, rank_tol: float = RANK_TOL) -> NuisanceBasis:
        """The basis of these nuisance columns and the columns of X (N × k). A column whose part outside the span
        so far is below rank_tol of its norm adds nothing (an exact dependence: an offset that the trips' levels
        already hold): a plain QR would add a direction made of rounding errors instead."""
        X = np.asarray(X, float).reshape(self.dense.shape[0], -1)
        added = _orthonormal_columns(self.project_out(X), np.linalg.norm(X, axis=0), rank_tol)
        return NuisanceBasis(np.column_stack([self.dense, added]), self.blocks) if added.shape[1] else self


def _orthonormal_columns(X: np.ndarray, norms: np.ndarray, rank_tol: float) -> np.ndarray:
    """An orthonormal basis of the columns of X (N × k) whose independent part is at least rank_tol of norms (each
    column's own size). A QR with column pivoting, cut where |R_jj| falls below rank_tol, decides which; but when the
    scaled columns' smallest singular value is WELL_INDEPENDENT times rank_tol or more, no |R_jj| can fall below it
    (|R_jj| ≥ σ_min for every triangular factor), so every column is kept and Cholesky QR twice (`_cholesky_qr2`)
    makes the basis: a few matrix products, where a pivoted QR works column by column."""
    if not X.shape[1]:
        return X
    scaled = X / np.where(norms > 0, norms, 1.0)
    twice = _cholesky_qr2(scaled)
    if twice is not None and svd(twice[1], compute_uv=False, check_finite=False)[-1] >= WELL_INDEPENDENT * rank_tol:
        return twice[0]
    return pivoted_qr_columns(scaled, rank_tol)


def pivoted_qr_columns(X: np.ndarray, rank_tol: float) -> np.ndarray:
    """An orthonormal basis of the columns of X (N × k, scaled to unit norm) by QR with column pivoting, cut where
    |R_jj| falls below rank_tol: a column independent of the others by less adds nothing."""
    Q, R, _ = qr(X, mode="economic", pivoting=True, check_finite=False)
    return Q[:, np.abs(np.diag(R)) > rank_tol]


def _cholesky_qr2(X: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(Q, R), X = Q R with Q (N × k) orthonormal and R upper triangular, by Cholesky QR — R₁ the Cholesky factor of
    XᵀX, Q₁ = X R₁⁻¹ — and Cholesky QR of Q₁ again, which the first pass leaves orthonormal only to about u κ(X)²
    (CholeskyQR2: Yamamoto, Nakatsukasa, Yanagisawa & Fukaya 2015); None when XᵀX is not numerically positive
    definite or ‖Q₁ᵀQ₁ − I‖_F > CHOLESKY_QR_ORTHOGONALITY (X too ill-conditioned for the second pass to finish)."""
    Xt = X.T  # k × N in column order, as the triangular solves take it, without a copy
    R1 = _upper_cholesky(Xt @ Xt.T)
    if R1 is None:
        return None
    Q1t = blas.dtrsm(1.0, R1, Xt, side=0, lower=0, trans_a=1)  # Q₁ᵀ = R₁⁻ᵀ Xᵀ
    gram = Q1t @ Q1t.T
    if not np.linalg.norm(gram - np.eye(len(gram))) <= CHOLESKY_QR_ORTHOGONALITY:  # NaN fails too
        return None
    R2 = _upper_cholesky(gram)
    return blas.dtrsm(1.0, R2, Q1t, side=0, lower=0, trans_a=1, overwrite_b=1).T, R2 @ R1


def _upper_cholesky(gram: np.ndarray) -> np.ndarray | None:
    """The upper Cholesky factor R (RᵀR = gram) of a symmetric matrix; None when it is not positive definite."""
    R, info = lapack.dpotrf(gram, lower=0, clean=1)
    return None if info else R


def nuisance_basis(Z: np.ndarray, segment_columns=()) -> NuisanceBasis:
    """The orthonormal basis of the nuisance columns Z (N × p, through every segment) and of segment_columns:
    per segment, in order, the columns (n_s × p_s) that are zero outside it, Σ n_s = N (none: Z alone)."""
    Z = np.asarray(Z, float)
    blocks = tuple(_orthonormal_columns(C, np.linalg.norm(C, axis=0), RANK_TOL)
                   for C in (np.asarray(C, float) for C in segment_columns))
    if blocks and sum(b.shape[0] for b in blocks) != Z.shape[0]:
        raise ValueError("the segments' columns must cover the rows of Z")
    return NuisanceBasis(np.zeros((Z.shape[0], 0)), blocks).extended(Z)


def score_test(eps, X, Q=None, hac_lags: int | None = None, rank_tol: float = 1e-4,
               eps_projected: np.ndarray | None = None, X_projected: np.ndarray | None = None) -> ScoreTest:
    """Score (LM) test that ε (N) does not depend on the columns of X (N × k) beyond the nuisance columns with
    basis Q (`nuisance_basis`; None: only a mean): LM = sᵀ Ω̂⁻¹ s ~ χ²(k_eff), module
    docstring. Columns of X whose part orthogonal to Q has less than rank_tol of their norm are not testable
    (k_eff counts the rest); k_eff = 0 gives LM = 0, p = 1. eps_projected, X_projected: Q.project_out(eps) and
    Q.project_out(X), when the caller tests many candidates on the same ε (and projects all their columns at once)."""
    eps = np.asarray(eps, float)
    X = np.asarray(X, float).reshape(eps.size, -1)
    if Q is not None:
        Xt = Q.project_out(X) if X_projected is None else X_projected
        et = Q.project_out(eps) if eps_projected is None else eps_projected
    else:
        Xt, et = X - X.mean(axis=0), eps - eps.mean()
    coef = np.linalg.lstsq(Xt, et, rcond=None)[0] if Xt.size else np.zeros(0)
    norms = np.linalg.norm(X, axis=0)
    norms[norms == 0] = 1.0
    U, sig, Vt = svd(Xt / norms, full_matrices=False, check_finite=False)
    keep = sig > rank_tol
    k = int(keep.sum())
    if k == 0:
        return ScoreTest(0.0, 0, 1.0, 0.0, coef)
    W = U[:, keep]  # orthonormal basis of the testable directions
    g = W * et[:, None]
    L = newey_west_lags(eps.size) if hac_lags is None else hac_lags
    s = g.sum(axis=0)
    lm = float(s @ np.linalg.solve(newey_west(g, L), s))
    return ScoreTest(lm, k, *_chi2_tail(lm, k), coef)


def ar_whitener(v: np.ndarray, order: int) -> np.ndarray:
    """a(q) = 1 − Σ_{j=1..p} φ_j q⁻ʲ of the AR(p) model of v fitted by Yule–Walker (biased autocovariances by
    FFT, Levinson solve), so that a(q) v is approximately white; always stable."""
    v = np.asarray(v, float) - np.mean(v)
    n = v.size
    # zero-padded to ≥ 2n − 1 the circular correlation is the linear one; a length of small prime factors, since
    # 2n has a large one for most n (pocketfft then falls back to Bluestein, many times slower)
    fft_len = next_fast_len(2 * n - 1, real=True)
    spec = rfft(v, fft_len)
    acov = irfft(spec * np.conj(spec), fft_len)[: order + 1] / n
    if acov[0] <= 0:
        return np.ones(1)
    return np.r_[1.0, -solve_toeplitz(acov[:order], acov[1:order + 1], check_finite=False)]


def level_test(r: np.ndarray, X: np.ndarray, lens, QG: NuisanceBasis, order: int = AR_ORDER,
               rank_tol: float = 1e-4, X_projected: np.ndarray | None = None) -> tuple[ScoreTest, float]:
    """The simulation-error test (module docstring, 2): r (N) the simulation errors with the basis QG of the
    simulation gradient already projected out, X (N × k) the candidate's columns, lens the lengths of the
    segments r is stacked from (each filtered from rest, its first `order` samples dropped); X_projected:
    QG.project_out(X), when the caller has it. Returns the test and the fraction ‖v‖/‖r‖ of the simulation error
    left after the candidate's least-squares fit.

    In the whitened domain the statistic is the Wald form W = ‖P_X a r‖² / σ̂², σ̂² the variance of a(q) v
    (the whitened noise under the alternative): a level shift whitens to a spike, and the score form's robust
    variance, built from errors that still contain the effect, would let that one sample cancel its own
    evidence."""
    Xt = QG.project_out(X) if X_projected is None else X_projected
    beta = np.linalg.lstsq(Xt, r, rcond=None)[0]
    v = r - Xt @ beta
    a = ar_whitener(v, order)
    ends = np.cumsum(lens)
    rw, Xw, vw = [], [], []
    for start, stop in zip(ends - np.asarray(lens), ends):
        rw.append(lfilter(a, [1.0], r[start:stop])[order:])
        vw.append(lfilter(a, [1.0], v[start:stop])[order:])
        Xw.append(lfilter(a, [1.0], Xt[start:stop], axis=0)[order:])
    rw, vw, Xw = np.concatenate(rw), np.concatenate(vw), np.vstack(Xw)
    left = float(np.linalg.norm(v) / max(np.linalg.norm(r), 1e-300))
    norms = np.linalg.norm(Xw, axis=0)
    norms[norms == 0] = 1.0
    U, sig, _ = svd(Xw / norms, full_matrices=False, check_finite=False)
    k = int((sig > rank_tol).sum())
    if k == 0 or rw.size <= k:
        return ScoreTest(0.0, 0, 1.0, 0.0, beta), left
    proj = U[:, :k].T @ rw
    wald = float(proj @ proj / (vw @ vw / (vw.size - k)))
    return ScoreTest(wald, k, *_chi2_tail(wald, k), beta), left


def holm(p_values, alpha: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Holm's step-down adjusted p-values p̃_(i) = max_{j≤i} min(1, (m − j + 1) p_(j)) (sorted order) and the
    rejections p̃ < alpha; controls the family-wise error rate at alpha under any dependence."""
    p = np.asarray(p_values, float)
    m = p.size
    order = np.argsort(p)
    adj = np.empty(m)
    adj[order] = np.minimum(1.0, np.maximum.accumulate((m - np.arange(m)) * p[order]))
    return adj, adj < alpha


def lagged(x: np.ndarray, lags) -> np.ndarray:
    """Columns x_j(t − l) for each column j and lag l ≥ 0 (zero before the start): N × (k·len(lags))."""
    x = np.asarray(x, float).reshape(len(x), -1)
    out = np.zeros((x.shape[0], x.shape[1] * len(lags)))
    for i, lag in enumerate(lags):
        out[lag:, i * x.shape[1]:(i + 1) * x.shape[1]] = x[: x.shape[0] - lag]
    return out


def free_responses(denominators, n: int) -> np.ndarray:
    """Columns (n × Σ deg) spanning every free (zero-input) response of the filters 1/den over n samples: for each
    denominator of degree d, its responses to unit impulses at samples 0 … d − 1. A filter started from zero
    state differs from one started in its true, unknown state by such a response, so projecting these columns
    out estimates the initial state (MATLAB's InitialCondition = 'estimate') instead of discarding a settling
    time."""
    cols = []
    for den in denominators:
        for j in range(len(den) - 1):
            impulse = np.zeros(n)
            impulse[j] = 1.0
            cols.append(lfilter([1.0], den, impulse))
    return np.column_stack(cols) if cols else np.zeros((n, 0))

