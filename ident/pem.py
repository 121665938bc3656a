"""Prediction-error identification of MISO polynomial models (Ljung, *System Identification*, ch. 7, 10).

    θ̂_N = argmin_θ V(θ),   V(θ) = ½ Σ_{t=n0}^{N−1} ε(t, θ)²,   ε = D/C · (A ỹ − Σ_i B_i/F_i ũ_i)

(paper eqs. 6–7), minimised by Levenberg–Marquardt with the analytic gradient ψ(t, θ) = −∂ε(t, θ)/∂θ.

Gradient by filtering (no finite differences). With x_i = B_i/F_i ũ_i and w = A ỹ − Σ_i x_i (so ε = D/C w):

    ∂ε/∂a_k     =  D/C ỹ(t−k)                  ψ_a,k   = −D/C ỹ(t−k)
    ∂ε/∂b_i,l   = −D/(C F_i) ũ_i(t−l)          ψ_b,i,l =  D/(C F_i) ũ_i(t−l)     (l = nk_i … nk_i+nb_i−1)
    ∂ε/∂f_i,k   =  D/(C F_i) x_i(t−k)          ψ_f,i,k = −D/(C F_i) x_i(t−k)
    ∂ε/∂c_k     = −D/C² w(t−k) = −ε(t−k)/C     ψ_c,k   =  1/C ε(t−k)
    ∂ε/∂d_k     =  1/C w(t−k)                  ψ_d,k   = −1/C w(t−k)

Each family is one filtered signal, shifted: for m inputs 2m + 3 lfilter calls give the whole N × d Jacobian
Ψ = [ψ(n0) … ψ(N−1)]ᵀ.

Levenberg–Marquardt step: with S = diag of the column norms of Ψ and the eigendecomposition
S⁻¹ΨᵀΨS⁻¹ = Q diag(ℓ) Qᵀ (a d × d problem, d = 41 for the paper's orders), g = Qᵀ S⁻¹ Ψᵀ ε and
δ(μ) = S⁻¹ Q diag(1/(ℓ + μ ℓ_max)) g, which minimises ‖ε − Ψ δ‖² + μ ℓ_max ‖S δ‖². One decomposition per
iteration serves every μ tried; μ adapts (see `levenberg_marquardt`). Stopping: the Gauss–Newton decrement
½ gᵀ diag(1/ℓ) g (the fall of V a full Gauss–Newton step promises) below tol · V, or no μ lowering V.
(Normal equations rather than a QR/SVD of the N × d Ψ: 10× cheaper here, and accurate enough for the step,
which is always checked by evaluating V.)

Stability: after every step the roots of F_i, C and D outside the unit circle are reflected to 1/z̄ and all
roots are clipped to radius ≤ 0.9999 (`stabilize`); the reflected candidate must still lower V to be
accepted. F_i and C stable keeps the predictor stable; D stable makes H = C/D a stationary noise model (the
spectrum |C/D|² changes only by a constant factor under reflection).

Initial conditions: every filter starts from zero state (the data are deviations from the operating point)
and the first n0 = max(na, nk_i + nb_i − 1, nf_i, nc, nd) samples are left out of V and Ψ.

Covariance: P = λ̂ (ΨᵀΨ)⁻¹ at θ̂ with λ̂ = 2V/(N − n0 − d) (Ljung eq. 9.18), d = dim θ.

Initialisation (`initial_estimate`): the input part by least squares (ARX, when there is no F or there is an
A), or for OE/BJ by a high-order ARX (A_h, B_h,i), whose per-input responses B_h,i/A_h u_i are reduced to
B_i/F_i by Steiglitz–McBride iterations and refined by the same LM as an OE model on data prefiltered by
A_h ≈ H⁻¹ (prefiltering by the inverse noise model makes the OE criterion the BJ one with H fixed, Ljung
sec. 14.4); then the noise model C/D by Hannan–Rissanen (a long AR, then least squares) on the residual
w = A y − Σ B_i/F_i u_i, refined by LM as an ARMA model. Hand-written because SciPy has no PEM; the linear
algebra is numpy/scipy.linalg and all filtering scipy.signal.lfilter.
"""
from __future__ import annotations

import contextlib
import time
import warnings

import numpy as np
from scipy.linalg import eigh, lstsq
from scipy.signal import lfilter

from ident.polymodel import PolyModel, Structure, as_inputs, from_theta, input_responses, parameter_names

try:  # BLAS threads only cost time on N × d problems this narrow (8× slower on 2 cores, measured)
    from threadpoolctl import threadpool_limits
except ImportError:  # pragma: no cover - threadpoolctl missing: run with the BLAS defaults
    threadpool_limits = None

RHO_MAX = 0.9999  # largest root radius allowed in F_i, C, D
HIGH_ORDER_ARX = 30  # order of the ARX model behind the OE/BJ initialisation


def stabilize(p: np.ndarray, rho: float = RHO_MAX) -> np.ndarray:
    """Monic polynomial p with roots z outside the unit circle reflected to 1/z̄ and every |z| clipped to ≤ rho."""
    p = np.asarray(p, float)
    if p.size < 2:
        return p
    z = np.roots(p)
    r = np.abs(z)
    if np.all(r <= rho):
        return p
    z = np.where(r > 1.0, 1.0 / np.conj(z), z)
    z = z * np.minimum(1.0, rho / np.maximum(np.abs(z), 1e-300))
    return np.real(np.poly(z))


def _regressors(blocks, n: int) -> np.ndarray:
    """The d × N matrix whose rows are sig(t − l), zero before the start, for each (sig, lags) block in turn.

    Rows, so every copy is contiguous; the N × d regressor matrix is its transpose (a view).
    """
    rows = np.empty((sum(len(lags) for _, lags in blocks), n))
    r = 0
    for sig, lags in blocks:
        for lag in lags:
            rows[r, :lag] = 0.0
            rows[r, lag:] = sig[: n - lag]
            r += 1
    return rows


def _least_squares(rows: np.ndarray, target: np.ndarray, n0: int) -> np.ndarray:
    """θ minimising Σ_{t≥n0} (target(t) − φ(t)ᵀθ)², φ(t) the columns of rows; by the normal equations with
    rows scaled to unit norm, solved by scipy.linalg.lstsq (robust to rank deficiency)."""
    R = rows[:, n0:]
    scale = np.linalg.norm(R, axis=1)
    scale[scale == 0] = 1.0
    R = R / scale[:, None]
    return lstsq(R @ R.T, R @ target[n0:], check_finite=False)[0] / scale


def _stable_theta(theta: np.ndarray, s: Structure) -> np.ndarray:
    """θ with F_i, C and D stabilised (A needs no stability: it enters the predictor as an FIR filter)."""
    m = from_theta(theta, s, 1.0)
    m.F = [stabilize(f) for f in m.F]
    m.C, m.D = stabilize(m.C), stabilize(m.D)
    return m.theta


def prediction_errors(theta, s: Structure, u: np.ndarray, y: np.ndarray, jacobian: bool = False):
    """ε(t, θ) for deviation data (u: N × m, y: N); with jacobian=True also Ψ (N × d), ψ = −∂ε/∂θ (module doc)."""
    m = from_theta(theta, s, 1.0)
    x = input_responses(m, u)
    w = lfilter(m.A, [1.0], y) - x.sum(axis=1)
    eps = lfilter(m.D, m.C, w)
    if not jacobian:
        return eps
    blocks = [(-lfilter(m.D, m.C, y), range(1, s.na + 1))]
    fx = []
    for i in range(s.n_inputs):
        filt = lfilter(m.D, np.convolve(m.C, m.F[i]), np.vstack([u[:, i], x[:, i]]))
        blocks.append((filt[0], range(s.nk[i], s.nk[i] + s.nb[i])))
        fx.append((-filt[1], range(1, s.nf[i] + 1)))
    ew = lfilter([1.0], m.C, np.vstack([eps, w]))
    blocks += fx + [(ew[0], range(1, s.nc + 1)), (-ew[1], range(1, s.nd + 1))]
    return eps, _regressors(blocks, y.size).T


def _loss(eps: np.ndarray, n0: int) -> float:
    v = 0.5 * float(eps[n0:] @ eps[n0:])
    return v if np.isfinite(v) else np.inf


def _scaled_normal_equations(psi: np.ndarray, eps: np.ndarray, n0: int):
    """(S, Q, ℓ, g): S the column norms of Ψ, Q diag(ℓ) Qᵀ = S⁻¹ΨᵀΨS⁻¹ (eigendecomposition), g = Qᵀ S⁻¹ Ψᵀ ε."""
    J, r = psi[n0:], eps[n0:]
    gram = J.T @ J
    scale = np.sqrt(np.diag(gram)).copy()
    scale[scale == 0] = 1.0
    ell, Q = eigh(gram / np.outer(scale, scale), check_finite=False)
    return scale, Q, np.maximum(ell, 0.0), Q.T @ ((J.T @ r) / scale)


def levenberg_marquardt(theta, s: Structure, u, y, *, max_iter: int = 100, tol: float = 1e-7):
    """Minimise V(θ) from θ; returns (θ̂, V, iterations, converged, Ψ at θ̂, ε at θ̂).

    Each iteration tries the damping μ (relative to the largest eigenvalue of the scaled ΨᵀΨ) and μ/10 and
    keeps the better; when neither lowers V, μ grows tenfold until one does (or μ > 1: a minimum).
    """
    n0 = s.n_start
    theta = _stable_theta(np.asarray(theta, float), s)
    eps, psi = prediction_errors(theta, s, u, y, jacobian=True)
    V, mu = _loss(eps, n0), 1e-4
    for it in range(1, max_iter + 1):
        scale, Q, ell, g = _scaled_normal_equations(psi, eps, n0)
        if 0.5 * g @ (g / np.maximum(ell, ell[-1] * 1e-14)) <= tol * V:
            return theta, V, it, True, psi, eps
        best = (V, None, mu)
        for trial in (mu / 10.0, mu, *(mu * 10.0**k for k in range(1, 12))):
            cand = _stable_theta(theta + Q @ (g / (ell + trial * ell[-1])) / scale, s)
            V_c = _loss(prediction_errors(cand, s, u, y), n0)
            if V_c < best[0]:
                best = (V_c, cand, trial)
            if trial >= mu and best[1] is not None:
                break
        if best[1] is None:  # no damping lowers V: a (numerical) minimum
            return theta, V, it, True, psi, eps
        V, theta, mu = best[0], best[1], max(best[2], 1e-15)
        eps, psi = prediction_errors(theta, s, u, y, jacobian=True)
    return theta, V, max_iter, False, psi, eps


def _arx_ls(u, y, na: int, nb, nk):
    """Least-squares ARX: A y = Σ B_i u_i + e; returns (A, [B_i]) with nk leading zeros in B_i."""
    n0 = max([na] + [k + b - 1 for k, b in zip(nk, nb)])
    blocks = [(-y, range(1, na + 1))] + [(u[:, i], range(nk[i], nk[i] + nb[i])) for i in range(u.shape[1])]
    th = _least_squares(_regressors(blocks, y.size), y, n0)
    parts = np.split(th, np.cumsum([na, *nb])[:-1])
    return np.r_[1.0, parts[0]], [np.r_[np.zeros(k), b] for b, k in zip(parts[1:], nk)]


def _steiglitz_mcbride(u_i, x_i, nb: int, nf: int, nk: int, iterations: int = 15):
    """B/F fitted to a noise-free input-output pair x = B/F u by Steiglitz–McBride: repeated least squares of
    F x_f = B u_f on the prefiltered u_f = u/F, x_f = x/F (Ljung sec. 10.4)."""
    F = np.ones(1)
    for _ in range(iterations):
        uf, xf = lfilter([1.0], F, u_i), lfilter([1.0], F, x_i)
        A, (B,) = _arx_ls(uf[:, None], xf, nf, (nb,), (nk,))
        F_new = stabilize(A)
        done = F_new.size == F.size and np.allclose(F_new, F, rtol=0, atol=1e-10)
        F = F_new
        if done:
            break
    return B, F


def _hannan_rissanen(w, nc: int, nd: int):
    """ARMA D w = C e by Hannan–Rissanen: a long AR(L) gives ê, then w(t) − ê(t) is regressed on −w(t−k)
    (k ≤ nd) and ê(t−k) (k ≤ nc). Returns stabilised (C, D)."""
    L = max(40, 4 * (nc + nd))
    ar, _ = _arx_ls(np.zeros((w.size, 0)), w, L, (), ())
    e_hat = lfilter(ar, [1.0], w)
    e_hat[:L] = 0.0
    rows = _regressors([(-w, range(1, nd + 1)), (e_hat, range(1, nc + 1))], w.size)
    th = _least_squares(rows, w - e_hat, L + max(nc, nd))
    return stabilize(np.r_[1.0, th[nd:]]), stabilize(np.r_[1.0, th[:nd]])


def _noise_model(w, nc: int, nd: int, *, max_iter: int, tol: float):
    """C/D of the ARMA model D w = C e: Hannan–Rissanen, refined by the same LM (a PEM with no inputs)."""
    if nc == 0 and nd == 0:
        return np.ones(1), np.ones(1)
    C, D = _hannan_rissanen(w, nc, nd)
    arma = Structure(nb=(), nf=(), nk=(), nc=nc, nd=nd)
    theta = levenberg_marquardt(np.r_[C[1:], D[1:]], arma, np.zeros((w.size, 0)), w, max_iter=max_iter, tol=tol)[0]
    return np.r_[1.0, theta[:nc]], np.r_[1.0, theta[nc:]]


def _input_model(u, y, s: Structure, *, max_iter: int, tol: float):
    """(A, [B_i], [F_i]) for `initial_estimate`: least-squares ARX when there is no F_i or there is an A;
    for OE/BJ a high-order ARX, its per-input responses reduced to B_i/F_i by Steiglitz–McBride, then the
    OE model B_i/F_i refined by LM (consistent whatever the noise colour)."""
    m = u.shape[1]
    if not any(s.nf) or s.na > 0:
        A, B = _arx_ls(u, y, s.na, s.nb, s.nk)
        return A, B, [np.r_[1.0, np.zeros(nf)] for nf in s.nf]
    n = max(HIGH_ORDER_ARX, *(k + b + f for k, b, f in zip(s.nk, s.nb, s.nf)))
    Ah, Bh = _arx_ls(u, y, n, (n + 1,) * m, (0,) * m)
    fits = [_steiglitz_mcbride(u[:, i], lfilter(Bh[i], stabilize(Ah), u[:, i]), s.nb[i], s.nf[i], s.nk[i])
            for i in range(m)]
    oe = Structure(nb=s.nb, nf=s.nf, nk=s.nk)
    theta = np.concatenate([b[k:] for (b, _), k in zip(fits, s.nk)] + [f[1:] for _, f in fits])
    uf, yf = lfilter(Ah, [1.0], u, axis=0), lfilter(Ah, [1.0], y)
    g = from_theta(levenberg_marquardt(theta, oe, uf, yf, max_iter=max_iter, tol=tol)[0], oe, 1.0)
    return g.A, g.B, g.F


def initial_estimate(u, y, s: Structure, *, max_iter: int = 100, tol: float = 1e-7) -> np.ndarray:
    """θ₀ for `pem` from deviation data: the input part (`_input_model`), then the noise model C/D fitted to
    the residual w = A y − Σ B_i/F_i u_i (`_noise_model`)."""
    A, B, F = _input_model(u, y, s, max_iter=max_iter, tol=tol)
    g = PolyModel(A=A, B=B, F=F, C=[1.0], D=[1.0], Ts=1.0, nk=s.nk)
    w = lfilter(A, [1.0], y) - input_responses(g, u).sum(axis=1)
    C, D = _noise_model(w[s.n_start :], s.nc, s.nd, max_iter=max_iter, tol=tol)
    return np.concatenate([A[1:]] + [b[k:] for b, k in zip(B, s.nk)] + [f[1:] for f in F] + [C[1:], D[1:]])


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


def pem(u, y, structure: Structure, Ts: float, *, init: PolyModel | None = None, u0=None, y0: float = 0.0,
        max_iter: int = 100, tol: float = 1e-7, cancel_tol: float = 0.01) -> PolyModel:
    """Prediction-error estimate of a MISO polynomial model (module docstring for the method).

    u: N × m inputs (or N for one input), y: N output, both sampled every Ts [s]; the model is identified on
    the deviations u − u0, y − y0 (default 0) and returned with that operating point. init: a PolyModel of the
    same structure to start from instead of `initial_estimate`. max_iter: LM iterations; tol: stop when a
    Gauss–Newton step would lower V by less than tol · V. Warns (and records in info['warnings']) on a near
    pole–zero cancellation closer than cancel_tol, and when LM stops without converging.
    Names and units of the signals are set afterwards with dataclasses.replace.
    """
    t_start = time.perf_counter()
    s = structure
    u = as_inputs(u, s.n_inputs)
    y = np.asarray(y, float)
    if y.ndim != 1 or y.size != u.shape[0]:
        raise ValueError(f"y must be 1-D with as many samples as u ({u.shape[0]}), got shape {y.shape}")
    u0 = np.zeros(s.n_inputs) if u0 is None else np.broadcast_to(np.asarray(u0, float), (s.n_inputs,))
    n_used = y.size - s.n_start
    if n_used <= 2 * s.n_params:
        raise ValueError(f"{y.size} samples are too few for {s.n_params} parameters")
    du, dy = u - u0, y - y0
    if init is not None and init.structure != s:
        raise ValueError(f"init has structure {init.structure}, expected {s}")
    with threadpool_limits(1, "blas") if threadpool_limits else contextlib.nullcontext():
        theta0 = init.theta if init is not None else initial_estimate(du, dy, s, max_iter=max_iter, tol=tol)
        theta, V, iterations, converged, psi, eps = levenberg_marquardt(theta0, s, du, dy, max_iter=max_iter, tol=tol)
        scale, Q, ell, _ = _scaled_normal_equations(psi, eps, s.n_start)

    lam = 2.0 * V / (n_used - s.n_params)
    inv_ell = np.where(ell > ell[-1] * 1e-14, 1.0 / np.maximum(ell, 1e-300), 0.0)
    P = lam * ((Q * inv_ell) @ Q.T) / np.outer(scale, scale)

    model = from_theta(theta, s, Ts, u0=tuple(u0), y0=y0, covariance=P)
    msgs = cancellations(model, cancel_tol)
    if not converged:
        msgs.append(f"PEM stopped after {iterations} iterations without meeting tol={tol}")
    for msg in msgs:
        warnings.warn(msg, stacklevel=2)
    model.info = {
        "method": "prediction error minimisation, Levenberg-Marquardt, analytic gradient",
        "initialisation": "given model" if init is not None else "high-order ARX, Steiglitz-McBride, prefiltered OE; Hannan-Rissanen + ARMA",
        "initial_conditions": f"zero initial state, first {s.n_start} samples excluded from V",
        "iterations": iterations,
        "converged": converged,
        "loss_V": V,
        "noise_variance": lam,
        "n_samples": int(y.size),
        "condition_number": float(np.sqrt(ell[-1] / ell[0])) if ell[0] > 0 else None,  # None: singular
        "parameter_names": parameter_names(s),
        "wall_time_s": time.perf_counter() - t_start,
        "warnings": msgs,
    }
    return model
