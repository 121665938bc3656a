"""The forward simulation of driver, engine, AMT and vehicle on a fine time grid.

Hand-written as one scalar time-stepping loop (explicit Euler, step dt) rather than vectorised: the gear state
machine, the clutch and the driver's feedback depend on the previous step. Everything that does not feed back
(fuel, temperatures, effects, CAN frames) is computed afterwards on whole arrays. The loop uses Python floats
and lists because numpy scalar indexing would make it several times slower.

Modes: NEUTRAL (clutch open, engine governed to idle or coasting), LAUNCH (gear in, clutch slipping, engine
held at the launch speed), DRIVE (clutch closed: n = v i_gear i_fd / r_w), SHIFT (traction interruption).
In DRIVE the engine inertia is part of the vehicle's effective mass; with the clutch open or slipping the
crankshaft obeys J dω/dt = T_brake - T_clutch.
"""
from dataclasses import dataclass

import numpy as np

from fuelid.errors import InputError
from fuelid.sim import gearbox
from fuelid.sim.driver import Driver, acceleration_noise, lowpass_noise
from fuelid.sim.engine import RPM_TO_RAD_S, Engine
from fuelid.sim.route import RoadProfile, SpeedProfile
from fuelid.sim.vehicle import G_M_S2, Truck, effective_mass_kg, wheel_speed_to_engine_rpm

NEUTRAL, LAUNCH, DRIVE, SHIFT = 0, 1, 2, 3
MODE_NAMES = ("neutral", "launch", "drive", "shift")
LAUNCH_RPM = 850.0
"""Engine speed the engine holds while the clutch slips at a start [rpm]."""
RETARDER_MAX_N = 25000.0
"""Largest braking force of the driveline retarder at the wheels [N]; above it the service brakes work."""
SYNC_UP_RPM_S, SYNC_DOWN_RPM_S = 1500.0, 1200.0
"""Fastest engine speed change while synchronising in neutral: throttle blip up, exhaust brake down [rpm/s]."""
IDLE_RIPPLE_RPM = 3.0
"""Standard deviation of the idle governor's speed ripple [rpm]."""


def _check_startable(need_n: float, can_n: float, truck: Truck, road: RoadProfile) -> None:
    """InputError when the engine's launch torque in first gear (can_n [N] at the wheels) cannot hold the truck on
    the route's steepest grade (need_n [N], rolling resistance and grade): such a truck would stand in its launch
    for the rest of the trip, a recording of nothing but a slipping clutch."""
    if can_n < need_n:
        raise InputError(f"the engine cannot start this truck: at {LAUNCH_RPM:g} rpm in first gear it pushes "
                         f"{can_n / 1000:.1f} kN, the {truck.mass_kg / 1000:g} t truck needs {need_n / 1000:.1f} kN "
                         f"on the route's steepest grade ({100 * np.tan(np.max(road.grade_rad)):.1f} %); the "
                         "simulator's truck needs a heavy-truck engine")


@dataclass
class Drive:
    """Fine-grid result of the drive simulation (all arrays of equal length, step dt_s)."""

    dt_s: float
    speed_m_s: np.ndarray
    distance_m: np.ndarray
    grade_rad: np.ndarray
    engine_speed_rpm: np.ndarray
    brake_torque_nm: np.ndarray      # engine flywheel torque incl. J dω/dt [Nm]
    demand_torque_nm: np.ndarray     # torque the driver / cruise control asks of the engine [Nm], brake
    pedal: np.ndarray                # accelerator pedal 0..1
    gear: np.ndarray                 # current gear, 0 = neutral
    selected_gear: np.ndarray        # gear the AMT is going to / holding
    service_brake_n: np.ndarray      # service brake force [N]
    retarder_n: np.ndarray           # retarder braking force [N]
    mode: np.ndarray                 # NEUTRAL, LAUNCH, DRIVE, SHIFT
    cruise: np.ndarray               # cruise control active


def simulate_drive(profile: SpeedProfile, road: RoadProfile, truck: Truck, engine: Engine,
                   air_density_kg_m3: np.ndarray, dt: float, rng: np.random.Generator,
                   driver: Driver = Driver()) -> Drive:
    n = len(profile.v_ref)
    v_ref, a_ref = profile.v_ref.tolist(), profile.a_ref.tolist()
    cruise = profile.cruise
    a_noise = acceleration_noise(driver, cruise, dt, rng).tolist()
    ripple = (IDLE_RIPPLE_RPM * lowpass_noise(n, dt, 0.3, rng)).tolist()
    half_rho_cda = (0.5 * air_density_kg_m3 * truck.cda_m2).tolist()
    grade_list = road.grade_rad.tolist()
    roll_mg = (truck.mass_kg * G_M_S2 * (truck.crr * np.cos(road.grade_rad) + np.sin(road.grade_rad))).tolist()
    n_road = len(grade_list) - 1
    rpm_per = [float(wheel_speed_to_engine_rpm(truck, 1.0, g)) for g in gearbox.GEAR_RATIOS]
    force_per_nm = [g * truck.final_drive * truck.driveline_eff / truck.wheel_radius_m for g in gearbox.GEAR_RATIOS]
    m_eff = [float(effective_mass_kg(truck, g, engine.inertia_kgm2)) for g in gearbox.GEAR_RATIOS]
    m_free = float(effective_mass_kg(truck, 0.0, engine.inertia_kgm2))
    # Engine curves tabulated per rpm: list look-ups instead of np.interp inside the loop.
    rpm_grid = np.arange(0, 2601, dtype=float)
    t_max = engine.max_brake_torque_nm(rpm_grid).tolist()
    t_full = engine.full_load_torque_nm(rpm_grid).tolist()
    t_drag = engine.drag_torque_nm(rpm_grid).tolist()
    # Full-load torque builds up with a PT1 where the engine gives one (VECTO .vfld): the limit moves from the
    # present torque towards the static full load by 1 - exp(-dt/τ) per step.
    has_pt1, capped = bool(engine.pt1_s), engine.strict_full_load
    tau = engine.pt1_time_constant_s(rpm_grid)
    k_pt1 = np.where(tau > 0.0, -np.expm1(-dt / np.maximum(tau, 1e-9)), 1.0).tolist()
    j_engine, idle = engine.inertia_kgm2, engine.idle_speed_rpm
    _check_startable(max(roll_mg), t_max[int(LAUNCH_RPM)] * force_per_nm[0], truck, road)
    k_sync = dt / engine.idle_governor_tau_s
    k_torque = dt / driver.torque_tau_s
    rad_s_per_rpm_dt = RPM_TO_RAD_S / dt

    out_v, out_x, out_n, out_tb, out_td, out_pedal = ([0.0] * n for _ in range(6))
    out_gear, out_sel, out_mode = ([0] * n for _ in range(3))
    out_brake, out_ret = [0.0] * n, [0.0] * n

    v = x = tb = shift_t = tb0 = 0.0
    rpm = idle
    mode, gear, sel = NEUTRAL, 0, 0
    hold_until = 0.0
    for i in range(n):
        t = i * dt
        xi = min(int(x), n_road)
        f_road = roll_mg[xi] + half_rho_cda[i] * v * v
        vr = v_ref[i]
        a_des = a_ref[i] + driver.kp_1_s * (vr - v) + (a_noise[i] if vr > 0.0 else 0.0)
        a_des = min(driver.a_max_m_s2, max(-driver.a_brake_m_s2, a_des))
        f_trac = t_dem = pedal = 0.0
        mass = m_free
        rpm_prev = rpm

        if mode == NEUTRAL:
            if vr > 0.3 and a_des > 0.0:
                mode = LAUNCH
                gear = sel = gearbox.launch_gear(grade_list[xi]) if v < 2.0 else max(
                    1, min(range(1, 13), key=lambda g: abs(v * rpm_per[g - 1] - 1000.0)))
            else:
                rpm += (idle + ripple[i] - rpm) * k_sync
                tb = j_engine * (rpm - rpm_prev) * rad_s_per_rpm_dt
        if mode == LAUNCH:
            k = gear - 1
            t_dem = (m_eff[k] * a_des + f_road) / force_per_nm[k]
            r = min(2600, int(rpm))
            rpm += (LAUNCH_RPM - rpm) * k_sync
            t_accel = j_engine * (rpm - rpm_prev) * rad_s_per_rpm_dt
            t_clutch = min(max(t_dem, 0.0), t_max[r] - max(t_accel, 0.0))
            tb = t_clutch + t_accel
            f_trac = t_clutch * force_per_nm[k]
            pedal = (tb + t_drag[r]) / t_full[r]
            if v * rpm_per[k] >= rpm - 10.0:
                mode = DRIVE
            elif vr <= 0.3 and a_des <= 0.0:
                mode, gear, sel = NEUTRAL, 0, 0
        elif mode == DRIVE:
            k = gear - 1
            rpm = max(v * rpm_per[k], 1.0)
            r = min(2600, int(rpm))
            mass = m_eff[k]
            t_dem = (mass * a_des + f_road) / force_per_nm[k]
            t_lim = tb + (t_max[r] - tb) * k_pt1[r] if has_pt1 else t_max[r]
            t_cmd = min(max(t_dem, -t_drag[r]), t_lim)
            tb += (t_cmd - tb) * k_torque
            if capped:  # the torque lag must not carry tb above a falling full-load curve as the speed rises
                tb = min(tb, t_max[r])
            f_trac = tb * force_per_nm[k]
            pedal = 0.0 if cruise[i] else max(0.0, (tb + t_drag[r]) / t_full[r])
            if rpm < gearbox.CLUTCH_OPEN_RPM:  # too slow for the gear: declutch, or slip in a start gear
                if t_dem > 0.0 and vr > 0.0:
                    mode, gear = LAUNCH, min(gear, gearbox.launch_gear(grade_list[xi]))
                    sel = gear
                else:
                    mode, gear, sel = NEUTRAL, 0, 0
            if mode == DRIVE and t >= hold_until:
                want = gearbox.select_gear(gear, rpm_per, v, max(0.0, min(1.0, (t_cmd + t_drag[r]) / t_full[r])))
                if want != gear:
                    mode, sel, shift_t, tb0 = SHIFT, want, 0.0, tb
        elif mode == SHIFT:
            shift_t += dt
            if shift_t < gearbox.RAMP_DOWN_S:
                k = gear - 1
                rpm = v * rpm_per[k]
                mass = m_eff[k]
                tb = tb0 * (1.0 - shift_t / gearbox.RAMP_DOWN_S)
                f_trac = tb * force_per_nm[k]
            elif shift_t < gearbox.RAMP_DOWN_S + gearbox.NEUTRAL_S:
                gear = 0
                step = (max(idle, v * rpm_per[sel - 1]) - rpm) * k_sync * 2.0
                rpm += min(SYNC_UP_RPM_S * dt, max(-SYNC_DOWN_RPM_S * dt, step))
                tb = j_engine * (rpm - rpm_prev) * rad_s_per_rpm_dt
            else:
                gear = sel
                k = gear - 1
                rpm = v * rpm_per[k]
                r = min(2600, int(rpm))
                mass = m_eff[k]
                t_dem = (mass * a_des + f_road) / force_per_nm[k]
                t_cmd = min(max(t_dem, -t_drag[r]), t_max[r])
                tb = t_cmd * min(1.0, (shift_t - gearbox.RAMP_DOWN_S - gearbox.NEUTRAL_S) / gearbox.RAMP_UP_S)
                f_trac = tb * force_per_nm[k]
                pedal = 0.0 if cruise[i] else max(0.0, (tb + t_drag[r]) / t_full[r])
                if shift_t >= gearbox.SHIFT_S or rpm < gearbox.CLUTCH_OPEN_RPM:
                    mode, hold_until = DRIVE, t + gearbox.MIN_GEAR_HOLD_S

        # Brakes: only when the engine cannot slow the truck enough (motoring or clutch open).
        free = (f_trac - f_road) / mass
        brake = 0.0
        if a_des < free and (mode == NEUTRAL or tb <= -t_drag[min(2600, int(rpm))] + 1.0 or a_des < -0.3):
            brake = (free - a_des) * mass
        retarder = min(brake, RETARDER_MAX_N) if v > 5.0 and mode == DRIVE else 0.0
        a = free - brake / mass
        v = max(0.0, v + a * dt)
        x += v * dt

        out_v[i], out_x[i], out_n[i], out_tb[i], out_td[i] = v, x, rpm, tb, t_dem
        out_pedal[i], out_gear[i], out_sel[i], out_mode[i] = min(1.0, pedal), gear, sel, mode
        out_brake[i], out_ret[i] = brake - retarder, retarder

    distance = np.array(out_x)
    return Drive(
        dt_s=dt, speed_m_s=np.array(out_v), distance_m=distance,
        grade_rad=road.grade_rad[np.minimum(distance.astype(int), n_road)],
        engine_speed_rpm=np.array(out_n), brake_torque_nm=np.array(out_tb), demand_torque_nm=np.array(out_td),
        pedal=np.array(out_pedal), gear=np.array(out_gear, np.int8), selected_gear=np.array(out_sel, np.int8),
        service_brake_n=np.array(out_brake), retarder_n=np.array(out_ret), mode=np.array(out_mode, np.int8),
        cruise=cruise & (np.array(out_mode) == DRIVE))
