"""Longitudinal dynamics of a 40-44 t articulated truck (tractor and semi-trailer).

    m_eff dv/dt = F_trac - F_roll - F_aero - F_grade - F_brake                       [N]
    F_roll  = m g C_rr cos(α)                                                        [N]
    F_aero  = ½ ρ C_d A v²                                                           [N]
    F_grade = m g sin(α)                                                             [N]
    F_trac  = T_clutch i_gear i_fd η / r_w                                           [N]
    m_eff   = m + (J_wheels + J_engine (i_gear i_fd)²) / r_w²    (clutch closed)     [kg]
"""
from dataclasses import dataclass

import numpy as np

G_M_S2 = 9.81
R_AIR_J_KGK = 287.05


@dataclass(frozen=True)
class Truck:
    mass_kg: float = 40000.0
    cda_m2: float = 5.8             # drag coefficient x frontal area
    crr: float = 0.0055             # rolling resistance coefficient
    wheel_radius_m: float = 0.492   # 315/70 R22.5 dynamic radius
    final_drive: float = 2.59       # rear-axle ratio
    driveline_eff: float = 0.94     # gearbox and axle efficiency η
    wheels_inertia_kgm2: float = 120.0  # all wheels, brake discs and axles at wheel speed


def air_density_kg_m3(pressure_kpa, temperature_c):
    """ρ = p / (R_air T)  [kg/m³], p in kPa, T in °C."""
    return np.asarray(pressure_kpa) * 1000.0 / (R_AIR_J_KGK * (np.asarray(temperature_c) + 273.15))


def wheel_speed_to_engine_rpm(truck: Truck, speed_m_s, gear_ratio):
    """n = v i_gear i_fd / r_w x 60/(2π)  [rpm] with the clutch closed."""
    return np.asarray(speed_m_s) * gear_ratio * truck.final_drive / truck.wheel_radius_m * 60.0 / (2.0 * np.pi)


def effective_mass_kg(truck: Truck, gear_ratio, engine_inertia_kgm2):
    """m_eff = m + (J_wheels + J_engine (i_gear i_fd)²) / r_w²  [kg]; gear_ratio 0 means clutch open."""
    i_total = np.asarray(gear_ratio) * truck.final_drive
    return truck.mass_kg + (truck.wheels_inertia_kgm2 + engine_inertia_kgm2 * i_total ** 2) / truck.wheel_radius_m ** 2
