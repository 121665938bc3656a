"""The engine: full-load curve, friction and auxiliaries, idle governor, reference torque and inertia.

Torques follow J1939: SPN 513 (actual engine percent torque) is the *indicated* torque, friction included, in %
of the reference torque SPN 544. The brake (flywheel) torque is

    T_brake = T_ind - T_fric - T_aux            [Nm]

and, while the clutch is open, the crankshaft obeys  J dω/dt = T_brake  [Nm], ω in rad/s.
"""
from dataclasses import dataclass

import numpy as np

RPM_TO_RAD_S = 2.0 * np.pi / 60.0


@dataclass(frozen=True)
class Engine:
    """A heavy-duty 9.3 L engine. Torque tables are indicated torque [Nm] over engine speed [rpm]."""

    name: str
    reference_torque_nm: float = 1600.0      # SPN 544
    idle_speed_rpm: float = 600.0            # SPN 188
    inertia_kgm2: float = 3.2                # SPN 1794: crankshaft, flywheel and clutch
    max_speed_rpm: float = 2100.0            # governor end
    full_load_rpm: tuple = (500, 600, 800, 1000, 1300, 1500, 1700, 1900, 2000, 2100, 2300)
    full_load_nm: tuple = (700, 900, 1300, 1700, 1700, 1600, 1420, 1270, 1150, 800, 0)
    friction_idle_nm: float = 80.0           # T_fric at idle [Nm]
    friction_slope_nm_per_rpm: float = 0.06  # T_fric growth with speed [Nm/rpm]
    friction_rpm: tuple = ()                 # a measured T_fric table [rpm] (VECTO: minus the motoring torque);
    friction_nm: tuple = ()                  # [Nm]; empty: the linear law above
    pt1_s: tuple = ()                        # full-load torque build-up time constant over full_load_rpm [s]
    strict_full_load: bool = False          # the drive caps the lagging torque at full load; off for the paper
                                             # engines only, so that their shipped trips stay byte for byte
    aux_nm: float = 32.0                     # alternator, air compressor, steering pump [Nm]
    idle_governor_tau_s: float = 0.25        # idle/synchronisation speed-control time constant [s]

    def full_load_torque_nm(self, speed_rpm):
        """Maximum indicated torque T_full(n) [Nm] at engine speed n [rpm] (linear in the table)."""
        return np.interp(speed_rpm, self.full_load_rpm, self.full_load_nm)

    def friction_torque_nm(self, speed_rpm):
        """T_fric(n) = T_fric,idle + k (n - n_idle) [Nm], or linear in the friction table if there is one."""
        if self.friction_rpm:
            return np.interp(speed_rpm, self.friction_rpm, self.friction_nm)
        return self.friction_idle_nm + self.friction_slope_nm_per_rpm * (speed_rpm - self.idle_speed_rpm)

    def drag_torque_nm(self, speed_rpm):
        """Torque the engine absorbs when no fuel is injected: T_fric + T_aux [Nm] (engine braking)."""
        return self.friction_torque_nm(speed_rpm) + self.aux_nm

    def max_brake_torque_nm(self, speed_rpm):
        """T_brake,max(n) = T_full(n) - T_fric(n) - T_aux [Nm]."""
        return self.full_load_torque_nm(speed_rpm) - self.drag_torque_nm(speed_rpm)

    def pt1_time_constant_s(self, speed_rpm):
        """Time constant [s] of the full-load torque build-up at engine speed [rpm]; 0 without a PT1 table."""
        if not self.pt1_s:
            return np.zeros_like(np.asarray(speed_rpm, float))
        return np.interp(speed_rpm, self.full_load_rpm, self.pt1_s)

    def percent(self, torque_nm):
        """Torque as J1939 percent of the reference torque: 100 T / T_ref [%]."""
        return 100.0 * np.asarray(torque_nm) / self.reference_torque_nm


ENGINES = {
    "diesel_p320": Engine("Scania DC09 320 hp diesel"),
    "gas_p340": Engine("Scania OC09 340 hp gas", full_load_nm=(650, 850, 1250, 1700, 1700, 1650, 1500,
                                                                 1350, 1250, 850, 0)),
}
"""Engine per fuel truth (the paper's P320 diesel and P340 gas tractors)."""
