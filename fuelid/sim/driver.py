"""The driver: follows the target speed with a feed-forward + proportional law and an imperfect foot.

    a_des = a_ref + K_p (v_ref - v) + a_noise(t)        clipped to [-a_brake, a_max]    [m/s²]
    F_des = m_eff a_des + F_road(v, α)                                                [N]

a_noise is low-pass filtered Gaussian noise (driver imperfection, traffic): the torque excitation that makes
on-road data informative. Under cruise control it is much smaller.
"""
from dataclasses import dataclass

import numpy as np
from scipy import signal


@dataclass(frozen=True)
class Driver:
    kp_1_s: float = 0.6              # speed error gain K_p [1/s]
    a_max_m_s2: float = 1.0          # strongest wanted acceleration [m/s²]
    a_brake_m_s2: float = 2.5        # strongest wanted deceleration [m/s²]
    noise_m_s2: float = 0.12         # std of a_noise when driving by pedal [m/s²]
    cruise_noise_m_s2: float = 0.03  # std of a_noise under cruise control [m/s²]
    noise_tau_s: float = 1.5         # correlation time of a_noise [s]
    torque_tau_s: float = 0.12       # engine torque response to the demand (first-order lag) [s]


def lowpass_noise(n: int, dt: float, tau_s: float, rng: np.random.Generator) -> np.ndarray:
    """Unit-variance first-order low-pass (Ornstein-Uhlenbeck) noise: x_k = a x_(k-1) + sqrt(1-a²) w_k,
    a = exp(-dt/τ)."""
    a = np.exp(-dt / tau_s)
    return signal.lfilter([np.sqrt(1.0 - a * a)], [1.0, -a], rng.normal(size=n))


def acceleration_noise(driver: Driver, cruise: np.ndarray, dt: float, rng: np.random.Generator) -> np.ndarray:
    """a_noise(t) [m/s²]: driver imperfection, smaller where cruise control is active."""
    x = lowpass_noise(len(cruise), dt, driver.noise_tau_s, rng)
    return x * np.where(cruise, driver.cruise_noise_m_s2, driver.noise_m_s2)
