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

(`gain_drift_Q`); any symmetric Q can be given instead.
"""
from __future__ import annotations

import numpy as np

from ident.rpem import RPEM


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
