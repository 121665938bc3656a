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

import contextlib
import functools
from dataclasses import dataclass

import numpy as np
from scipy.linalg import qr, solve_toeplitz, svd
from scipy.signal import lfilter
from scipy.stats import chi2

try:  # BLAS threads only cost time on N × k problems this narrow (as in ident.pem)
    from threadpoolctl import ThreadpoolController
except ImportError:  # pragma: no cover - threadpoolctl missing: run with the BLAS defaults
    ThreadpoolController = None

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


def newey_west(g: np.ndarray, lags: int) -> np.ndarray:
    """Long-run covariance Σ_{|l|≤L} (1 − |l|/(L+1)) Γ_l of the rows of g (N × k), Γ_l = Σ_t g_t g_{t−l}ᵀ."""
    omega = g.T @ g
    for lag in range(1, lags + 1):
        gamma = g[lag:].T @ g[:-lag]
        omega += (1.0 - lag / (lags + 1.0)) * (gamma + gamma.T)
    return omega


def nuisance_basis(Z: np.ndarray) -> np.ndarray:
    """An orthonormal basis Q (N × p) of the nuisance columns Z, so that M_Z x = x − Q Qᵀ x."""
    return qr(Z, mode="economic", check_finite=False)[0]


def score_test(eps, X, Q=None, hac_lags: int | None = None, rank_tol: float = 1e-4) -> ScoreTest:
    """Score (LM) test that ε (N) does not depend on the columns of X (N × k) beyond the nuisance columns with
    orthonormal basis Q (N × p, `nuisance_basis`; None: only a mean): LM = sᵀ Ω̂⁻¹ s ~ χ²(k_eff), module
    docstring. Columns of X whose part orthogonal to Q has less than rank_tol of their norm are not testable
    (k_eff counts the rest); k_eff = 0 gives LM = 0, p = 1."""
    eps = np.asarray(eps, float)
    X = np.asarray(X, float).reshape(eps.size, -1)
    if Q is not None and Q.size:
        Xt, et = X - Q @ (Q.T @ X), eps - Q @ (Q.T @ eps)
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
    L = int(4 * (eps.size / 100.0) ** (2 / 9)) if hac_lags is None else hac_lags
    s = g.sum(axis=0)
    lm = float(s @ np.linalg.solve(newey_west(g, L), s))
    return ScoreTest(lm, k, float(chi2.sf(lm, k)), float(chi2.logsf(lm, k)), coef)


def ar_whitener(v: np.ndarray, order: int) -> np.ndarray:
    """a(q) = 1 − Σ_{j=1..p} φ_j q⁻ʲ of the AR(p) model of v fitted by Yule–Walker (biased autocovariances by
    FFT, Levinson solve), so that a(q) v is approximately white; always stable."""
    v = np.asarray(v, float) - np.mean(v)
    n = v.size
    spec = np.fft.rfft(v, 2 * n)
    acov = np.fft.irfft(spec * np.conj(spec))[: order + 1] / n
    if acov[0] <= 0:
        return np.ones(1)
    return np.r_[1.0, -solve_toeplitz(acov[:order], acov[1:order + 1], check_finite=False)]


def level_test(r: np.ndarray, X: np.ndarray, lens, QG: np.ndarray, order: int = AR_ORDER,
               rank_tol: float = 1e-4) -> tuple[ScoreTest, float]:
    """The simulation-error test (module docstring, 2): r (N) the simulation errors with the basis QG of the
    simulation gradient already projected out, X (N × k) the candidate's columns, lens the lengths of the
    segments r is stacked from (each filtered from rest, its first `order` samples dropped). Returns the test
    and the fraction ‖v‖/‖r‖ of the simulation error left after the candidate's least-squares fit.

    In the whitened domain the statistic is the Wald form W = ‖P_X a r‖² / σ̂², σ̂² the variance of a(q) v
    (the whitened noise under the alternative): a level shift whitens to a spike, and the score form's robust
    variance, built from errors that still contain the effect, would let that one sample cancel its own
    evidence."""
    Xt = X - QG @ (QG.T @ X)
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
    return ScoreTest(wald, k, float(chi2.sf(wald, k)), float(chi2.logsf(wald, k)), beta), left


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


@functools.lru_cache(maxsize=1)
def _blas_controller():
    # found once: threadpoolctl scans the process's loaded libraries each time it is built (tens of ms)
    return ThreadpoolController()


def one_blas_thread():
    """A context in which BLAS runs on one thread (none when threadpoolctl is missing)."""
    return _blas_controller().limit(limits=1, user_api="blas") if ThreadpoolController else contextlib.nullcontext()
