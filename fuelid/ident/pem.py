"""Prediction-error identification of MISO polynomial models (Ljung, *System Identification*, ch. 7, 10).

    θ̂_N = argmin_θ V(θ),   V(θ) = ½ Σ_{t=n0}^{N−1} ε(t, θ)²,   ε = D/C · (A ỹ − Σ_i B_i/F_i ũ_i)

(paper eqs. 6–7), minimised by Levenberg–Marquardt with the analytic gradient ψ(t, θ) = −∂ε(t, θ)/∂θ.

Gradient by filtering (no finite differences). With x_i = B_i/F_i ũ_i and w = A ỹ − Σ_i x_i (so ε = D/C w):

    ∂ε/∂a_k     =  D/C ỹ(t−k)                  ψ_a,k   = −D/C ỹ(t−k)
    ∂ε/∂b_i,l   = −D/(C F_i) ũ_i(t−l)          ψ_b,i,l =  D/(C F_i) ũ_i(t−l)     (l = nk_i … nk_i+nb_i−1)
    ∂ε/∂f_i,k   =  D/(C F_i) x_i(t−k)          ψ_f,i,k = −D/(C F_i) x_i(t−k)
    ∂ε/∂c_k     = −D/C² w(t−k) = −ε(t−k)/C     ψ_c,k   =  1/C ε(t−k)
    ∂ε/∂d_k     =  1/C w(t−k)                  ψ_d,k   = −1/C w(t−k)

Each family is one filtered signal, shifted: for m inputs at most 2m + 3 lfilter calls give the whole N × d Jacobian
Ψ = [ψ(n0) … ψ(N−1)]ᵀ.

Levenberg–Marquardt step, by QR (never the normal equations, whose ΨᵀΨ squares Ψ's condition number). The
triangular factor of [Ψ ε] over the used samples, accumulated over chunks of samples (TSQR, `_triangular_factor`),

    [Ψ ε] = Q [[R, z], [0, ρ]],   z = Qᵀε,

is scaled by S = diag of the column norms of Ψ and decomposed, R S⁻¹ = U diag(σ) Vᵀ (a d × d problem, d = 41 for
the paper's orders), c = Uᵀ z. The damped step

    δ(μ) = S⁻¹ V diag(σ / (σ² + μ σ_max²)) c

is the least-squares solution of [Ψ S⁻¹; √μ σ_max I] S δ ≈ [ε; 0], i.e. it minimises ‖ε − Ψ δ‖² + μ σ_max² ‖S δ‖²;
one factorisation per iteration serves every μ tried, μ adapts (`levenberg_marquardt`) and never falls below
DAMPING_FLOOR. Memory: Ψ is never formed whole (`_Lagged`: its at most 2m + 3 filtered signals, lagged chunk by
chunk), so the LM needs O(m N) for the signals and O(QR_CHUNK · d) for the factorisation. The LM loop is written
here, its linear algebra LAPACK's through scipy and numpy (dgeqrt, scipy.linalg.lstsq; numpy.linalg.svd):
scipy.optimize.least_squares (MINPACK's LM, or its trust-region methods) takes the whole N × d Jacobian as one
array and has no place for the stability projection of each trial step.

Stopping (`levenberg_marquardt`, reasons in `STOP_REASONS`, recorded in model.info). The Gauss–Newton
decrement Δ = ½ ‖c‖² is the fall of V a full Gauss–Newton step promises; since λ̂ = 2V/(N − d)
and P = λ̂ (ΨᵀΨ)⁻¹, 2Δ/λ̂ = δᵀ P⁻¹ δ is the squared length of that step in standard errors. Converged when
Δ ≤ tol · V (MATLAB's SearchOptions.Tolerance, there in %, default 0.01 % — ours is stricter), or when V
fell by ≤ ftol · λ̂/2 (a thousandth of what one standard error is worth, far above rounding) in each of the last 3
iterations and the step left is within one standard error, or when no damped step lowers V and the step left is
within one standard error. Near pole–zero cancellations (e.g. the paper's orders on data from its own model: Gw's
printed F has a lightly damped pair at |z| = 0.9988 all but cancelled by zeros of B) make V flat along the
direction that moves the pair together: the fit is fine then, the cancelling pair's coefficients are not
determined; pem says so in its warning. Not converged: the iteration limit; no damping lowering V while the step
left is larger than one standard error; and a root of F_i, C or D held at the stability bound (below).

Continuing a search: Levenberg–Marquardt's state after an iteration is θ, V, μ, the count of flat iterations and
whether the last step was cut back (`LMResult`); a search stopped at its iteration limit continues from it
(`levenberg_marquardt(after=...)`, `pem_with_search`) through the same iterates as one search run to the larger
limit in the same process — so a short warm-started refit need not be run again as the start of a longer one
(ident.identify.FitMemo).

Stability: after every step the roots of F_i, C and D outside the unit circle are reflected to 1/z̄ and all
roots are clipped to radius ≤ RHO_MAX = 0.9999 (`stabilize`); the reflected candidate must still lower V to be
accepted. F_i and C stable keeps the predictor stable; D stable makes H = C/D a stationary noise model (the
spectrum |C/D|² changes only by a constant factor under reflection). A root on the bound that the step would push
outward is held there: the step is searched in the directions that keep its radius to first order (an active set
of the constraints |z| ≤ RHO_MAX, `_free_directions`: δ = N w with N an orthonormal basis of the null space of
the held roots' radius gradients ∂|z|/∂θ, and the LM step for w from the QR of [Ψ N ε]), so the search goes on to
the least V with those roots on the bound; clipping the full step instead would stall it where its path happened
to meet the bound, a point the last bits of the data move. A fit that ends with a root at the bound
(`at_stability_bound`) is a minimum under that constraint, not of V: it is reported not converged, stop_reason
"stability_bound", with the polynomials named in its warning.

Initial conditions: every filter starts from zero state (the data are deviations from the operating point)
and the first n0 = max(na, nk_i + nb_i − 1, nf_i, nc, nd) samples are left out of V and Ψ.

Several records (segments, e.g. a log split by gaps): V sums over the segments, each filtered from its own
zero state with its own first n0 samples left out, V(θ) = ½ Σ_s Σ_{t=n0}^{N_s−1} ε_s(t, θ)²; Ψ likewise, the
initialisation's least squares and filters too. Joining them end to end instead would make each junction a
transient the model does not have (the predictor carries the previous record's state).

Covariance: P = λ̂ (ΨᵀΨ)⁻¹ at θ̂ with λ̂ = 2V/(N_used − d) (Ljung eq. 9.18), d = dim θ, N_used = Σ_s (N_s − n0).

Initialisation (`initial_estimate`): the input part by least squares (ARX, when there is no F or there is an
A), or for OE/BJ by a high-order ARX (A_h, B_h,i), whose per-input responses B_h,i/A_h u_i are reduced to
B_i/F_i by Steiglitz–McBride iterations and refined by the same LM as an OE model on data prefiltered by
A_h ≈ H⁻¹ (prefiltering by the inverse noise model makes the OE criterion the BJ one with H fixed, Ljung
sec. 14.4) — by LM for OE_LM_ITERATIONS iterations, then, when it is still going, by variable projection; then
the noise model C/D by Hannan–Rissanen (a long AR, then least squares) on the residual
w = A y − Σ B_i/F_i u_i, refined by LM as an ARMA model. Hand-written because SciPy has no PEM; the linear
algebra is numpy/scipy.linalg (the least squares by QR: `_least_squares`) and all filtering scipy.signal.lfilter's
(ident.filters: compiled, the same numbers to rounding).

Variable projection (Golub & Pereyra 1973; Kaufman's Jacobian, Ruhe & Wedin 1980) for the OE start's flat valleys.
The Steiglitz–McBride start reduces each input's response on its own, so where inputs are collinear (the engine
map term's) their split is arbitrary, and the LM then moves b and f together along a valley it crawls through
(hundreds of iterations). Given the F_i the OE error is linear in every b:

    ε = y − Φ(f) b,   Φ(f) = [v_i(t − l)],  v_i = u_i/F_i  (v_i = u_i for an FIR input),

so b̂(f) = argmin_b ‖y − Φ(f) b‖² and the search runs over f alone on the projected residual
r(f) = P⊥(f) y, P⊥ = I − Φ Φ⁺. Kaufman's Jacobian keeps the term of ∂r/∂f that acts through Φ b̂:

    ψ_f,i,k = −∂r/∂f_i,k ≈ −P⊥ x_i(t − k)/F_i,   x_i = B̂_i/F_i u_i,

and LM steps on f as above. Neither Φ nor P⊥ is formed: P⊥ M = Q₂ R₂₂ for the QR factorisation
[Φ M] = Q [[R₁₁, R₁₂], [0, R₂₂]], so one chunked QR of [Φ −G y] (G the lagged x_i/F_i) gives the triangular factor
of [Ψ r] the LM step needs, and one of [Φ y] gives b̂ and ‖r‖: O(m N) memory, as the LM's. A well-started LM is
left alone (the same iterates); one still going after OE_LM_ITERATIONS continues by projection from where it is,
whose first b̂ already lowers V (the least-squares b at the same F). Written here because scipy.optimize.least_squares has no variable projection and no per-input
filters; its LM would need Φ⁺'s derivative by finite differences.
"""
from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from scipy.linalg import lapack, lstsq

from fuelid.blas import one_blas_thread
from fuelid.errors import InputError
from fuelid.ident.filters import lfilter, lfilter_each
from fuelid.ident.polymodel import (Polynomials, PolyModel, Structure, as_inputs, from_theta, input_responses,
                                    parameter_names, polynomials)

RHO_MAX = 0.9999  # largest root radius allowed in F_i, C, D
HIGH_ORDER_ARX = 30  # order of the ARX model behind the OE/BJ initialisation
# Iteration limit of the LM fits inside the initialisation (OE, ARMA), apart from pem's max_iter: a start cut
# off at a limit leaves the BJ fit in a valley it crawls along (shipped 20-min DPF trip: OE stopped at 100
# iterations → BJ V = 565.6, not converged after 100; OE run to its minimum in 161 → BJ converged in 7 at 558.7).
INIT_MAX_ITER = 500
# The OE start's LM iterations before variable projection takes over (module docstring): well-started fits
# converge within them and are left as they were; a fit still going is in a valley where b and f move together.
OE_LM_ITERATIONS = 30
PROJECTION_WINDOW = 10  # variable projection stops when V fell by less than λ̂/2 over this many iterations
# `stabilize` skips np.roots when the Schur–Cohn test puts every root within rho · STABLE_MARGIN: a margin far
# above np.roots' error (≲ 1e-8 relative for a double root), so that the roots it would compute are ≤ rho too.
STABLE_MARGIN = 1.0 - 1e-4


def _roots_within(p, r: float) -> bool:
    """Whether every root of the monic polynomial p lies strictly inside |z| < r, by the Schur–Cohn (step-down)
    test on q_k = p_k / r^k: every reflection coefficient of q of magnitude below 1 (Jury, Åström)."""
    q = [float(c) / r**k for k, c in enumerate(p)]
    for n in range(len(q) - 1, 0, -1):
        k = q[n]
        if not abs(k) < 1.0:
            return False
        q = [(q[i] - k * q[n - i]) / (1.0 - k * k) for i in range(n)]
    return True


def stabilize(p: np.ndarray, rho: float = RHO_MAX) -> np.ndarray:
    """Monic polynomial p with roots z outside the unit circle reflected to 1/z̄ and every |z| clipped to ≤ rho."""
    p = np.asarray(p, float)
    if p.size < 2 or _roots_within(p, rho * STABLE_MARGIN):
        return p
    z = np.roots(p)
    r = np.abs(z)
    if np.all(r <= rho):
        return p
    z = np.where(r > 1.0, 1.0 / np.conj(z), z)
    z = z * np.minimum(1.0, rho / np.maximum(np.abs(z), 1e-300))
    return np.real(np.poly(z))


def _restarted(fn, x: np.ndarray, starts, axis: int = 0) -> np.ndarray:
    """fn applied to each segment of x along axis (segments begin at the indices `starts`, the first 0) and the
    results joined: every filter inside fn restarts from zero state at each segment's start."""
    if len(starts) == 1:
        return fn(x)
    return np.concatenate([fn(p) for p in np.split(x, starts[1:], axis=axis)], axis=axis)


def _used(n: int, starts, n0: int):
    """The samples that enter V: all but the first n0 of each segment (a slice for one segment, else a mask)."""
    if len(starts) == 1:
        return slice(n0, None)
    keep = np.ones(n, bool)
    for a, b in zip(starts, [*starts[1:], n]):
        keep[a : min(a + n0, b)] = False
    return keep


class _Lagged(NamedTuple):
    """The N × d matrix whose columns are sig(t − l), zero before the start of t's segment, for each (sig, lags)
    block in turn (segments begin at `starts`): Ψ or a regressor matrix, held as its few signals (O(N) each) and
    made chunk by chunk of samples (`self[a:b]`), so that the whole N × d is formed only where asked for."""

    blocks: list
    n: int
    starts: tuple = (0,)

    @property
    def shape(self) -> tuple[int, int]:
        return self.n, sum(len(lags) for _, lags in self.blocks)

    def __getitem__(self, samples: slice) -> np.ndarray:
        """Rows a … b − 1 (a slice of samples, step 1) as a (b − a) × d array in Fortran order."""
        a, b, _ = samples.indices(self.n)
        out = np.empty((max(b - a, 0), self.shape[1]), order="F")
        longest = max((max(lags, default=0) for _, lags in self.blocks), default=0)
        inside = [start for start in self.starts[1:] if a - longest < start < b]  # those whose first rows are here
        c = 0
        for sig, lags in self.blocks:
            for lag in lags:
                col = out[:, c]
                lo = a - lag  # the sample of sig in the chunk's first row
                col[max(-lo, 0):] = sig[max(lo, 0) : b - lag]
                col[: max(-lo, 0)] = 0.0
                for start in inside:  # the segments' first `lag` samples
                    col[max(start - a, 0) : max(min(start + lag, b) - a, 0)] = 0.0
                c += 1
        return out


def _least_squares(phi: _Lagged, target: np.ndarray, used) -> np.ndarray:
    """θ minimising Σ_{t used} (target(t) − φ(t)ᵀθ)², φ(t)ᵀ the rows of Φ = phi (used: `_used`): `_solution` of the
    triangular factor of [Φ target] (`_triangular_factor`, chunk by chunk)."""
    return _solution(_triangular_factor(phi, target, used))


def _solution(Rbar: np.ndarray) -> np.ndarray:
    """The least-squares θ of Φ θ ≈ target from the triangular factor R̄ = [[R, z], [0, ρ]] of [Φ target]
    (`_triangular_factor`): R S⁻¹ (S the column norms) η = z by scipy.linalg.lstsq (an SVD: robust to rank
    deficiency) and θ = S⁻¹ η."""
    d = Rbar.shape[1] - 1
    scale = np.linalg.norm(Rbar[:d, :d], axis=0)
    scale[scale == 0] = 1.0
    return lstsq(Rbar[:d, :d] / scale, Rbar[:d, d], check_finite=False)[0] / scale


def _stable_theta(theta: np.ndarray, s: Structure) -> tuple[np.ndarray, Polynomials]:
    """θ with F_i, C and D stabilised (A needs no stability: it enters the predictor as an FIR filter), and its
    polynomials; θ itself when `stabilize` left every one as it was."""
    p = polynomials(theta, s)
    q = p._replace(F=[stabilize(f) for f in p.F], C=stabilize(p.C), D=stabilize(p.D))
    if all(a is b for a, b in zip([*p.F, p.C, p.D], [*q.F, q.C, q.D])):
        return theta, p
    theta = q.theta(s.nk)
    return theta, polynomials(theta, s)


class _Responses(NamedTuple):
    """The filtered signals of one θ: its polynomials m, the input responses x_i = B_i/F_i u_i, the residual
    w = A y − Σ x_i and ε = D/C w."""

    m: object
    x: list
    w: np.ndarray
    eps: np.ndarray


def _filter_each(starts):
    """[lfilter(b, a, x) for b, a, x in jobs] for 1-D signals, every filter restarted at each segment start, by
    lfilter_each (filters of one length run two at a time); by 1/1 (A, C, D of an OE model) x itself."""
    def each(jobs):
        jobs = list(jobs)
        out = [x if len(b) == len(a) == 1 and b[0] == a[0] == 1.0 else None for b, a, x in jobs]
        todo = [k for k, y in enumerate(out) if y is None]
        for k, y in zip(todo, lfilter_each([jobs[k] for k in todo], starts)):
            out[k] = y
        return out
    return each


def _responses(m: Polynomials, u: np.ndarray, y: np.ndarray, starts=(0,)) -> _Responses:
    """x_i, w and ε of the polynomials m of θ (`_Responses`) for deviation data, every filter restarting at the
    segment `starts`."""
    each = _filter_each(starts)
    x = each((b, f, u[:, i]) for i, (b, f) in enumerate(zip(m.B, m.F)))
    w = each([(m.A, [1.0], y)])[0] - sum(x, np.zeros(y.size))
    return _Responses(m, x, w, each([(m.D, m.C, w)])[0])


def _jacobian(r: _Responses, s: Structure, u: np.ndarray, y: np.ndarray, starts=(0,)) -> _Lagged:
    """Ψ (N × d), ψ = −∂ε/∂θ (module doc), from the filtered signals r of θ: its at most 2m + 3 filtered signals,
    lagged (`_Lagged`, made chunk by chunk where used); the signals of empty regressor blocks are not filtered."""
    m = r.m
    dens = [np.convolve(m.C, f) for f in m.F]
    with_f = [i for i in range(s.n_inputs) if s.nf[i]]  # an FIR input (F_i = 1) has no x_i/F_i block
    jobs = [(m.D, m.C, y)] if s.na else []
    jobs += [(m.D, den, u[:, i]) for i, den in enumerate(dens)] + [(m.D, dens[i], r.x[i]) for i in with_f]
    jobs += ([([1.0], m.C, r.eps)] if s.nc else []) + ([([1.0], m.C, r.w)] if s.nd else [])
    filtered = iter(_filter_each(starts)(jobs))
    blocks = [(-next(filtered), range(1, s.na + 1))] if s.na else []
    blocks += [(next(filtered), range(s.nk[i], s.nk[i] + s.nb[i])) for i in range(s.n_inputs)]
    blocks += [(-next(filtered), range(1, s.nf[i] + 1)) for i in with_f]
    blocks += [(next(filtered), range(1, s.nc + 1))] if s.nc else []
    blocks += [(-next(filtered), range(1, s.nd + 1))] if s.nd else []
    return _Lagged(blocks, y.size, tuple(starts))


def prediction_errors(theta, s: Structure, u: np.ndarray, y: np.ndarray, jacobian: bool = False, starts=(0,)):
    """ε(t, θ) for deviation data (u: N × m, y: N); with jacobian=True also Ψ (N × d), ψ = −∂ε/∂θ (module doc).

    starts: the indices where segments begin (the first 0); every filter restarts from zero state there."""
    r = _responses(polynomials(theta, s), u, y, starts)
    return (r.eps, _jacobian(r, s, u, y, starts)[:]) if jacobian else r.eps


def _loss(eps: np.ndarray, used) -> float:
    """V = ½ Σ_{t used} ε(t)² (∞ when not finite)."""
    v = 0.5 * float(eps[used] @ eps[used])
    return v if np.isfinite(v) else np.inf


QR_CHUNK = 2048  # samples of [Ψ ε] per QR update: the working array is (d + 1 + QR_CHUNK) × (d + 1)
# The LM's damping never falls below this (relative to σ_max², `_damped_step`). The step's component along a
# direction of singular value σ_k carries a relative rounding error of about u σ_max / σ_k (u = 1.1e-16, QR of Ψ);
# the floor bounds that amplification at u / √DAMPING_FLOOR ≈ 4e-9, so the step is a smooth function of the data
# whatever the conditioning of Ψ, and leaves every direction with σ_k above 3e-8 σ_max undamped.
DAMPING_FLOOR = 1e-15


def _triangular_factor(psi, eps: np.ndarray, used) -> np.ndarray:
    """The (d + 1) × (d + 1) upper triangular R̄ of the QR factorisation of [Ψ ε] over the used samples,
    accumulated over chunks of QR_CHUNK samples (TSQR): R̄ ← R(qr([R̄; Ψ_k ε_k])). R̄ = [[R, z], [0, ρ]] with
    Ψ = Q R, z = Qᵀε and ρ = ‖ε − Q z‖. psi: an N × d array or `_Lagged` (made chunk by chunk here); the extra
    memory is O(QR_CHUNK · d), whatever N.

    Chunked here because scipy.linalg.qr and numpy.linalg.qr take the whole N × (d + 1) matrix (a copy of Ψ) and
    are slower on it than on chunks that stay in cache. Each chunk is factored by LAPACK's dgeqrt (blocked Householder
    QR in compact-WY form; its block size `_qr_block`): 2–3 times faster than dgeqrf, scipy.linalg.qr's, on these
    arrays of a few dozen to a few hundred columns (benchmarks/bench_qr.py)."""
    n, d = psi.shape
    keep = np.zeros(n + 2, bool)
    keep[1:-1][used] = True
    edges = np.flatnonzero(np.diff(keep))  # the used samples: runs [edges[2j], edges[2j + 1])
    R = np.zeros((0, d + 1))
    work = np.empty((d + 1 + QR_CHUNK, d + 1), order="F")
    for a in range(0, n, QR_CHUNK):
        b = min(a + QR_CHUNK, n)
        chunk, k = psi[a:b], R.shape[0]
        work[:k] = R
        m = k
        for lo, hi in zip(np.clip(edges[0::2], a, b), np.clip(edges[1::2], a, b)):
            work[m : m + hi - lo, :d] = chunk[lo - a : hi - a]
            work[m : m + hi - lo, d] = eps[lo:hi]
            m += hi - lo
        if m == k:
            continue
        factored, _, info = lapack.dgeqrt(min(_qr_block(d + 1), m, d + 1), work[:m], overwrite_a=True)
        if info:
            raise ValueError(f"dgeqrt failed (info {info})")
        R = np.triu(factored[: d + 1])  # R in its upper triangle
    if R.shape[0] < d + 1:  # fewer used samples than d + 1
        R = np.vstack([R, np.zeros((d + 1 - R.shape[0], d + 1))])
    return R


def _qr_block(columns: int) -> int:
    """The block size nb of LAPACK's dgeqrt for an array of `columns` columns: 8 up to 64 (a Jacobian of a few dozen
    parameters), 32 above (the initialisation's wide ARX regressors), the fastest of 8, 16 and 32 on each
    (benchmarks/bench_qr.py)."""
    return 8 if columns <= 64 else 32


class _Linearised(NamedTuple):
    """The LM's linear algebra at one θ (`_linearised`): S the column norms of Ψ, the SVD R S⁻¹ = U diag(σ) Vᵀ of
    the scaled triangular factor (σ descending), and c = Uᵀ z (z = Qᵀε)."""

    scale: np.ndarray
    V: np.ndarray
    sigma: np.ndarray
    c: np.ndarray


def _linearised(psi, eps: np.ndarray, used) -> _Linearised:
    """`_Linearised` of Ψ, ε over the used samples: from the QR of [Ψ ε] (`_triangular_factor`, then
    `_linearised_factor`), never ΨᵀΨ (whose condition number is the square of Ψ's)."""
    return _linearised_factor(_triangular_factor(psi, eps, used))


def _linearised_factor(Rbar: np.ndarray) -> _Linearised:
    """`_Linearised` from the triangular factor R̄ = [[R, z], [0, ρ]] of [Ψ ε]."""
    d = Rbar.shape[1] - 1
    R, z = Rbar[:d, :d], Rbar[:d, d]
    scale = np.linalg.norm(R, axis=0)
    scale[scale == 0] = 1.0
    U, sigma, Vt = np.linalg.svd(R / scale)
    return _Linearised(scale, Vt.T, sigma, U.T @ z)


FLAT_ITERATIONS = 3  # consecutive iterations with a negligible fall of V before V counts as flat


class LMResult(NamedTuple):
    """What `levenberg_marquardt` found: θ̂, V(θ̂), iterations, whether it converged and why (`STOP_REASONS`),
    V after each iteration (history[0] at the start), Ψ and ε at θ̂ (None once dropped: `searched`), and the
    search's state when it stopped — the damping μ, the count of flat iterations, whether the last step was cut
    back — from which `levenberg_marquardt(after=...)` continues a search stopped at its iteration limit."""

    theta: np.ndarray
    V: float
    iterations: int
    converged: bool
    reason: str
    history: list
    psi: _Lagged | None
    eps: np.ndarray | None
    mu: float
    flat: int
    cut: bool

    def searched(self) -> LMResult:
        """This result without Ψ and ε (d × N numbers): what continuing the search needs, to keep."""
        return self._replace(psi=None, eps=None)


STOP_REASONS = {
    "expected_improvement": "the Gauss-Newton step promises to lower V by less than tol * V",
    "flat_loss": "V fell by less than ftol * lambda/2 in each of the last iterations and the remaining "
                 "Gauss-Newton step is within one standard error",
    "stability_bound": f"a root of F_i, C or D is held at the stability bound |z| = {RHO_MAX}: V is at its least "
                       "with the root there, not at a minimum of V",
    "no_descent": "no damping lowers V",
    "max_iterations": "the iteration limit was reached",
}


def _damping_trials(mu: float) -> tuple[float, ...]:
    """The LM damping factors tried in turn from the last accepted one, mu (≥ DAMPING_FLOOR): one tenth of it when
    that is not below the floor, it, then ten times more each time (a step search stops at the first that lowers
    V from mu on)."""
    lower = (mu / 10.0,) if mu / 10.0 >= DAMPING_FLOOR else ()
    return (*lower, mu, *(mu * 10.0**k for k in range(1, 12)))


def _decrement(lin: _Linearised) -> float:
    """The Gauss–Newton decrement Δ = ½ Σ_k c_k² (σ_k below 1e-7 σ_max counting as 1e-7 σ_max, which scales their
    terms down): the fall of V a full Gauss–Newton step promises, ½‖Qᵀε‖² when Ψ has full rank."""
    sigma = lin.sigma
    return 0.5 * float(np.sum(lin.c**2 * (sigma / np.maximum(sigma, 1e-7 * sigma[0]))**2))


def _damped_step(lin: _Linearised, mu: float) -> np.ndarray:
    """δ(μ) = S⁻¹ V diag(σ/(σ² + μ σ_max²)) c (module docstring), which minimises ‖ε − Ψ δ‖² + μ σ_max² ‖S δ‖²,
    for μ ≥ DAMPING_FLOOR."""
    sigma = lin.sigma
    return lin.V @ (sigma * lin.c / (sigma**2 + max(mu, DAMPING_FLOOR) * sigma[0]**2)) / lin.scale


def _descent(mu: float, V: float, trial: Callable[[float], NamedTuple]) -> tuple[float, NamedTuple] | None:
    """One LM step search from the loss V: trial(μ), the search's candidate at the step δ(μ) with its loss as the
    field V, for the damping factors `_damping_trials(mu)` in turn, up to the first from mu on that lowers the loss;
    (μ, trial(μ)) of the lowest loss, or None when no damping lowers it."""
    best = None
    for damping in _damping_trials(mu):
        candidate = trial(damping)
        if candidate.V < (V if best is None else best[1].V):
            best = (damping, candidate)
        if damping >= mu and best is not None:
            break
    return best


HELD = 1e-6  # a root within this fraction of RHO_MAX from the bound is held there (np.roots' error is far below)


def _held_gradients(theta: np.ndarray, s: Structure) -> np.ndarray:
    """k × d: for each root z of F_i, C or D on the stability bound (|z| ≥ RHO_MAX (1 − HELD); one per real root
    or conjugate pair) the gradient of its radius, ∂|z|/∂θ, scaled to unit length. For the monic
    p(z) = zⁿ + p_1 zⁿ⁻¹ + … + p_n with p(z) = 0, ∂z/∂p_j = −zⁿ⁻ʲ / p′(z) and ∂|z| = Re(z̄ ∂z) / |z|."""
    p = polynomials(theta, s)
    offset, rows = s.na + sum(s.nb), []
    for poly in [*p.F, p.C, p.D]:
        n = poly.size - 1
        z = np.zeros(0) if not n or _roots_within(poly, RHO_MAX * (1.0 - HELD)) else np.roots(poly)
        for r in z[(np.abs(z) >= RHO_MAX * (1.0 - HELD)) & (z.imag >= 0.0)]:
            dz = -r ** np.arange(n - 1, -1, -1) / np.polyval(np.polyder(poly), r)
            g = np.zeros(s.n_params)
            g[offset : offset + n] = np.real(np.conj(r) * dz) / abs(r)
            norm = np.linalg.norm(g)
            if np.isfinite(norm) and norm > 0.0:
                rows.append(g / norm)
        offset += n
    return np.array(rows).reshape(-1, s.n_params)


def _free_directions(theta: np.ndarray, s: Structure, lin: _Linearised, mu: float) -> np.ndarray | None:
    """An orthonormal basis N (d × (d − k)) of the steps that keep, to first order, the radius of each root held at
    the stability bound that the damped step δ(μ) would push outward (gᵀδ > 0, `_held_gradients`): the active
    set of the constraints |z| ≤ RHO_MAX. None when no root is held there against the step.

    Searching δ = N w instead of clipping the full step to the bound each time (`stabilize`) moves the other
    parameters to the minimum of V with those roots on the bound, so the search ends at a constrained minimum that
    the last bits of the data do not move, rather than where the clipped steps stopped making progress."""
    G = _held_gradients(theta, s)
    if not G.size:
        return None
    G = G[G @ _damped_step(lin, mu) > 0.0]
    if not G.size:
        return None
    _, sv, Wt = np.linalg.svd(G)
    rank = int(np.sum(sv > 1e-8 * sv[0]))
    return Wt[rank:].T


class _Trial(NamedTuple):
    """One damped step of `levenberg_marquardt`: V at the stabilised θ, whether the stability projection cut the
    step back, and the filtered signals of θ."""

    V: float
    theta: np.ndarray
    cut: bool
    r: _Responses


def _split(x: np.ndarray, sizes) -> list[np.ndarray]:
    """x cut into consecutive pieces of the given sizes."""
    return np.split(x, np.cumsum(sizes)[:-1])


def levenberg_marquardt(theta, s: Structure, u, y, *, starts=(0,), max_iter: int = 100, tol: float = 1e-7,
                        ftol: float = 1e-3, after: LMResult | None = None) -> LMResult:
    """Minimise V(θ) from θ (module docstring); starts: segment starts (filters restart there, the first n0
    samples of each are left out of V). after: a search on the same data stopped at its iteration limit, which
    this one continues from its θ and state (theta is then ignored) up to max_iter iterations in all: the same
    iterates, in one process, as one search run to max_iter.

    Each iteration tries the damping μ (relative to σ_max², module docstring) and μ/10 (not below DAMPING_FLOOR)
    and keeps the better; when neither lowers V, μ grows tenfold until one does. Roots held at the stability bound
    against the step restrict it to the directions that keep them there (`_free_directions`), and Δ is then the
    fall promised in those directions. Stops (reason in
    `STOP_REASONS`): converged when the Gauss–Newton decrement Δ = ½ ‖c‖² is ≤ tol · V (MATLAB's
    SearchOptions.Tolerance, there in %); or when V fell by ≤ ftol · λ̂/2 in each of the last FLAT_ITERATIONS
    iterations and Δ ≤ λ̂/2 — the remaining step δ has δᵀ P⁻¹ δ = 2Δ/λ̂ ≤ 1, i.e. it is within one standard
    error; or when no damping lowers V and Δ ≤ λ̂/2. Not converged: V flat or no damping lowering it while the
    steps were cut back by the stability projection and more than one standard error is left ("stability_bound":
    a root pressed against |z| = RHO_MAX), no damping lowering V otherwise, or max_iter iterations. ftol is in
    units of λ̂/2 = V/(N − d), what moving one standard error is worth (likelihood ratio 1): a fall of 1e-3 of
    that per iteration is statistically nothing whatever N, and above 10³ times the rounding of V (about 1e-12
    of V) for N up to 10⁶.
    """
    used = _used(y.size, starts, s.n_start)
    u = np.asfortranarray(u)  # each input is filtered on its own in every trial: its column contiguous, not copied
    if after is None:
        theta, m = _stable_theta(np.asarray(theta, float), s)
    else:  # the accepted iterate was stabilised when it was taken: its polynomials are the ones it was scored by
        if after.reason != "max_iterations" or after.iterations > max_iter:
            raise ValueError(f"a search that stopped for {after.reason} after {after.iterations} iterations is not "
                             f"continued to {max_iter}")
        theta, m = after.theta, polynomials(after.theta, s)
    r = _responses(m, u, y, starts)
    eps, psi = r.eps, _jacobian(r, s, u, y, starts)
    dof = max(eps[used].size - s.n_params, 1)
    if after is None:
        V, mu, flat, cut, first = _loss(eps, used), 1e-4, 0, False, 1
        history = [V]
    else:
        V, mu, flat, cut, first = after.V, after.mu, after.flat, after.cut, after.iterations + 1
        history = list(after.history)

    def stopped(iterations: int, converged: bool, reason: str) -> LMResult:
        return LMResult(theta, V, iterations, converged, reason, history, psi, eps, mu, flat, cut)

    for it in range(first, max_iter + 1):
        Rbar = _triangular_factor(psi, eps, used)
        lin = _linearised_factor(Rbar)
        basis = _free_directions(theta, s, lin, mu)
        if basis is not None:  # roots held at the bound: the step is searched where they stay there
            lin = _linearised_factor(np.linalg.qr(np.column_stack([Rbar[:-1, :-1] @ basis, Rbar[:-1, -1]]),
                                                  mode="r"))
        decrement = _decrement(lin)
        small_step = decrement <= V / dof  # 2Δ/λ̂ ≤ 1 with λ̂ = 2V/dof
        if decrement <= tol * V:
            return stopped(it - 1, True, "expected_improvement")
        if flat >= FLAT_ITERATIONS and (small_step or (cut and basis is None)):
            return stopped(it - 1, small_step, "flat_loss" if small_step else "stability_bound")
        cuts = []

        def trial(damping: float) -> _Trial:
            step = _damped_step(lin, damping)
            raw = theta + (step if basis is None else basis @ step)
            stable, m = _stable_theta(raw, s)
            cuts.append(stable is not raw and not np.array_equal(stable, raw))
            r = _responses(m, u, y, starts)
            return _Trial(_loss(r.eps, used), stable, cuts[-1], r)

        best = _descent(mu, V, trial)
        if best is None:  # no damping lowers V: a (numerical) minimum if nothing is left to gain
            if not small_step and basis is None and (cut or all(cuts)):
                return stopped(it - 1, False, "stability_bound")
            return stopped(it - 1, small_step, "no_descent")
        damping, taken = best
        flat = flat + 1 if V - taken.V <= ftol * V / dof else 0
        V, theta, mu, cut, r = taken.V, taken.theta, max(damping, DAMPING_FLOOR), taken.cut, taken.r
        history.append(V)
        eps, psi = r.eps, _jacobian(r, s, u, y, starts)  # the accepted trial's signals, not filtered again
    return stopped(max_iter, False, "max_iterations")


def _arx_ls(u, y, na: int, nb, nk, starts=(0,)):
    """Least-squares ARX: A y = Σ B_i u_i + e; returns (A, [B_i]) with nk leading zeros in B_i."""
    n0 = max([na] + [k + b - 1 for k, b in zip(nk, nb)])
    blocks = [(-y, range(1, na + 1))] + [(u[:, i], range(nk[i], nk[i] + nb[i])) for i in range(u.shape[1])]
    th = _least_squares(_Lagged(blocks, y.size, tuple(starts)), y, _used(y.size, starts, n0))
    parts = _split(th, [na, *nb])
    return np.r_[1.0, parts[0]], [np.r_[np.zeros(k), b] for b, k in zip(parts[1:], nk)]


def _steiglitz_mcbride(u_i, x_i, nb: int, nf: int, nk: int, starts=(0,), iterations: int = 15):
    """B/F fitted to a noise-free input-output pair x = B/F u by Steiglitz–McBride: repeated least squares of
    F x_f = B u_f on the prefiltered u_f = u/F, x_f = x/F (Ljung sec. 10.4)."""
    F = np.ones(1)
    for _ in range(iterations):
        uf, xf = _filter_each(starts)([([1.0], F, u_i), ([1.0], F, x_i)])
        A, (B,) = _arx_ls(uf[:, None], xf, nf, (nb,), (nk,), starts)
        F_new = stabilize(A)
        done = F_new.size == F.size and np.allclose(F_new, F, rtol=0, atol=1e-10)
        F = F_new
        if done:
            break
    return B, F


def _hannan_rissanen(w, nc: int, nd: int, starts=(0,)):
    """ARMA D w = C e by Hannan–Rissanen: a long AR(L) gives ê, then w(t) − ê(t) is regressed on −w(t−k)
    (k ≤ nd) and ê(t−k) (k ≤ nc). Returns stabilised (C, D)."""
    L = max(40, 4 * (nc + nd))
    ar, _ = _arx_ls(np.zeros((w.size, 0)), w, L, (), (), starts)
    e_hat = _restarted(lambda p: lfilter(ar, [1.0], p), w, starts)
    warm = np.ones(w.size, bool)
    warm[_used(w.size, starts, L)] = False
    e_hat[warm] = 0.0
    phi = _Lagged([(-w, range(1, nd + 1)), (e_hat, range(1, nc + 1))], w.size, tuple(starts))
    th = _least_squares(phi, w - e_hat, _used(w.size, starts, L + max(nc, nd)))
    return stabilize(np.r_[1.0, th[nd:]]), stabilize(np.r_[1.0, th[:nd]])


def _noise_model(w, nc: int, nd: int, *, starts=(0,), max_iter: int, tol: float):
    """(C, D, LM iterations) of the ARMA model D w = C e: Hannan–Rissanen, refined by the same LM (a PEM with
    no inputs)."""
    if nc == 0 and nd == 0:
        return np.ones(1), np.ones(1), 0
    C, D = _hannan_rissanen(w, nc, nd, starts)
    arma = Structure(nb=(), nf=(), nk=(), nc=nc, nd=nd)
    fit = levenberg_marquardt(np.r_[C[1:], D[1:]], arma, np.zeros((w.size, 0)), w, starts=starts,
                              max_iter=max_iter, tol=tol)
    return np.r_[1.0, fit.theta[:nc]], np.r_[1.0, fit.theta[nc:]], fit.iterations


class _Projection(NamedTuple):
    """Variable projection at one set of F_i (`_output_error_by_projection`): the regressor signals v_i (u_i/F_i
    for a B/F input, u_i for an FIR one), the triangular factor R̄ = [[R, z], [0, ρ]] of [Φ(f) y] over the used
    samples (Φ(f) = [v_i(t − l)], `_triangular_factor`: chunk by chunk) and V = ½ ρ², ρ = ‖P⊥(f) y‖."""

    F: dict
    v: dict
    Rbar: np.ndarray
    V: float


def _output_error_by_projection(theta, s: Structure, u, y, *, starts=(0,), max_iter: int, tol: float,
                                ftol: float = 1e-3) -> tuple[np.ndarray, int]:
    """(θ, iterations) of the OE model y = Σ B_i/F_i u_i + e (s has no A, C, D) by variable projection from the F_i
    of θ (module docstring): LM over f alone, b = b̂(f) by least squares. Stops when the Gauss–Newton decrement is
    ≤ tol · V, when V was flat (as `levenberg_marquardt`), when it fell by less than λ̂/2 over the last
    PROJECTION_WINDOW iterations (what one standard error is worth: a valley too flat to matter), when no damping
    lowers V, or after max_iter iterations.

    Never forms Φ or P⊥: with the QR factorisation [Φ M] = Q [[R₁₁, R₁₂], [0, R₂₂]] of Φ beside any columns M,
    P⊥ M = Q₂ R₂₂, so R₂₂ is the triangular factor of P⊥ M. The LM's [Ψ r] = P⊥ [−G y] (G the lagged x_i/F_i,
    Kaufman's Jacobian) is therefore factored by one chunked QR of [Φ −G y] (`_triangular_factor`): memory
    O(m N) for the filtered signals whatever the number of columns."""
    used = _used(y.size, starts, s.n_start)
    n_used = y[used].size
    each = _filter_each(starts)
    rational = [i for i in range(s.n_inputs) if s.nf[i]]
    d = sum(s.nb)  # the columns of Φ: every input's b

    def lagged(v: dict, extra=()) -> _Lagged:
        return _Lagged([(v[i], range(s.nk[i], s.nk[i] + s.nb[i])) for i in range(s.n_inputs)] + list(extra),
                       y.size, tuple(starts))

    def projection(F: dict) -> _Projection:
        v = dict(enumerate(u.T)) | dict(zip(rational, each([([1.0], F[i], u[:, i]) for i in rational])))
        Rbar = _triangular_factor(lagged(v), y, used)
        return _Projection(F, v, Rbar, 0.5 * float(Rbar[d, d]) ** 2)

    def b_hat(p: _Projection) -> list:
        return _split(_solution(p.Rbar), s.nb)

    def linearised(p: _Projection) -> _Linearised:
        b = b_hat(p)
        x = each([(np.r_[np.zeros(s.nk[i]), b[i]], p.F[i], u[:, i]) for i in rational])
        xf = each([([1.0], p.F[i], xi) for i, xi in zip(rational, x)])
        G = [(-xi, range(1, s.nf[i] + 1)) for i, xi in zip(rational, xf)]
        return _linearised_factor(_triangular_factor(lagged(p.v, G), y, used)[d:, d:])

    def with_f(f: np.ndarray) -> dict:
        return {i: stabilize(np.r_[1.0, fi]) for i, fi in zip(rational, _split(f, [s.nf[i] for i in rational]))}

    f = np.asarray(theta, float)[sum(s.nb):]
    p = projection(with_f(f))
    mu, flat, dof, history = 1e-4, 0, max(n_used - s.n_params, 1), [p.V]
    iterations = 0
    while iterations < max_iter:
        lin = linearised(p)
        decrement = _decrement(lin)
        window = history[-1 - PROJECTION_WINDOW] - p.V if len(history) > PROJECTION_WINDOW else np.inf
        if decrement <= tol * p.V or (flat >= FLAT_ITERATIONS and decrement <= p.V / dof) or window < p.V / dof:
            break
        f = np.concatenate([p.F[i][1:] for i in rational])
        best = _descent(mu, p.V, lambda damping: projection(with_f(f + _damped_step(lin, damping))))
        if best is None:
            break
        damping, taken = best
        flat = flat + 1 if p.V - taken.V <= ftol * p.V / dof else 0
        p, mu = taken, max(damping, DAMPING_FLOOR)
        history.append(p.V)
        iterations += 1
    return np.concatenate(b_hat(p) + [p.F[i][1:] for i in rational]), iterations


def _input_model(u, y, s: Structure, *, starts=(0,), max_iter: int, tol: float):
    """(A, [B_i], [F_i], OE LM iterations, variable projection iterations) for `initial_estimate`: least-squares
    ARX when there is no F_i or there is an A; for OE/BJ a high-order ARX, its per-input responses reduced to
    B_i/F_i by Steiglitz–McBride, then the OE model B_i/F_i refined by LM (consistent whatever the noise colour),
    by variable projection once the LM has run OE_LM_ITERATIONS without converging (module docstring)."""
    m = u.shape[1]
    if not any(s.nf) or s.na > 0:
        A, B = _arx_ls(u, y, s.na, s.nb, s.nk, starts)
        return A, B, [np.r_[1.0, np.zeros(nf)] for nf in s.nf], 0, 0
    n = max(HIGH_ORDER_ARX, *(k + b + f for k, b, f in zip(s.nk, s.nb, s.nf)))
    Ah, Bh = _arx_ls(u, y, n, (n + 1,) * m, (0,) * m, starts)
    Ahs = stabilize(Ah)
    fits = [_steiglitz_mcbride(u[:, i], _restarted(lambda p: lfilter(Bh[i], Ahs, p), u[:, i], starts),
                               s.nb[i], s.nf[i], s.nk[i], starts) for i in range(m)]
    oe = Structure(nb=s.nb, nf=s.nf, nk=s.nk)
    theta = np.concatenate([b[k:] for (b, _), k in zip(fits, s.nk)] + [f[1:] for _, f in fits])
    uf = _restarted(lambda p: lfilter(Ah, [1.0], p, axis=0), u, starts)
    yf = _restarted(lambda p: lfilter(Ah, [1.0], p), y, starts)
    fit = levenberg_marquardt(theta, oe, uf, yf, starts=starts, max_iter=min(OE_LM_ITERATIONS, max_iter), tol=tol)
    theta, projected = fit.theta, 0
    if fit.reason == "max_iterations" and fit.iterations < max_iter:
        theta, projected = _output_error_by_projection(fit.theta, oe, uf, yf, starts=starts,
                                                       max_iter=max_iter - fit.iterations, tol=tol)
    g = from_theta(theta, oe, 1.0)
    return g.A, g.B, g.F, fit.iterations, projected


def _drop_warmup(x: np.ndarray, starts, n0: int):
    """x without the first n0 samples of each segment, and the starts of the segments that remain."""
    lengths = np.diff([*starts, len(x)]) - n0
    return x[_used(len(x), starts, n0)], tuple(int(a) for a in np.cumsum(np.r_[0, lengths[lengths > 0]])[:-1])


class InitialEstimate(NamedTuple):
    """θ₀ from `initial_estimate` and the iterations its OE fit (LM, then variable projection) and ARMA fit took
    (0: no such fit)."""

    theta: np.ndarray
    oe_iterations: int
    arma_iterations: int
    projected_iterations: int = 0


def initial_estimate(u, y, s: Structure, *, starts=(0,), max_iter: int = INIT_MAX_ITER,
                     tol: float = 1e-7) -> InitialEstimate:
    """θ₀ for `pem` from deviation data (segments beginning at `starts`): the input part (`_input_model`), then
    the noise model C/D fitted to the residual w = A y − Σ B_i/F_i u_i (`_noise_model`)."""
    A, B, F, oe_iterations, projected_iterations = _input_model(u, y, s, starts=starts, max_iter=max_iter, tol=tol)
    g = PolyModel(A=A, B=B, F=F, C=[1.0], D=[1.0], Ts=1.0, nk=s.nk)
    w = (_restarted(lambda p: lfilter(A, [1.0], p), y, starts)
         - _restarted(lambda p: input_responses(g, p), u, starts).sum(axis=1))
    w, w_starts = _drop_warmup(w, starts, s.n_start)
    C, D, arma_iterations = _noise_model(w, s.nc, s.nd, starts=w_starts, max_iter=max_iter, tol=tol)
    theta = np.concatenate([A[1:]] + [b[k:] for b, k in zip(B, s.nk)] + [f[1:] for f in F] + [C[1:], D[1:]])
    return InitialEstimate(theta, oe_iterations, arma_iterations, projected_iterations)


def at_stability_bound(model: PolyModel) -> list[str]:
    """Which of F_i, C, D have a root on the stability bound |z| = RHO_MAX (within HELD: where `stabilize` clips
    them and the search holds them, `_free_directions`)."""
    polys = [(f"F{i + 1} ({name})", f) for i, (name, f) in enumerate(zip(model.input_names, model.F))]
    polys += [("C", model.C), ("D", model.D)]
    return [label for label, p in polys if p.size > 1 and np.abs(np.roots(p)).max() >= RHO_MAX * (1.0 - HELD)]


def cancellations(model: PolyModel, tol: float = 0.01) -> list[str]:
    """Near pole–zero cancellations: a zero of B_i within tol of a root of F_i, or of C within tol of D."""
    pairs = [(f"B{i + 1}/F{i + 1} ({name})", b[k:], f) for i, (name, b, f, k) in
             enumerate(zip(model.input_names, model.B, model.F, model.nk))]
    pairs.append(("C/D (noise model)", model.C, model.D))
    found = []
    for label, num, den in pairs:
        zeros, poles = np.roots(num), np.roots(den)
        if zeros.size and poles.size:
            dist = np.abs(zeros[:, None] - poles[None, :])
            i, j = np.unravel_index(np.argmin(dist), dist.shape)
            if dist[i, j] < tol:
                found.append(f"near pole-zero cancellation in {label}: zero {zeros[i]:.4f} vs pole {poles[j]:.4f} "
                             f"(distance {dist[i, j]:.2g}); the orders may be higher than the data support")
    return found


def _segment_starts(segments, n: int, n0: int) -> tuple[np.ndarray | None, tuple[int, ...]]:
    """(indices of the samples in `segments`, or None for all; starts of the segments once joined)."""
    if segments is None:
        return None, (0,)
    spans = sorted((s.start, s.stop) if isinstance(s, slice) else (int(s[0]), int(s[1])) for s in segments)
    if not spans:
        raise ValueError("segments is empty")
    for (a, b), (c, _) in zip(spans, [*spans[1:], (n, n)]):
        if not 0 <= a < b <= c:
            raise ValueError(f"segment ({a}, {b}) is empty, outside 0..{n} or overlaps the next one")
    spans = [(a, b) for a, b in spans if b - a > n0]  # nothing of a segment this short enters V
    if not spans:
        raise InputError(f"every segment is at most {n0} samples long (the initial-condition samples)")
    idx = np.concatenate([np.arange(a, b) for a, b in spans])
    return idx, tuple(int(v) for v in np.cumsum([0] + [b - a for a, b in spans])[:-1])


def pem(u, y, structure: Structure, Ts: float, *, segments=None, init: PolyModel | None = None, u0=None,
        y0: float = 0.0, max_iter: int = 100, tol: float = 1e-7, ftol: float = 1e-3,
        cancel_tol: float = 0.01) -> PolyModel:
    """Prediction-error estimate of a MISO polynomial model: `pem_with_search`'s model (its docstring)."""
    return pem_with_search(u, y, structure, Ts, segments=segments, init=init, u0=u0, y0=y0, max_iter=max_iter,
                           tol=tol, ftol=ftol, cancel_tol=cancel_tol)[0]


def pem_with_search(u, y, structure: Structure, Ts: float, *, segments=None, init: PolyModel | None = None,
                    u0=None, y0: float = 0.0, max_iter: int = 100, tol: float = 1e-7, ftol: float = 1e-3,
                    cancel_tol: float = 0.01, after: LMResult | None = None) -> tuple[PolyModel, LMResult]:
    """Prediction-error estimate of a MISO polynomial model (module docstring for the method).

    u: N × m inputs (or N for one input), y: N output, both sampled every Ts [s]; the model is identified on
    the deviations u − u0, y − y0 (default 0) and returned with that operating point. segments: list of
    (start, stop) index ranges (or slices) into u, y of separate records (e.g. split by gaps in the logs);
    every filter restarts from zero state in each, the first n0 samples of each are left out of V, and the
    initialisation and the covariance use them all; None = one record. init: a PolyModel of the
    same structure to start from instead of `initial_estimate`. max_iter, tol, ftol: the stopping rules of
    `levenberg_marquardt` for the final fit (the initialisation's own fits stop at INIT_MAX_ITER in all). Warns
    (and records in info['warnings']) on a near pole–zero cancellation closer than cancel_tol, when LM stops
    without converging, and when it converged on a flat loss.
    info records converged, stop_reason (a key of STOP_REASONS), iterations, loss_history (V per iteration)
    and gauss_newton_step_se, the length √(δᵀP⁻¹δ) of the Gauss–Newton step still left at θ̂ [standard errors];
    initialisation_iterations ({output_error, arma, output_error_projected}: the LM iterations of the
    initialisation's fits and the variable projection's after the OE one, 0 with init)
    and initialisation_time_s [s], the wall time up to the final fit.
    Names and units of the signals are set afterwards with dataclasses.replace.
    after: the search (`LMResult.searched`) of an earlier call with the same data, init and a lower max_iter that
    stopped at that limit, continued here (`levenberg_marquardt`): the model one call to max_iter gives.
    Returns the model and its search (`LMResult.searched`).
    """
    t_start = time.perf_counter()
    s = structure
    u = as_inputs(u, s.n_inputs)
    y = np.asarray(y, float)
    if y.ndim != 1 or y.size != u.shape[0]:
        raise ValueError(f"y must be 1-D with as many samples as u ({u.shape[0]}), got shape {y.shape}")
    u0 = np.zeros(s.n_inputs) if u0 is None else np.broadcast_to(np.asarray(u0, float), (s.n_inputs,))
    idx, starts = _segment_starts(segments, y.size, s.n_start)
    du, dy = (u - u0, y - y0) if idx is None else (u[idx] - u0, y[idx] - y0)
    n_used = dy.size - len(starts) * s.n_start
    if n_used <= 2 * s.n_params:
        raise InputError(f"{dy.size} samples in {len(starts)} segment(s) are too few for {s.n_params} parameters")
    if init is not None and init.structure != s:
        raise ValueError(f"init has structure {init.structure}, expected {s}")
    if after is not None and init is None:
        raise ValueError("a search is continued from the start it began at: init is needed with after")
    with one_blas_thread():
        start = (InitialEstimate(init.theta, 0, 0) if init is not None else
                 initial_estimate(du, dy, s, starts=starts, tol=tol))
        t_init = time.perf_counter()
        fit = levenberg_marquardt(start.theta, s, du, dy, starts=starts, max_iter=max_iter, tol=tol, ftol=ftol,
                                  after=after)
        lin = _linearised(fit.psi, fit.eps, _used(dy.size, starts, s.n_start))

    V = fit.V
    lam = 2.0 * V / (n_used - s.n_params)
    sigma = lin.sigma  # P = λ̂ S⁻¹ V diag(1/σ²) Vᵀ S⁻¹, directions with σ ≤ 1e-7 σ_max left out (pseudo-inverse)
    inv_ell = np.where(sigma > sigma[0] * 1e-7, 1.0 / np.maximum(sigma, 1e-300)**2, 0.0)
    P = lam * ((lin.V * inv_ell) @ lin.V.T) / np.outer(lin.scale, lin.scale)
    step_se = float(np.sqrt(2.0 * _decrement(lin) / lam))  # √(2Δ/λ̂)

    model = from_theta(fit.theta, s, Ts, u0=tuple(u0), y0=y0, covariance=P)
    msgs = cancellations(model, cancel_tol)
    bound = at_stability_bound(model)
    # a root held at the bound is where the projection stopped the search, not a minimum of V: never converged
    converged, reason = (False, "stability_bound") if bound else (fit.converged, fit.reason)
    where = f"; {', '.join(bound)} at the stability bound |z| = {RHO_MAX}" if bound else ""
    if not converged:
        fall = (fit.history[-min(4, len(fit.history))] - V) / V
        msgs.append(f"PEM did not converge: stopped after {fit.iterations} iterations ({STOP_REASONS[reason]}); "
                    f"the last iterations lowered V by {fall:.1e} of V, the Gauss-Newton step left is "
                    f"{step_se:.2g} standard errors{where}")
    elif reason != "expected_improvement" and msgs:
        msgs.append(f"PEM converged on a flat loss after {fit.iterations} iterations ({STOP_REASONS[reason]}): "
                    "near-cancelling pole-zero pairs leave directions of the parameters that the data do not "
                    "determine; the fit is fine, those coefficients are not (see their standard errors)")
    for msg in msgs:
        warnings.warn(msg, stacklevel=2)
    model.info = {
        "method": "prediction error minimisation, Levenberg-Marquardt, analytic gradient",
        "initialisation": "given model" if init is not None else "high-order ARX, Steiglitz-McBride, prefiltered OE; Hannan-Rissanen + ARMA",
        "initial_conditions": f"zero initial state in each of {len(starts)} segment(s), first {s.n_start} "
                              "samples of each excluded from V",
        "segments": len(starts),
        "iterations": fit.iterations,
        "initialisation_iterations": {"output_error": start.oe_iterations, "arma": start.arma_iterations,
                                      "output_error_projected": start.projected_iterations},
        "initialisation_time_s": t_init - t_start,
        "converged": converged,
        "stop_reason": reason,
        "stopping": {"max_iter": max_iter, "tol": tol, "ftol": ftol},
        "loss_history": fit.history,
        "gauss_newton_step_se": step_se,
        "loss_V": V,
        "noise_variance": lam,
        "n_samples": int(dy.size),
        "condition_number": float(sigma[0] / sigma[-1]) if sigma[-1] > 0 else None,  # None: singular
        "parameter_names": parameter_names(s),
        "wall_time_s": time.perf_counter() - t_start,
        "warnings": msgs,
    }
    return model, fit.searched()
