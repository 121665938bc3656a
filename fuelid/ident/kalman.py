"""Kalman-filter tracking of a drifting BJ model: the parameters as a random walk.

    θ(t) = θ(t−1) + w(t),        w ~ N(0, Q)   [parameter units² per sample]
    ỹ(t) = ψᵀ(t) θ(t) + e(t),    e ~ N(0, R)   [output unit²]

The measurement equation is the BJ predictor linearised around the current estimate: ψ(t) = −∂ε/∂θ is the
RPEM gradient (pseudo-regressor) and ε(t) the prediction error, both from the recursive filters of
ident.rpem. The filter (Ljung, *System Identification*, 1999, eq. 11.66 with λ = 1, R1 = Q, R2 = R):

    K = P ψ / (R + ψᵀ P ψ)
    θ ← θ + K ε                       (projected: F_i, C, D stay stable, as in ident.rpem)
    P ← P − K ψᵀ P + Q

This is filterpy.kalman.KalmanFilter with F = I, H = ψᵀ(t), update then predict. filterpy is not used in the
loop: H changes every sample, and one predict/update of its 41-state filter costs tens of µs of numpy calls
(a few thousand samples/s); the same equations run here in the compiled loop of ident.rpem (tens of
thousands of samples/s). tests/ident/test_kalman.py checks one step against filterpy.

Which Q. Compared with RPEM forgetting (which inflates all of P by 1/λ), Q says which parameters drift and
how. A diagonal Q is a poor choice for the paper's orders: the BJ model has near pole–zero cancellations
(the PEM covariance has a condition number ~1e16), and independent random walks of the coefficients wander
along the directions the data do not determine, where the DC gain B_i(1)/F_i(1) (a small difference of
large coefficients) is very sensitive. The default is the physical drift of fuel systems — injector wear,
fuel quality, meter calibration — a common relative change g(t) of every B_i, the dynamics fixed:

    θ_b(t) = g(t) θ_b(0),  g a random walk of step std `rate`   ⇒   Q = rate² β βᵀ,  β = [θ_b(0); 0; …; 0]

(`gain_drift_Q`); any symmetric Q can be given instead. With F_i, C and D free through P0 (the prior's
covariance) this still does not track a drift robustly; `GainTracker` estimates g alone with the prior's
dynamics and noise model held, exactly (its docstring), and is what the live estimator runs from a prior.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from fuelid.ident.rpem import RPEM, Trace, running_fits


def gain_drift_Q(theta, structure, rate: float) -> np.ndarray:
    """Q = rate² β βᵀ with β the B coefficients of θ (zeros elsewhere): a random walk of the common relative
    fuel gain, step std `rate` per sample (e.g. 3e-4: ~3 % over 10⁴ samples, 50 min at Ts = 0.3 s)."""
    beta = np.zeros(structure.n_params)
    nb = sum(structure.nb)
    beta[:nb] = np.asarray(theta, float)[:nb]
    return rate**2 * np.outer(beta, beta)


class ParameterKalman(RPEM):
    """Kalman filter for a random-walk θ (module docstring); the rest as ident.rpem.RPEM (gaps, projection,
    reports, `update`, `model`).

    Q       random-walk covariance per sample: scalar, vector (diagonal) or d × d; default
            gain_drift_Q(prior θ, rate)
    rate    relative fuel-gain drift per sample for the default Q (needs a prior)
    R       measurement noise variance [output unit²]; default the prior's noise variance, else 1
    """

    def __init__(self, structure=None, Ts: float | None = None, *, prior=None, Q=None, rate: float = 3e-4,
                 R: float | None = None, **kwargs):
        if Q is None:
            if prior is None:
                raise ValueError("give the random-walk covariance Q or a prior model to scale it from")
            Q = gain_drift_Q(prior.theta, prior.structure, rate)
        super().__init__(structure, Ts, prior=prior, lam=1.0, Q=Q, R=R, **kwargs)

    def model(self, **info):
        return super().model(**{"method": "Kalman filter, random-walk parameters (linearised BJ predictor)", **info})


@njit(cache=True)
def _track(eps0, phi, status, y, w0, cfg, st, g_out, p_out, e_out):
    """The scalar gain filter of GainTracker over one block (its docstring); g_out, p_out g and p after each
    sample, e_out ε(g) with the g before it. st = [g, p, Σw, Σw ỹ, Σw ỹ², Σw ε², Σw v², updates]."""
    lam, q, R, gamma = cfg[0], cfg[1], cfg[2], cfg[3]
    g, p = st[0], st[1]
    for t in range(eps0.size):
        e = eps0[t] - (g - 1.0) * phi[t]
        e_out[t] = e
        if status[t] > 0:  # inputs and output present, not warming up: a sample the RPEM would update on
            v = y[t] - g * w0[t]
            st[2] = gamma * st[2] + 1.0
            st[3] = gamma * st[3] + y[t]
            st[4] = gamma * st[4] + y[t] * y[t]
            st[5] = gamma * st[5] + e * e
            st[6] = gamma * st[6] + v * v
            k = p * phi[t] / (lam * R + p * phi[t] * phi[t])
            g += k * e
            p = (p - k * phi[t] * p) / lam + q
            st[7] += 1.0
        g_out[t], p_out[t] = g, p
    st[0], st[1] = g, p


class GainTracker:
    """Tracks the common relative fuel gain g of a prior BJ model, everything else held (the prior's poles F_i
    and noise model C/D):

        ỹ(t) = g(t) Σ_i B⁰_i/F⁰_i ũ_i(t) + C⁰/D⁰ e(t)        ⇒   θ_b = g θ⁰_b, every DC gain × g

    so g − 1 is the change of the steady-state fuel at any operating point (injector wear, fuel quality, meter
    calibration). The prediction error is affine in g,

        ε(t; g) = D⁰/C⁰ (ỹ − g w⁰) = ε⁰(t) − (g − 1) φ(t),   w⁰ = Σ_i B⁰_i/F⁰_i ũ_i,  φ = D⁰/C⁰ w⁰ = −∂ε/∂g,

    and ε⁰ and φ come from two ident.rpem.RPEM runs with θ held at the prior's (P = 0): one on the data, one
    with ỹ = 0 (−φ), with the same gaps, holds and restarts. The filters hold the prior's θ, so — unlike an RPEM
    adapting B_i, whose past filtered values stay those of older θ and, through the near-integrators of the
    paper's F_i, for hours — ε(t; g) is the exact prediction error of every g. The scalar filter

        K = p φ / (λ R + p φ²),   g ← g + K ε(t; g),   p ← (p − K φ p)/λ + q

    is recursive least squares with forgetting λ (q = 0) or the Kalman filter of a random-walk gain with step
    variance q = rate² (λ = 1): Q = q β βᵀ in θ (β = θ⁰_b, zeros elsewhere; gain_drift_Q), zero for F, C, D.
    var(g) = p Λ̂/R (Λ̂ the running mean of ε²) gives the confidence interval of the fuel change.

    Why not every parameter: with F_i, C, D free (RPEM or ParameterKalman from a prior) the noise model, D close
    to an integrator, absorbs a slow gain change in the one-step prediction, and the DC gains of the paper's
    orders (near pole–zero cancellations) are poorly determined: +5 % was reported as +4.9 / +3.6 / +1.2 /
    +0.8 % on four synthetic data sets, and −0.2 % with 7-s not-available bursts in the fuel signal.

    prior   PolyModel (its θ, operating point, noise variance R, names and units)
    lam     forgetting factor λ in (0, 1] (memory Ts/(1 − λ): 0.9995 ≈ 10 min at Ts = 0.3 s)
    rate    relative gain drift per sample (random-walk step std) [-]
    P0      initial variance of g [-] (default 0.1²: 10 %)
    kwargs  max_gap_s, warmup_s, fit_window_s as ident.rpem.RPEM
    """

    def __init__(self, prior, *, lam: float = 1.0, rate: float = 0.0, P0: float = 0.1**2, **kwargs):
        if not 0.0 < lam <= 1.0:
            raise ValueError(f"lam must be in (0, 1], got {lam}")
        fixed = dict(prior=prior, lam=1.0, P0=0.0, **kwargs)
        self._data, self._sim = RPEM(**fixed), RPEM(**fixed)
        self.prior, self.structure, self.Ts = prior, prior.structure, self._data.Ts
        self.u0, self.y0, self.R = self._data.u0, self._data.y0, self._data.R
        self._theta0 = prior.theta  # (PolyModel.theta is assembled on every call)
        self._beta = np.where(np.arange(self._theta0.size) < sum(prior.structure.nb), self._theta0, 0.0)
        self._cfg = np.array([lam, rate**2, self.R, 1.0 - self.Ts / kwargs.get("fit_window_s", 600.0)])
        self._st = np.array([1.0, P0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])

    def reset(self) -> None:
        """Restart the filters (ident.rpem.RPEM.reset); g and its variance are kept."""
        self._data.reset()
        self._sim.reset()

    def update(self, u, y, valid=None, every: int = 0) -> Trace:
        """As ident.rpem.RPEM.update; θ in the Trace is the prior's with B scaled by g."""
        y = np.asarray(y, float)
        g_before = self._st[0]
        td = self._data.update(u, y, valid, every)
        ts = self._sim.update(u, np.where(np.isfinite(y), self.y0, np.nan), valid)
        w0, phi = td.ysim - self.y0, -ts.eps
        g, p, e = np.empty(y.size), np.empty(y.size), np.empty(y.size)
        _track(td.eps, phi, td.status, y - self.y0, w0, self._cfg, self._st, g, p, e)
        g_prev = np.concatenate(([g_before], g[:-1]))
        beta2 = self._beta @ self._beta
        dtheta = np.abs(g - g_prev) * math.sqrt(beta2) / np.linalg.norm(self._theta0)
        theta = self._theta0 + np.outer(g[td.theta_at] - 1.0, self._beta)
        return Trace(td.yhat + (g_prev - 1.0) * (ts.yhat - self.y0), self.y0 + g_prev * w0, e, td.status, dtheta,
                     p * beta2, theta, td.theta_at)

    @property
    def gain(self) -> float:
        """g: the fuel gain relative to the prior's [-]."""
        return float(self._st[0])

    @property
    def theta(self) -> np.ndarray:
        """The prior's θ with B × g."""
        return self._theta0 + (self.gain - 1.0) * self._beta

    @property
    def P(self) -> np.ndarray:
        """p β βᵀ: the θ covariance (in R units) of the gain filter."""
        return self._st[1] * np.outer(self._beta, self._beta)

    @property
    def lam(self) -> float:
        """Forgetting factor λ."""
        return float(self._cfg[0])

    @property
    def noise_variance(self) -> float:
        """Λ̂: running mean of ε² [output unit²] (NaN before the first update)."""
        return float(self._st[5] / self._st[2]) if self._st[2] > 0 else math.nan

    def fuel_change(self) -> tuple[float, float]:
        """(100 (g − 1), 1.96 · 100 √var(g)): the steady-state fuel change since the prior and its 95 %
        confidence half-width [%], var(g) = p Λ̂/R (p when Λ̂ is not known yet)."""
        lam_hat = self.noise_variance
        var = self._st[1] * (lam_hat / self.R if math.isfinite(lam_hat) else 1.0)
        return 100.0 * (self.gain - 1.0), 196.0 * math.sqrt(var)

    def fits(self) -> tuple[float, float]:
        """Running (prediction, simulation) fit [%] over the fit window (ident.rpem.RPEM.fits)."""
        return running_fits(*self._st[2:7])

    def report(self) -> dict:
        """As ident.rpem.RPEM.report, plus the fuel change [%] and its 95 % half-width [%]."""
        fit_pred, fit_sim = self.fits()
        change, ci = self.fuel_change()
        return {"samples": self._data.report()["samples"], "updates": int(self._st[7]), "shrunk_steps": 0,
                "rejected_steps": 0, "lam": self.lam, "trace_P": float(self._st[1] * (self._beta @ self._beta)),
                "running_fit_prediction_pct": fit_pred, "running_fit_simulation_pct": fit_sim,
                "noise_variance": self.noise_variance, "fuel_change_pct": change, "fuel_change_ci95_pct": ci}

    def covariance(self) -> np.ndarray:
        """θ covariance var(g) β βᵀ."""
        return (self.fuel_change()[1] / 196.0) ** 2 * np.outer(self._beta, self._beta)

    def model(self, **info):
        """The prior with B scaled by g (ident.rpem.RPEM.model)."""
        return RPEM.model(self, **{"method": "fuel-gain tracking (prior's dynamics and noise model held)", **info})
