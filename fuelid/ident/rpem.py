"""Recursive prediction-error identification (RPEM) of the MISO Box–Jenkins model.

Model (ident.polymodel, na = 0), on deviations ũ = u − u0, ỹ = y − y0 from the operating point:

    ỹ(t) = Σ_i B_i(q)/F_i(q) ũ_i(t) + C(q)/D(q) e(t),        θ in the order of polymodel.parameter_names:
    θ = [b_1,…, b_m, f_1,…, f_m, c_1…c_nc, d_1…d_nd]

Per sample t, with the current estimate θ(t−1) (Ljung & Söderström, *Theory and Practice of Recursive
Identification*, 1983, §3.7; Ljung, *System Identification*, 1999, §11.4 and eq. 11.66):

    w_i(t) = B_i/F_i ũ_i(t)    :  w_i(t) = Σ_l b_i,l ũ_i(t−nk_i−l) − Σ_k f_i,k w_i(t−k)
    v(t)   = ỹ(t) − Σ_i w_i(t)                                   (the noise, if θ were true)
    ε(t)   = D/C v(t)          :  ε(t) = v(t) + Σ_k d_k v(t−k) − Σ_k c_k ε(t−k)
    ŷ(t)   = ỹ(t) − ε(t)                                         (one-step prediction; Σ_i w_i is the simulation)
    ψ(t)   = −∂ε(t)/∂θ, the gradient families of ident.pem, each a recursive filter with the current θ:
             ψ_b,i,l = D/(C F_i) ũ_i(t−l),  ψ_f,i,k = −D/(C F_i) w_i(t−k),  ψ_c,k = 1/C ε(t−k),  ψ_d,k = −1/C v(t−k)
    K(t)   = P ψ / (λ R + ψᵀ P ψ)
    θ(t)   = θ(t−1) + K ε(t)                                     (projected: F_i and C stay stable)
    P(t)   = (P − K ψᵀ P) / λ + Q
    λ(t)   = λ0 λ(t−1) + (1 − λ0) λ∞

With Q = 0 this is the RPEM with forgetting factor λ (λ∞ = 1 and λ(0) < 1: forgetting that grows towards 1;
default λ0 = 0.9995, λ(0) = 0.99, so 1 − λ(t) = 0.01 · 0.9995ᵗ: the memory Ts/(1 − λ) grows from 30 s to
10 min after half an hour and 3 h after an hour). The textbook 0.99/0.95 remembers ~20 samples at the
start, fewer than the 41 parameters of the paper's orders, and diverged on the simulated truck logs;
λ0 = 0.999 stops forgetting after ~15 min, too early to forget the estimates made before the noise model is
released (noise_after_s): it ended at 73.9 % simulation fit on the 1.5 h identification trip then shipped
(offline PEM 91.2 %; λ0 = 0.9995: 91.0 %) and at 69 % on one of six synthetic data sets (λ0 = 0.9995: all
six within 0.2 point of the offline PEM). With λ ≡ 1 and Q > 0 it is the Kalman filter for the random-walk
parameter model of ident.kalman. R is the noise variance the weights refer to (1 when unknown); since
P⁻¹ grows by ψψᵀ/R, the parameter covariance is P Λ̂/R with Λ̂ the running mean of ε².

After the update, w_i(t), v(t), ε(t) and the filtered signals are recomputed with θ(t) (a-posteriori values,
L&S §3.7) and kept as the past values of the next sample's recursions (past filtered values are never
recomputed: the standard RPEM approximation). The gradient filter D/(C F_i) runs in direct form with the
product C·F_i formed every sample.

Projection (stability of the predictor and gradient filters: F_i and C, whose roots are their poles): every
candidate θ(t) is tested by the Schur–Cohn step-down recursion (reflection coefficients |r_k| < 1 of the
polynomial with its roots scaled by 1/radius; O(n²), ~0.1 µs for n = 11, so it runs on every update, no
eigenvalues). An unstable candidate is retried with the step K ε halved, up to 8 times; then the update is
rejected (θ(t) = θ(t−1)) and only P is updated (Ljung 1999, §11.7). D is not constrained: it enters the
predictor as a numerator.

Covariance bound: when trace(P) exceeds trace_max (default 10 trace(P0)) P is scaled down to it, so P cannot
wind up when the data stop exciting the model under forgetting.

Gaps (NaN input/output or valid = False): no update. An input missing for at most max_gap samples is held
(zero-order hold) and the recursions run on; an output missing for at most max_gap samples gives ε(t) = 0 (v
is then its own prediction). After a longer input gap the state is unknown: outputs are NaN until the input
returns, then every filter restarts in the steady state of that first sample (u held constant forever) and
`warmup` samples pass without updates. After a longer output gap the noise filters restart in the steady
state of the first v(t) back, likewise followed by a warm-up. `reset()` forces the restart (e.g. at a jump in
the time axis).

Convergence reports (per sample in `Trace`, running in `report()`): the relative parameter change
‖θ(t) − θ(t−1)‖/‖θ(t)‖, trace(P), λ(t), and running fits over an exponential window of `fit_window`
samples: the one-step prediction fit 100 (1 − ‖ε‖/‖ỹ − mean‖) and the simulation fit with v in place of ε
(restarted when the output-error phase ends: its errors from θ = 0 would dominate the window for hours).

The per-sample loop is compiled with numba (`_run`); this module imports numpy, numba and ident.polymodel (which
loads scipy.signal only on first use), so the in-cab live estimator stays light.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from fuelid.ident.polymodel import from_theta, parameter_names

RADIUS = 0.9999  # largest root radius allowed in F_i and C (ident.pem.RHO_MAX)
MAX_HALVINGS = 8  # step halvings tried before an update is rejected

# status of a sample (Trace.status)
NO_STATE, NO_UPDATE, UPDATED, SHRUNK, REJECTED = -1, 0, 1, 2, 3

# cfg: settings passed to the kernel
(C_LAM_INF, C_LAM0, C_R, C_TRACE_MAX, C_RADIUS, C_MAX_GAP, C_WARMUP, C_FIT_GAMMA, C_OE_UPDATES, C_N_INPUT,
 C_FIR_UPDATES, C_N_B) = range(12)
# st: running state
S_LAM, S_GAP_U, S_GAP_Y, S_WARM, S_SW, S_SY, S_SYY, S_SEE, S_SVV, S_T, S_UPDATES, S_SHRUNK, S_REJECTED = range(13)


@njit(cache=True)
def _stable(theta, off, n, radius, work):
    """True when every root of 1 + θ[off] z⁻¹ + … + θ[off+n−1] z⁻ⁿ lies in |z| < radius (Schur–Cohn).

    Scaling a_k → a_k/radius^k maps the roots z to z/radius; then the step-down recursion
    r = a_k,  a_j ← (a_j − r a_{k−j}) / (1 − r²)  (j = 1…k−1),  k = n…1, needs |r| < 1 at every step.
    """
    g = 1.0
    for k in range(n):
        g /= radius
        work[k + 1] = theta[off + k] * g
    for k in range(n, 0, -1):
        r = work[k]
        if not abs(r) < 1.0:
            return False
        s = 1.0 - r * r
        for j in range(1, k // 2 + 1):
            aj, akj = work[j], work[k - j]
            work[j] = (aj - r * akj) / s
            if j != k - j:
                work[k - j] = (akj - r * aj) / s
    return True


@njit(cache=True)
def _stable_all(theta, orders, nc, nd, oc, od, radius, work):
    """F_i (every input), C and D stable."""
    for i in range(orders.shape[0]):
        if not _stable(theta, orders[i, 4], orders[i, 1], radius, work):
            return False
    return _stable(theta, oc, nc, radius, work) and _stable(theta, od, nd, radius, work)


@njit(cache=True)
def _signals(theta, orders, nc, nd, oc, od, hist, cf, y, y_ok):
    """The lag-0 values of every recursion from the lag-0 inputs in hist (module docstring).

    hist rows: per input i 4i ũ_i, 4i+1 w_i, 4i+2 D/(C F_i) ũ_i, 4i+3 D/(C F_i) w_i; then v, ε, v/C, ε/C;
    column j holds lag j. Without an output sample (y_ok False) ε(t) = 0. Returns (Σ w_i, v, ε).
    """
    m = orders.shape[0]
    ysim = 0.0
    for i in range(m):
        nb, nf, nk, ob, of = orders[i, 0], orders[i, 1], orders[i, 2], orders[i, 3], orders[i, 4]
        U, W = hist[4 * i], hist[4 * i + 1]
        w = 0.0
        for l in range(nb):
            w += theta[ob + l] * U[nk + l]
        for k in range(1, nf + 1):
            w -= theta[of + k - 1] * W[k]
        W[0] = w
        ysim += w
    V, E, VF, EF = hist[4 * m], hist[4 * m + 1], hist[4 * m + 2], hist[4 * m + 3]
    known = 0.0  # Σ d_k v(t−k) − Σ c_k ε(t−k): the part of ε(t) known before y(t)
    for k in range(1, nd + 1):
        known += theta[od + k - 1] * V[k]
    for k in range(1, nc + 1):
        known -= theta[oc + k - 1] * E[k]
    if y_ok:
        v = y - ysim
        e = v + known
    else:
        v = -known
        e = 0.0
    V[0], E[0] = v, e
    vf, ef = v, e
    for k in range(1, nc + 1):
        vf -= theta[oc + k - 1] * VF[k]
        ef -= theta[oc + k - 1] * EF[k]
    VF[0], EF[0] = vf, ef
    for i in range(m):
        nf, of = orders[i, 1], orders[i, 4]
        n_cf = nc + nf  # cf = C F_i
        for j in range(n_cf + 1):
            acc = 0.0
            for k in range(max(0, j - nf), min(j, nc) + 1):
                ck = 1.0 if k == 0 else theta[oc + k - 1]
                fj = 1.0 if j == k else theta[of + j - k - 1]
                acc += ck * fj
            cf[j] = acc
        for row in range(4 * i, 4 * i + 2):
            X, XF = hist[row], hist[row + 2]
            acc = X[0]
            for k in range(1, nd + 1):
                acc += theta[od + k - 1] * X[k]
            for k in range(1, n_cf + 1):
                acc -= cf[k] * XF[k]
            XF[0] = acc
    return ysim, v, e


@njit(cache=True)
def _gradient(orders, nc, nd, oc, od, hist, psi):
    """ψ(t) = −∂ε(t)/∂θ from the filtered signals in hist (module docstring)."""
    m = orders.shape[0]
    for i in range(m):
        nb, nf, nk, ob, of = orders[i, 0], orders[i, 1], orders[i, 2], orders[i, 3], orders[i, 4]
        for l in range(nb):
            psi[ob + l] = hist[4 * i + 2, nk + l]
        for k in range(1, nf + 1):
            psi[of + k - 1] = -hist[4 * i + 3, k]
    for k in range(1, nc + 1):
        psi[oc + k - 1] = hist[4 * m + 3, k]
    for k in range(1, nd + 1):
        psi[od + k - 1] = -hist[4 * m + 2, k]


@njit(cache=True)
def _poly_at_one(theta, off, n):
    """1 + θ[off] + … + θ[off+n−1]: a monic polynomial at q = 1 (its DC gain)."""
    s = 1.0
    for k in range(n):
        s += theta[off + k]
    return s


@njit(cache=True)
def _steady_noise(theta, nc, nd, oc, od, hist, m, v):
    """Noise rows in the steady state of a constant v: ε = D(1)/C(1) v, v/C = v/C(1), ε/C = ε/C(1)."""
    C1, D1 = _poly_at_one(theta, oc, nc), _poly_at_one(theta, od, nd)
    e = D1 / C1 * v
    hist[4 * m, :] = v
    hist[4 * m + 1, :] = e
    hist[4 * m + 2, :] = v / C1
    hist[4 * m + 3, :] = e / C1


@njit(cache=True)
def _steady_inputs(theta, orders, nc, nd, oc, od, hist, u):
    """Input rows in the steady state of constant inputs u: w_i = B_i(1)/F_i(1) ũ_i, filtered × D(1)/(C(1) F_i(1))."""
    C1, D1 = _poly_at_one(theta, oc, nc), _poly_at_one(theta, od, nd)
    for i in range(orders.shape[0]):
        nb, nf, ob, of = orders[i, 0], orders[i, 1], orders[i, 3], orders[i, 4]
        B1 = _poly_at_one(theta, ob, nb) - 1.0
        F1 = _poly_at_one(theta, of, nf)
        w = B1 / F1 * u[i]
        g = D1 / (C1 * F1)
        hist[4 * i, :] = u[i]
        hist[4 * i + 1, :] = w
        hist[4 * i + 2, :] = g * u[i]
        hist[4 * i + 3, :] = g * w


@njit(cache=True)
def gain(P, psi, r, n, Ppsi, K):
    """K = P ψ / (r + ψᵀ P ψ) over the first n entries of ψ (and n × n block of P); writes Ppsi = P ψ and K,
    returns r + ψᵀ P ψ (r = λ R for RPEM, R for the Kalman filter)."""
    denom = r
    for a in range(n):
        acc = 0.0
        for b in range(n):
            acc += P[a, b] * psi[b]
        Ppsi[a] = acc
        denom += psi[a] * acc
    for a in range(n):
        K[a] = Ppsi[a] / denom
    return denom


@njit(cache=True)
def covariance_update(P, Ppsi, denom, lam, Q, n):
    """P = (P − K ψᵀ P)/λ + Q on the n × n block, with K ψᵀ P = P ψ (P ψ)ᵀ/denom so that P stays symmetric
    to the last bit (Q symmetric)."""
    for a in range(n):
        for b in range(n):
            P[a, b] = (P[a, b] - Ppsi[a] * Ppsi[b] / denom) / lam + Q[a, b]


@njit(cache=True)
def _run(u, y, valid, theta, P, Q, hist, orders, nc, nd, oc, od, cfg, st, every, snaps,
         yhat, ysim, eps, status, dtheta, trace_P):
    """Process samples u[t] (deviation inputs, N×m), y[t] (deviation output) in order; see the module docstring.

    Updates theta, P, hist, st in place; writes the per-sample outputs and, every `every` samples (counted
    over the estimator's life in st[S_T]), a copy of θ into the next row of snaps.
    """
    N, m = u.shape
    n = theta.size
    psi, Ppsi, K, trial = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    cf = np.empty(hist.shape[1] + 1)
    work = np.empty(hist.shape[1] + 1)
    H = hist.shape[1]
    max_gap, lam_inf, lam0, R = cfg[C_MAX_GAP], cfg[C_LAM_INF], cfg[C_LAM0], cfg[C_R]
    gamma = cfg[C_FIT_GAMMA]
    n_snap = 0
    for t in range(N):
        yhat[t], ysim[t], eps[t], dtheta[t] = np.nan, np.nan, np.nan, 0.0
        status[t] = NO_UPDATE
        u_ok = valid[t]
        for i in range(m):
            u_ok = u_ok and math.isfinite(u[t, i])
        y_ok = valid[t] and math.isfinite(y[t])
        if u_ok:
            if st[S_GAP_U] > max_gap:  # first sample, or back after a long gap: restart in steady state
                _steady_inputs(theta, orders, nc, nd, oc, od, hist, u[t])
                _steady_noise(theta, nc, nd, oc, od, hist, m, 0.0)
                st[S_GAP_Y] = np.inf
                st[S_WARM] = cfg[C_WARMUP]
            st[S_GAP_U] = 0.0
        else:
            st[S_GAP_U] += 1.0
        if st[S_GAP_U] > max_gap:
            status[t] = NO_STATE
        else:
            for r in range(hist.shape[0]):
                for j in range(H - 1, 0, -1):
                    hist[r, j] = hist[r, j - 1]
            for i in range(m):
                hist[4 * i, 0] = u[t, i] if u_ok else hist[4 * i, 1]
            if y_ok and st[S_GAP_Y] > max_gap:  # output back after a long gap: noise filters restart
                s_w, _, _ = _signals(theta, orders, nc, nd, oc, od, hist, cf, 0.0, False)
                _steady_noise(theta, nc, nd, oc, od, hist, m, y[t] - s_w)
                st[S_WARM] = max(st[S_WARM], cfg[C_WARMUP])
            st[S_GAP_Y] = 0.0 if y_ok else st[S_GAP_Y] + 1.0
            if st[S_GAP_Y] == max_gap + 1.0:  # the noise state is lost: prediction falls back to simulation
                _steady_noise(theta, nc, nd, oc, od, hist, m, 0.0)
            s_w, v, e = _signals(theta, orders, nc, nd, oc, od, hist, cf, y[t], y_ok)
            ysim[t], yhat[t] = s_w, s_w + v - e
            if y_ok:
                eps[t] = e
            if u_ok and y_ok and st[S_WARM] > 0:
                st[S_WARM] -= 1.0
            elif u_ok and y_ok:
                # running fits and noise variance over an exponential window, restarted when the noise model is
                # released: the output-error phase's errors from θ = 0 are orders of magnitude larger and would
                # dominate the window for hours
                if st[S_UPDATES] == cfg[C_OE_UPDATES] and cfg[C_OE_UPDATES] > 0:
                    for j in (S_SW, S_SY, S_SYY, S_SEE, S_SVV):
                        st[j] = 0.0
                st[S_SW] = gamma * st[S_SW] + 1.0
                st[S_SY] = gamma * st[S_SY] + y[t]
                st[S_SYY] = gamma * st[S_SYY] + y[t] * y[t]
                st[S_SEE] = gamma * st[S_SEE] + e * e
                st[S_SVV] = gamma * st[S_SVV] + v * v
                # K = P ψ / (λ R + ψᵀ P ψ), over the input part of θ only during the output-error phase
                _gradient(orders, nc, nd, oc, od, hist, psi)
                if st[S_UPDATES] < cfg[C_FIR_UPDATES]:
                    n_act = int(cfg[C_N_B])
                elif st[S_UPDATES] < cfg[C_OE_UPDATES]:
                    n_act = int(cfg[C_N_INPUT])
                else:
                    n_act = theta.size
                lam = st[S_LAM]
                denom = gain(P, psi, lam * R, n_act, Ppsi, K)
                if math.isfinite(denom) and denom > 0.0 and math.isfinite(e):
                    # θ = θ + μ K ε, μ = 1, ½, ¼, … until F_i, C and D are stable
                    mu = 1.0
                    accepted = False
                    for h in range(MAX_HALVINGS + 1):
                        trial[:] = theta
                        for a in range(n_act):
                            trial[a] += mu * K[a] * e
                        if _stable_all(trial, orders, nc, nd, oc, od, cfg[C_RADIUS], work):
                            accepted = True
                            status[t] = UPDATED if h == 0 else SHRUNK
                            break
                        mu *= 0.5
                    if accepted:
                        change = 0.0
                        for a in range(n_act):
                            change += (trial[a] - theta[a]) ** 2
                            theta[a] = trial[a]
                        size = np.dot(theta, theta)
                        dtheta[t] = math.sqrt(change / size) if size > 0.0 else 0.0
                        st[S_UPDATES] += 1.0
                        if status[t] == SHRUNK:
                            st[S_SHRUNK] += 1.0
                    else:
                        status[t] = REJECTED
                        st[S_REJECTED] += 1.0
                    covariance_update(P, Ppsi, denom, lam, Q, n_act)
                    tr = np.trace(P)
                    if tr > cfg[C_TRACE_MAX]:
                        P *= cfg[C_TRACE_MAX] / tr
                    st[S_LAM] = lam0 * lam + (1.0 - lam0) * lam_inf
                    _signals(theta, orders, nc, nd, oc, od, hist, cf, y[t], True)  # a-posteriori values
        trace_P[t] = np.trace(P)
        st[S_T] += 1.0
        if every > 0 and st[S_T] % every == 0:
            snaps[n_snap] = theta
            n_snap += 1


def scaled_P0(structure, u_scale, y_scale: float) -> np.ndarray:
    """Diagonal P0 from scratch in the units of θ: (y_scale/u_scale_i)² for the b_i,l of input i
    [(output unit per input unit)²], 1 for the dimensionless f, c, d; u_scale [input units] and y_scale [output
    unit] the magnitudes the inputs and the output are known to have.

    A unit-free P0 = p I is the textbook choice for normalised regressors. With inputs of hundreds of rpm and
    N·m and p = 100, the a-priori spread of the prediction ψᵀP0ψ is some 10⁸ output unit², so each early update
    fits the last few samples exactly, and one disturbed sample (a gap bridged by held inputs, a late burst of
    frames) throws θ into a wrong minimum where P has already collapsed. Scaled, ψᵀP0ψ is of the order of
    y_scale² times the squared input deviations in units of u_scale."""
    s = structure
    u_scale = np.broadcast_to(np.asarray(u_scale, float), (s.n_inputs,))
    if not (np.all(u_scale > 0) and y_scale > 0 and np.all(np.isfinite(u_scale)) and math.isfinite(y_scale)):
        raise ValueError(f"scales must be finite and > 0, got inputs {u_scale}, output {y_scale}")
    b = np.repeat((y_scale / u_scale) ** 2, s.nb)
    return np.r_[b, np.ones(s.n_params - b.size)]


def running_fits(sw, sy, syy, see, svv) -> tuple[float, float]:
    """(prediction, simulation) fit [%] 100 (1 − √(Σε²/Σ(ỹ − mean)²)), v for ε, from exponentially weighted
    sums: sw Σ1, sy Σỹ, syy Σỹ², see Σε², svv Σv²; NaN while ỹ has not varied."""
    var = syy / sw - (sy / sw) ** 2 if sw > 0 else 0.0
    if var <= 0.0:
        return math.nan, math.nan
    return (100.0 * (1.0 - math.sqrt(see / sw / var)), 100.0 * (1.0 - math.sqrt(svv / sw / var)))


@dataclass
class Trace:
    """What one `RPEM.update` call saw, per sample (N) unless stated.

    yhat ŷ(t|t−1) and ysim the simulation y0 + Σ w_i [output unit] (NaN where no state: long input gap);
    eps ε(t) [output unit] (NaN without an output sample); status −1 no state, 0 no update (gap, warm-up),
    1 updated, 2 updated with a shrunk step, 3 rejected (the step would have destabilised F_i or C);
    dtheta ‖Δθ‖/‖θ‖ [-]; trace_P trace(P); lam λ after the block; theta (k × d) θ every `every` samples and
    theta_at (k) the sample index (within this block) each was taken after.
    """
    yhat: np.ndarray
    ysim: np.ndarray
    eps: np.ndarray
    status: np.ndarray
    dtheta: np.ndarray
    trace_P: np.ndarray
    theta: np.ndarray
    theta_at: np.ndarray


class RPEM:
    """Recursive prediction-error estimator of a MISO BJ model (module docstring for the equations).

    structure   ident.polymodel.Structure (na = 0), or None to take the prior's
    Ts          sampling interval [s]; default the prior's
    prior       PolyModel to start from (θ(0), its operating point, names, units and, when it has one, its
                covariance as P0); None starts from θ = 0 (B_i = 0, F_i = C = D = 1)
    lam         constant forgetting factor λ; None: λ grows from lam_start to 1 at rate lam0
    lam_start   λ(0) when lam is None: default 0.99 from scratch, 1 from a prior (a λ below 1 would inflate
                P0, the prior's information, by Π 1/λ(t) ≈ e^10)
    lam0        growth rate of λ(t) towards lam (default 0.9995)
    P0          initial P: scalar (× I), vector (diagonal) or d × d matrix; default from a prior its covariance
                × R/Λ (Λ its noise variance), or (0.1 θ_j)² without one (10 % uncertainty); from scratch
                100 I, unit-blind: give `scaled_P0` when the inputs' and output's magnitudes are known
    R           noise variance [output unit²] the update weighs ε against; default the prior's, else 1
    Q           random-walk covariance added to P each update: scalar (× I), vector (diagonal) or d × d
                matrix; 0 for RPEM (ident.kalman sets it)
    u0, y0      operating point [input units], [output unit]; default the prior's, else 0
    trace_max   bound on trace(P) (default 10 trace(P0))
    max_gap_s   longest stretch [s] of missing input (held) or output (ε = 0) bridged without a restart
    warmup_s    time [s] without updates after a restart
    fit_window_s  window [s] of the running fits
    noise_after_s  output-error phase: C and D stay at their initial values for the first noise_after_s [s] of
                updates (default 600 s from scratch, 0 from a prior). From θ = 0 the noise model would
                otherwise explain the output as an AR process (D/C y ≈ e) before B_i/F_i has moved, a
                local minimum with a good one-step prediction and a poor simulation.
    poles_after_s  FIR phase: F_i too stay at their initial values for the first poles_after_s [s] of updates
                (default 60 s from scratch, 0 from a prior), so only the B_i move: a linear regression, whose
                estimate cannot run off. From θ = 0, B_i and F_i adapting together can reach, within seconds
                and on a few disturbed samples, large opposite gains whose F_i cancel them on that stretch; P
                has collapsed by then and the estimate never leaves that minimum.
    """

    def __init__(self, structure=None, Ts: float | None = None, *, prior=None, lam: float | None = None,
                 lam_start: float | None = None, lam0: float = 0.9995, P0=None, R: float | None = None, Q=0.0,
                 u0=None, y0: float | None = None, trace_max: float | None = None, radius: float = RADIUS,
                 max_gap_s: float = 1.0, warmup_s: float = 10.0, fit_window_s: float = 600.0,
                 noise_after_s: float | None = None, poles_after_s: float | None = None):
        if structure is None:
            if prior is None:
                raise ValueError("give a structure or a prior model")
            structure = prior.structure
        s = self.structure = structure
        if s.na:
            raise ValueError("RPEM estimates BJ/OE structures (na = 0)")
        if prior is not None and prior.structure != s:
            raise ValueError(f"prior has structure {prior.structure}, expected {s}")
        if Ts is None and prior is None:
            raise ValueError("give the sampling interval Ts or a prior model")
        self.Ts = float(prior.Ts if Ts is None else Ts)
        self.prior = prior
        m, d = s.n_inputs, s.n_params
        ob = np.cumsum([0, *s.nb])[:-1]
        of = sum(s.nb) + np.cumsum([0, *s.nf])[:-1]
        self._orders = np.column_stack([s.nb, s.nf, s.nk, ob, of]).astype(np.int64)
        self._oc = int(sum(s.nb) + sum(s.nf))
        self._od = self._oc + s.nc
        lags = [s.nc, s.nd] + [k + b - 1 for k, b in zip(s.nk, s.nb)] + [s.nc + f for f in s.nf]
        self._hist = np.zeros((4 * m + 4, max(lags) + 1))

        self.theta = prior.theta.copy() if prior is not None else np.zeros(d)
        cov = prior.covariance if prior is not None else None
        noise_var = (prior.info or {}).get("noise_variance") if prior is not None else None
        self.R = float(R if R is not None else noise_var or 1.0)
        if P0 is None and cov is not None:
            P0 = cov * (self.R / noise_var) if noise_var else cov
        elif P0 is None:
            P0 = (0.1 * self.theta) ** 2 + 1e-10 if prior is not None else 100.0
        P0 = np.asarray(P0, float)
        self.P = P0 if P0.ndim == 2 else np.diag(np.broadcast_to(P0, (d,)).astype(float))
        self.P = np.array(self.P, float)
        if self.P.shape != (d, d):
            raise ValueError(f"P0 must be {d} × {d}")
        Q = np.asarray(Q, float)
        self.Q = np.array(Q if Q.ndim == 2 else np.diag(np.broadcast_to(Q, (d,))), float)
        if self.Q.shape != (d, d):
            raise ValueError(f"Q must be {d} × {d}")
        self.u0 = np.asarray(u0 if u0 is not None else prior.u0 if prior is not None else np.zeros(m), float)
        self.y0 = float(y0 if y0 is not None else prior.y0 if prior is not None else 0.0)

        lam_inf = 1.0 if lam is None else float(lam)
        if lam_start is None:
            lam_start = 0.99 if prior is None else 1.0
        for name, value in (("lam", lam_inf), ("lam_start", lam_start), ("lam0", lam0)):
            if not 0.0 < value <= 1.0:
                raise ValueError(f"{name} must be in (0, 1], got {value}")
        trace0 = float(np.trace(self.P))
        if noise_after_s is None:
            noise_after_s = 0.0 if prior is not None else 600.0
        if poles_after_s is None:
            poles_after_s = 0.0 if prior is not None else 60.0
        self._cfg = np.array([lam_inf, lam0, self.R, trace_max or 10.0 * trace0, radius, round(max_gap_s / self.Ts),
                              round(warmup_s / self.Ts), 1.0 - self.Ts / fit_window_s,
                              round(noise_after_s / self.Ts), self._oc, round(poles_after_s / self.Ts), sum(s.nb)],
                             float)
        self._st = np.zeros(13)
        self._st[S_LAM] = lam_inf if lam is not None else lam_start
        self._st[S_GAP_U] = np.inf

    def reset(self) -> None:
        """Forget the filter states: the next sample with valid inputs restarts them (e.g. after a jump in time)."""
        self._st[S_GAP_U] = np.inf

    def update(self, u, y, valid=None, every: int = 0) -> Trace:
        """Run the estimator over N more samples: u (N × m) [input units], y (N) [output unit], absolute
        values (the operating point is subtracted here); valid (N) bool, False = not available (like NaN).
        every > 0 keeps θ every `every` samples in the Trace."""
        u = np.asarray(u, float)
        u = u[:, None] if u.ndim == 1 else u
        y = np.asarray(y, float)
        N = y.size
        if u.shape != (N, self.structure.n_inputs):
            raise ValueError(f"u must be ({N}, {self.structure.n_inputs}), got {u.shape}")
        valid = np.ones(N, bool) if valid is None else np.asarray(valid, bool)
        t0 = int(self._st[S_T])
        k = (t0 + N) // every - t0 // every if every > 0 else 0
        snaps = np.empty((k, self.theta.size))
        out = [np.empty(N) for _ in range(3)] + [np.empty(N, np.int8)] + [np.empty(N) for _ in range(2)]
        _run(np.ascontiguousarray(u - self.u0), y - self.y0, valid, self.theta, self.P, self.Q, self._hist,
             self._orders, self.structure.nc, self.structure.nd, self._oc, self._od, self._cfg, self._st, every,
             snaps, *out)
        yhat, ysim, eps, status, dtheta, trace_P = out
        at = (np.arange(t0 // every + 1, (t0 + N) // every + 1) * every - t0 - 1) if every > 0 else np.empty(0, int)
        return Trace(yhat + self.y0, ysim + self.y0, eps, status, dtheta, trace_P, snaps, at)

    @property
    def lam(self) -> float:
        """Current forgetting factor λ(t)."""
        return float(self._st[S_LAM])

    @property
    def noise_variance(self) -> float:
        """Λ̂: running mean of ε² [output unit²] (NaN before the first update)."""
        return float(self._st[S_SEE] / self._st[S_SW]) if self._st[S_SW] > 0 else math.nan

    def fits(self) -> tuple[float, float]:
        """Running (prediction, simulation) fit [%] over the fit window: 100 (1 − ‖ε‖/‖ỹ − mean‖), v for ε."""
        return running_fits(*self._st[[S_SW, S_SY, S_SYY, S_SEE, S_SVV]])

    def report(self) -> dict:
        """Convergence summary: samples, updates (shrunk, rejected), λ, trace(P), running fits, Λ̂."""
        fit_pred, fit_sim = self.fits()
        return {
            "samples": int(self._st[S_T]),
            "updates": int(self._st[S_UPDATES]),
            "shrunk_steps": int(self._st[S_SHRUNK]),
            "rejected_steps": int(self._st[S_REJECTED]),
            "lam": self.lam,
            "trace_P": float(np.trace(self.P)),
            "running_fit_prediction_pct": fit_pred,
            "running_fit_simulation_pct": fit_sim,
            "noise_variance": self.noise_variance,
        }

    def covariance(self) -> np.ndarray:
        """Parameter covariance P Λ̂/R (P when Λ̂ is not yet known)."""
        lam_hat = self.noise_variance
        return self.P * (lam_hat / self.R) if math.isfinite(lam_hat) else self.P.copy()

    def model(self, **info):
        """The current estimate as a PolyModel (operating point, names and units of the prior), with the
        covariance and the `report()` (None for what is not known yet) in info, plus any extra info given."""
        meta = {}
        if self.prior is not None:
            p = self.prior
            meta = dict(input_names=p.input_names, input_units=p.input_units, output_name=p.output_name,
                        output_unit=p.output_unit, effects=p.effects)
        rep = {k: (v if v == v else None) for k, v in self.report().items()}  # NaN (not yet known) → None
        return from_theta(self.theta, self.structure, self.Ts, u0=tuple(self.u0), y0=self.y0,
                          covariance=self.covariance(), **meta,
                          info={"method": "recursive prediction error (RPEM)", **rep,
                                "parameter_names": parameter_names(self.structure), **info})
