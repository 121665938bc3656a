"""Map-based fuel truth: a VECTO engine's steady-state fuel map run at the engine's instantaneous speed and torque.

A physical truth outside the Box-Jenkins model class (the map is curved over speed x torque), built only from the
engine set (sim.vecto) and the drive; nothing here comes from the identification side.

    T_map  = T_brake + T_aux + T_fan                                flywheel torque the combustion delivers [N m]
    FC     = map(n, T_map)                                          [g/h]; 0 at or below the motoring curve:
                                                                    the injection is cut while the engine motors
    k_tr   = 1 + c_max r / (r + r_half),  r = PT1_τ(max(0, dT_map/dt))   transient fuelling [-], r in N m/s
    f_inj  = FC k_tr / (1000 ρ)                                     injected fuel [L/h], ρ the fuel's density
    f_LFE1 = mean of f_inj over the ECU's last update period, held until the next update      (SPN 183)

Transient fuelling: in a fast load step the turbocharger lags and the engine burns more per unit of torque than
the steady-state map says. VECTO corrects its map-based cycle fuel by the WHTC factors (urban, i.e. most
transient, 1.04 for the 325 kW engine; motorway 1.00). Here the surcharge grows with the recent rate of torque
increase and saturates at c_max = 2 (WHTC_urban - 1): zero in steady driving, at most twice the urban-cycle
average in the steepest steps.

The engine the drive uses (`sim_engine`) is the VECTO engine in sim.engine's terms: friction = minus the motoring
torque, indicated full load = full load + friction, reference torque (EC1 SPN 544) = the largest full-load torque.
"""
import numpy as np
from scipy import signal

from fuelid.sim.engine import Engine
from fuelid.sim.vecto import VectoEngine

TRANSIENT_TAU_S = 1.0
"""Memory of the transient surcharge [s]: about a turbocharger's spool-up time."""
LFE1_UPDATE_S = 0.1
"""The ECU updates its fuel-rate estimate once per LFE1 period (sim.gateway sends LFE1 every 100 ms)."""


def sim_engine(v: VectoEngine, aux_nm: float = 32.0) -> Engine:
    """The VECTO engine as the drive and the bus see it (torque tables over the .vfld speeds)."""
    friction = -v.motoring_nm
    return Engine(name=v.name, reference_torque_nm=v.max_torque_nm, idle_speed_rpm=v.idle_speed_rpm,
                  inertia_kgm2=v.inertia_kgm2, max_speed_rpm=float(v.fld_rpm[-1]),
                  full_load_rpm=tuple(v.fld_rpm.tolist()), full_load_nm=tuple((v.full_load_nm + friction).tolist()),
                  friction_rpm=tuple(v.fld_rpm.tolist()), friction_nm=tuple(friction.tolist()), aux_nm=aux_nm,
                  pt1_s=() if v.pt1_s is None else tuple(v.pt1_s.tolist()), strict_full_load=True)


def transient_factor(v: VectoEngine, torque_nm: np.ndarray, dt: float) -> np.ndarray:
    """k_tr = 1 + c_max r/(r + r_half) [-] on the fine grid (step dt [s]) from the flywheel torque [N m]:
    r is the torque's rate of increase [N m/s] through a first-order lag of TRANSIENT_TAU_S, r_half the engine's
    maximum torque per second, c_max = 2 (WHTC_urban - 1)."""
    rise = np.maximum(0.0, np.diff(np.asarray(torque_nm, float), prepend=torque_nm[0]) / dt)
    a = dt / (TRANSIENT_TAU_S + dt)
    r = _lag(rise, a)
    c_max = 2.0 * max(0.0, v.whtc["urban"] - 1.0)
    return 1.0 + c_max * r / (r + v.max_torque_nm)


def injected_fuel_l_h(v: VectoEngine, speed_rpm: np.ndarray, torque_nm: np.ndarray, dt: float) -> np.ndarray:
    """f_inj = map(n, T) k_tr / (1000 ρ) [L/h] on the fine grid, ρ the engine's (primary) fuel density [kg/L]."""
    return v.fuel_g_h(speed_rpm, torque_nm) * transient_factor(v, torque_nm, dt) / (1000.0 * v.fuel_density_kg_l)


def ecu_reported(values: np.ndarray, dt: float, period_s: float = LFE1_UPDATE_S) -> np.ndarray:
    """What the ECU reports on the fine grid: the mean over each update period [j P, (j+1) P), held over the next
    one (the first period holds the first value)."""
    k = max(1, int(round(period_s / dt)))
    starts = np.arange(0, len(values), k)
    means = np.add.reduceat(values, starts) / np.diff(np.r_[starts, len(values)])
    held = np.r_[values[0], means[:-1]]
    return np.repeat(held, k)[: len(values)]


def _lag(x: np.ndarray, a: float) -> np.ndarray:
    """y(k) = y(k-1) + a (x(k) - y(k-1)), y(-1) = 0: a first-order lag, as a linear filter."""
    return signal.lfilter([a], [1.0, a - 1.0], x)
