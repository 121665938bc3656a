"""One simulated trip: route, drive, engine torques, fuel truth, effects, bus signals and the output files.

    simulate(TripConfig(...)) -> Trip          everything on the fine grid and at Ts = 0.3 s
    write(trip, "x.log.gz")                    x.log.gz (candump -L), x.flow.gz (gas), x.truth.json, x.truth.npz

Fuel pipeline (sim.effects explains each step):

    T_true   = max(0, T_brake + T_fric + T_aux + T_fan)                 indicated torque [Nm]
    y        = y_idle + Gw (n - n_idle) + GT (T_true% - T_idle%) + H e   on the Ts-bin means of n and T_true,
                                                                         held over each bin [k Ts, (k+1) Ts)
    f_engine = max(0, (y + Δf_power) x k_dpf x k_cold x k_shift x k_air x k_overrun)
    f_bus    = f_engine(t - delay)                                       LFE1 SPN 183 or the flow meter
    T_bus%   = T_true% - T_fan% (fan effect) - J dω/dt (inertia effect)  EEC1 SPN 513, J the effect's magnitude;
                                                                         the drive keeps the engine's own inertia

With the map truth (`truth="map"`, a VECTO engine set, sim.mapfuel) the second line is instead

    y = map(n, T_true - T_fric) k_tr / ρ + [f_inj > 0] H e              on the fine grid [L/h]

the engine's fuel map at the instantaneous speed and flywheel torque, with transient fuelling, plus the fuel
noise H e (held over each Ts bin; none while the injection is cut, when the ECU reports exactly 0) of std
`TripConfig.noise` (default 0) with the spectrum of the paper's diesel noise model; the effects act on it as above,
then the ECU's LFE1 update (mean over each 0.1 s, held), then the delay. The drive, the bus torque (% of the
engine's largest full-load torque, EC1 SPN 544) and idle use that engine.

Noise floor (truth file, "noise_floor"): the same pipeline run once more without H e gives the noise-free fuel f0;

    floor = sqrt(mean_k (mean over bin k of (f_bus - f0))^2)              over every Ts bin of the trip [fuel unit]

is the part of the fuel signal, as the dataset's bin means see it, that no model of the bus signals can
explain: a model's RMS simulation error on the trip is at least about the floor. The per-bin differences are the
truth.npz array `fuel_noise_bin`, so that the floor can be taken over any subset of the bins (e.g. the valid ones).

Why bin means, held: the logger's dataset averages speed, torque and fuel over the same bins (ident.dataset), so
the truth is exactly a Box-Jenkins model of what the bus shows. A truth on point samples of the inputs, linearly
interpolated, differs from the bin means by a within-bin timing no discrete-time model represents; on trips with
nothing hidden every torque-like bus signal then "explained" the residual (p ~ 1e-200 in ident.diagnosis).

Randomness: one numpy SeedSequence per trip, one child stream per part (route, road, driver, weather, noise,
effects, gateway, meter), so switching an effect on leaves the route and the driving unchanged.
"""
import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fuelid.errors import InputError
from fuelid.sim import effects as fx
from fuelid.sim import fuel, gateway, mapfuel, meter, route, thermal, vecto
from fuelid.sim.drive import DRIVE, NEUTRAL, SHIFT, MODE_NAMES, simulate_drive
from fuelid.sim.engine import ENGINES
from fuelid.sim.files import open_binary, save_npz
from fuelid.sim.gearbox import GEAR_RATIOS
from fuelid.sim.vehicle import Truck, air_density_kg_m3

FORMAT_VERSION = 1
DIESEL_LHV_KJ_L, GAS_LHV_KJ_KG = 35800.0, 50000.0
RETARDER_REFERENCE_NM = 5000.0
"""Retarder reference torque at the propeller shaft (100 % in ERC1) [Nm]."""
MAP_TRUTH = "map"
MAP_NOISE_SPECTRUM = "diesel_p320"
"""The paper truth whose noise model H shapes the map truth's fuel noise (the residual paper 000 identified on a
real diesel truck)."""
"""The map-based engine truth (sim.mapfuel) on a VECTO engine set; the other truths are sim.fuel's paper models."""
TRUTH_NAMES = (*fuel.TRUTHS, MAP_TRUTH)
DEFAULT_MAP_ENGINE = "vecto_325kW"
STREAMS = ("route", "road", "driver", "weather", "noise", "effects", "gateway", "meter")


@dataclass(frozen=True)
class TripConfig:
    truth: str = "diesel_p320"
    cycle: str = "mixed"
    duration_s: float = 1800.0
    seed: int = 1
    effects: tuple = ()            # ((name, magnitude), ...)
    mass_kg: float = 40000.0
    ambient_c: float = 12.0        # ambient temperature at the start [°C]
    ambient_drift_c: float = 0.0   # change of ambient temperature over the trip [K]
    altitude_m: float = 60.0       # altitude at the start [m]
    hilliness: float = 1.0         # multiplies the cycle's grade standard deviation
    dt_s: float = 0.01             # simulation step [s]
    start_unix_s: float | None = None  # None: 2024-06-01 10:00 UTC plus `seed` days, so trips never overlap
    vin: str = ""                  # empty: derived from the seed
    engine: str = ""               # map truth: a VECTO .veng path or a shipped set's name (default vecto_325kW)
    noise: float | None = None     # std of the fuel noise H e [fuel unit]; None: the truth's own (map truth: 0)

    def __post_init__(self):
        if self.start_unix_s is None:  # frozen dataclass: set the derived default through object.__setattr__
            object.__setattr__(self, "start_unix_s", 1717236000.0 + 86400.0 * self.seed)
        if self.truth not in TRUTH_NAMES:
            raise InputError(f"unknown truth {self.truth!r}; known: {', '.join(TRUTH_NAMES)}")
        if self.truth == MAP_TRUTH and not self.engine:
            object.__setattr__(self, "engine", DEFAULT_MAP_ENGINE)
        if self.engine and self.truth != MAP_TRUTH:
            raise InputError(f"an engine set drives the map truth only (truth {MAP_TRUTH!r}), not {self.truth!r}")
        if self.cycle not in route.CYCLE_NAMES:
            raise InputError(f"unknown cycle {self.cycle!r}; known: {', '.join(route.CYCLE_NAMES)}")
        if not 60.0 <= self.duration_s <= 6 * 3600.0:
            raise InputError("duration must be between 60 s and 6 h")
        if not 30000.0 <= self.mass_kg <= 44000.0:
            raise InputError("mass must be between 30,000 and 44,000 kg")
        if self.truth == "gas_p340" and "dpf_regeneration" in dict(self.effects):
            raise InputError("the gas truck has no diesel particulate filter")
        if self.noise is not None and not 0.0 <= self.noise <= 10.0:
            raise InputError(f"fuel noise std must be between 0 and 10 (L/h or kg/h), got {self.noise:g}")
        if abs(fuel.TS_S / self.dt_s - round(fuel.TS_S / self.dt_s)) > 1e-9:
            raise InputError("the simulation step must divide Ts = 0.3 s")

    @property
    def diesel(self) -> bool:
        return self.truth == MAP_TRUTH or fuel.TRUTHS[self.truth].fuel == "diesel"

    @property
    def vehicle_id(self) -> str:
        return self.vin or f"YS2R4X2000{self.seed % 10}{1000000 + self.seed * 7919 % 1000000:07d}"[:17]


@dataclass
class Trip:
    config: TripConfig
    t_s: np.ndarray              # fine grid, from 0 [s]
    signals: dict                # fine-grid bus signals, keys as in gateway.fms_schedule
    truth: dict                  # Ts-grid truth arrays (the .truth.npz)
    summary: dict = field(default_factory=dict)
    meter: dict | None = None    # gas flow-meter readings


def _since_last(flags: np.ndarray) -> np.ndarray:
    """Index of the last sample where `flags` was True (or -1), per sample."""
    idx = np.where(flags, np.arange(len(flags)), -1)
    return np.maximum.accumulate(idx)


def _smooth(x: np.ndarray, dt: float, window_s: float) -> np.ndarray:
    k = max(1, int(window_s / dt))
    return np.convolve(x, np.ones(k) / k, mode="same")


def bin_means(x: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Mean of the fine-grid x over each Ts bin [starts[i], starts[i+1])."""
    return np.add.reduceat(x, starts) / np.diff(np.r_[starts, len(x)])


def simulate(cfg: TripConfig, progress=None) -> Trip:
    """Run the trip. `progress(step_name)` is called between stages, for a progress bar."""
    tick = progress or (lambda name: None)
    rng = dict(zip(STREAMS, (np.random.default_rng(s) for s in np.random.SeedSequence(cfg.seed).spawn(len(STREAMS)))))
    eff = dict(cfg.effects)
    vecto_engine = vecto.read_engine(cfg.engine) if cfg.truth == MAP_TRUTH else None
    truth = fuel.TRUTHS.get(cfg.truth)  # None for the map truth
    engine = mapfuel.sim_engine(vecto_engine) if vecto_engine else ENGINES[cfg.truth]
    truck = Truck(mass_kg=cfg.mass_kg)
    dt = cfg.dt_s
    n = int(round(cfg.duration_s / dt))
    t = np.arange(n) * dt

    tick("route")
    profile = route.speed_profile(cfg.cycle, cfg.duration_s, dt, rng["route"])
    road = route.road_profile(cfg.cycle, profile.v_ref.max() * cfg.duration_s * 1.2 + 2000.0, rng["road"],
                              cfg.altitude_m, cfg.hilliness)
    # Air density for the drive: altitude from where the target speed would take the truck.
    x_plan = np.minimum(np.cumsum(profile.v_ref) * dt, len(road.altitude_m) - 1).astype(int)
    ambient_plan = cfg.ambient_c + cfg.ambient_drift_c * t / t[-1]
    rho_plan = air_density_kg_m3(thermal.pressure_kpa(road.altitude_m[x_plan]), ambient_plan)

    tick("drive")
    d = simulate_drive(profile, road, truck, engine, rho_plan, dt, rng["driver"])
    rpm = d.engine_speed_rpm
    altitude = road.altitude_m[np.minimum(d.distance_m.astype(int), len(road.altitude_m) - 1)]

    tick("engine")
    ambient = thermal.ambient_temperature_c(t, altitude, cfg.ambient_c, cfg.ambient_drift_c, rng["weather"])
    pressure = thermal.pressure_kpa(altitude)
    rho = air_density_kg_m3(pressure, ambient)
    drag = engine.drag_torque_nm(rpm)
    full = engine.full_load_torque_nm(rpm)
    load = np.clip(d.brake_torque_nm / np.maximum(engine.max_brake_torque_nm(rpm), 1.0), 0.0, 1.25)
    fan_on = (thermal.fan_episodes(t, load, rng["effects"]) if "engine_fan" in eff else np.zeros(n, bool))
    fan_pct = thermal.fan_speed_pct(fan_on, rpm, dt)
    t_fan = (fx.fan_torque_nm(eff["engine_fan"], fan_pct, rpm) - fx.fan_torque_nm(eff["engine_fan"], 8.0, rpm)
             if "engine_fan" in eff else np.zeros(n))
    aux_on = fx.auxiliary_episodes(t, rng["effects"]) if "auxiliary_load" in eff else np.zeros(n, bool)
    t_aux = eff.get("auxiliary_load", 0.0) * aux_on
    t_true = np.maximum(0.0, d.brake_torque_nm + drag + t_fan + t_aux)
    t_shown = np.maximum(0.0, d.brake_torque_nm + drag)
    if "inertia" in eff:
        t_shown = t_shown - fx.inertia_torque_nm(eff["inertia"], rpm, dt)
    true_pct, shown_pct = engine.percent(t_true), engine.percent(t_shown)

    tick("fuel")
    step = int(round(fuel.TS_S / dt))
    k = np.arange(0, n, step)
    bin_of = np.arange(n) // step  # fine sample -> its Ts bin [k Ts, (k+1) Ts)
    rpm_bin, true_pct_bin = bin_means(rpm, k), bin_means(true_pct, k)
    if vecto_engine:  # flywheel torque from combustion: indicated minus friction (the motoring torque at zero)
        f_injected = mapfuel.injected_fuel_l_h(vecto_engine, rpm, t_true - engine.friction_torque_nm(rpm), dt)
        y_model = bin_means(f_injected, k)
        noise = (fuel.fuel_noise(fuel.TRUTHS[MAP_NOISE_SPECTRUM], len(k), rng["noise"], cfg.noise) if cfg.noise
                 else np.zeros(len(k)))
    else:
        y_model = fuel.deterministic_fuel(truth, rpm_bin, true_pct_bin)
        noise = fuel.fuel_noise(truth, len(k), rng["noise"], cfg.noise)
    lhv_kw = (DIESEL_LHV_KJ_L if cfg.diesel else GAS_LHV_KJ_KG) / 3600.0
    coolant = thermal.coolant_temperature_c(
        t, np.interp(t, t[k], y_model) * lhv_kw, ambient,
        ambient[0] if "cold_engine" in eff else thermal.THERMOSTAT_C - 1.0, fan_on)
    dpf_active = fx.dpf_events(t, rng["effects"]) if "dpf_regeneration" in eff else np.zeros(n, bool)
    shift_end = t[1:][(d.mode[:-1] == SHIFT) & (d.mode[1:] != SHIFT)]
    overrun = fx.overrun_mask(true_pct, d.pedal, rpm, d.mode == DRIVE)
    load_smooth = _smooth(load, dt, 30.0)
    inlet = ambient + 4.0 + 12.0 * load_smooth  # intake air after the charge-air cooler [°C]

    def engine_fuel(f):
        if "power_nonlinearity" in eff:
            f = f + fx.power_nonlinearity_add(eff["power_nonlinearity"], rpm, true_pct, engine.idle_speed_rpm)
        factors = {"dpf_regeneration": lambda m: fx.dpf_factor(m, dpf_active),
                   "cold_engine": lambda m: fx.cold_factor(m, coolant),
                   "gear_shift": lambda m: fx.shift_factor(m, t, shift_end),
                   "ambient": lambda m: fx.ambient_factor(m, rho),
                   "overrun_cutoff": lambda m: fx.overrun_factor(m, overrun),
                   "hot_intake_air": lambda m: fx.hot_intake_factor(m, inlet)}
        for name, factor in factors.items():
            if name in eff:
                f = f * factor(eff[name])
        f = np.maximum(f, 0.0)
        if vecto_engine:
            f = mapfuel.ecu_reported(f, dt)
        return fx.delayed(t, f, eff["fuel_delay"]) if "fuel_delay" in eff else f

    if vecto_engine:
        fuel_true = engine_fuel(f_injected)
        fuel_bus = engine_fuel(f_injected + noise[bin_of] * (f_injected > 0.0)) if noise.any() else fuel_true
    else:
        fuel_bus = engine_fuel((y_model + noise)[bin_of])
        fuel_true = engine_fuel(y_model[bin_of])

    tick("signals")
    speed_kmh = d.speed_m_s * 3.6
    stopped = d.speed_m_s <= 0.0
    standstill_s = (np.arange(n) - _since_last(~stopped)) * dt
    cruise_idx = _since_last(d.cruise)
    demand = np.clip(d.demand_torque_nm + drag, 0.0, None)
    fuel_l = fuel_bus if cfg.diesel else fuel_bus / truth.fuel_density_kg_l
    trip_fuel_l = np.cumsum(fuel_l) * dt / 3600.0
    signals = {
        "zero": 0.0,
        "torque_mode": np.select([(d.mode == NEUTRAL) & stopped, d.mode == SHIFT, d.cruise, d.pedal <= 0.0],
                                 [0, 6, 2, 0], 1),
        "driver_demand_pct": engine.percent(demand),
        "engine_demand_pct": np.where(d.mode == SHIFT, shown_pct, engine.percent(np.minimum(demand, full))),
        "torque_reported_pct": shown_pct,
        "engine_speed_rpm": rpm,
        "low_idle_switch": (d.pedal < 0.005).astype(float),
        "pedal_pct": 100.0 * d.pedal,
        "load_pct": 100.0 * load,
        "friction_pct": engine.percent(engine.friction_torque_nm(rpm)),
        "desired_speed_rpm": np.where(d.mode == NEUTRAL, engine.idle_speed_rpm, rpm),
        "aux_pct": engine.percent(engine.aux_nm + t_aux),
        "fuel_rate_l_h": fuel_bus,
        "economy_km_l": np.where(stopped, 0.0, speed_kmh / np.maximum(fuel_bus, 1e-3)),
        "throttle_pct": np.clip(100.0 * t_true / np.maximum(full, 1.0), 0.0, 100.0),
        "park_brake": (stopped & (standstill_s > 20.0)).astype(float),
        "speed_kmh": speed_kmh,
        "cruise_active": d.cruise.astype(float),
        "brake_switch": (d.service_brake_n > 1.0).astype(float),
        "clutch_switch": ((d.gear == 0) | (d.mode == 1)).astype(float),
        "cruise_set_kmh": np.where(cruise_idx >= 0, np.round(profile.v_ref[np.maximum(cruise_idx, 0)] * 3.6),
                                   np.nan),
        "selected_gear": d.selected_gear.astype(float),
        "current_gear": d.gear.astype(float),
        "gear_ratio": np.where(d.gear > 0, np.asarray((np.nan,) + GEAR_RATIOS)[d.gear], np.nan),
        "retarder_mode": (d.retarder_n > 0).astype(float),
        "retarder_pct": -100.0 * d.retarder_n * truck.wheel_radius_m / truck.final_drive / RETARDER_REFERENCE_NM,
        "pressure_kpa": pressure,
        "cab_c": 21.0 + 0.3 * np.sin(2 * np.pi * t / 900.0),
        "ambient_c": ambient,
        "inlet_c": inlet,
        "coolant_c": coolant,
        "fuel_temp_c": ambient + (8.0 if "cold_engine" in eff else 20.0) + 15.0 * (1 - np.exp(-t / 2400.0)),
        "oil_c": coolant + 3.0 + 6.0 * load_smooth,
        "trip_fuel_l": trip_fuel_l,
        "total_fuel_l": 184532.0 + 1000.0 * (cfg.seed % 97) + trip_fuel_l,
        "fan_pct": fan_pct,
        "fan_state": np.where(fan_on, 4.0, 0.0),
        "dpf_active": dpf_active.astype(float),
    }

    truth_arrays = {
        "t_s": t[k], "speed_kmh": speed_kmh[k], "engine_speed_rpm": rpm[k], "torque_true_pct": true_pct[k],
        "engine_speed_bin_rpm": rpm_bin, "torque_true_bin_pct": true_pct_bin,
        "torque_reported_pct": shown_pct[k], "fuel_model": y_model, "noise": noise, "fuel_true": fuel_true[k],
        "fuel_noise_bin": bin_means(fuel_bus - fuel_true, k),
        "fuel_measured": fuel_bus[k], "pedal_pct": 100.0 * d.pedal[k], "gear": d.gear[k], "mode": d.mode[k],
        "air_density_kg_m3": rho[k], "coolant_c": coolant[k], "fan_pct": fan_pct[k],
        "dpf_active": dpf_active[k], "overrun": overrun[k],
    }
    # the generic effects' driving signals, only on trips that have them (the other trips' files stay as they were)
    if "hot_intake_air" in eff:
        truth_arrays["inlet_c"] = inlet[k]
    if "auxiliary_load" in eff:
        truth_arrays["auxiliary_torque_nm"] = t_aux[k]
    trip = Trip(cfg, t, signals, truth_arrays)
    if not cfg.diesel:
        tick("meter")
        trip.meter = meter.readings(t, fuel_bus, cfg.start_unix_s, rng["meter"])
    trip.summary = summarise(trip, profile, engine, truck, d, altitude, vecto_engine)
    return trip


def summarise(trip: Trip, profile, engine, truck, d, altitude, vecto_engine=None) -> dict:
    """The truth file's description of the trip (no time series)."""
    cfg, tr = trip.config, trip.truth
    truth = fuel.TRUTHS.get(cfg.truth)
    fuel_unit = truth.fuel_unit if truth else "L/h"
    config = {**dataclasses.asdict(cfg), "effects": dict(cfg.effects), "vin": cfg.vehicle_id}
    if not vecto_engine:
        config.pop("engine")  # the paper truths' files stay as they were before engine sets existed
    if cfg.noise is None:
        config.pop("noise")
    idle = (tr["mode"] == NEUTRAL) & (tr["speed_kmh"] == 0)
    dt = cfg.dt_s
    return {
        "format_version": FORMAT_VERSION,
        "generator": "fuelid simulate (sim/)",
        "seed": cfg.seed,
        "config": config,
        "start_unix_s": cfg.start_unix_s,
        "vin": cfg.vehicle_id,
        "truck": {**dataclasses.asdict(truck), "fuel": truth.fuel if truth else "diesel"},
        "engine": {"name": engine.name, "reference_torque_nm": engine.reference_torque_nm,
                   "idle_speed_rpm": engine.idle_speed_rpm, "inertia_kgm2": engine.inertia_kgm2,
                   "full_load_rpm": list(engine.full_load_rpm), "full_load_nm": list(engine.full_load_nm)},
        "gearbox": {"ratios": list(GEAR_RATIOS), "shifts": int(np.sum(np.diff(d.selected_gear) != 0))},
        "route": {"cycle": cfg.cycle, "blocks": list(profile.blocks), "duration_s": cfg.duration_s,
                  "distance_km": round(float(d.distance_m[-1]) / 1000.0, 3),
                  "altitude_m": [round(float(altitude.min()), 1), round(float(altitude.max()), 1)],
                  "mean_speed_kmh": round(float(tr["speed_kmh"].mean()), 2),
                  "idle_share": round(float(idle.mean()), 4),
                  "time_in_mode_s": {m: round(float(np.sum(d.mode == i)) * dt, 1) for i, m in enumerate(MODE_NAMES)}},
        "fuel_truth": fuel.describe(truth, cfg.noise) if truth else describe_map_truth(vecto_engine, cfg.noise),
        "effects": fx.describe(dict(cfg.effects)),
        "noise_floor": noise_floor(tr["fuel_noise_bin"], fuel_unit, cfg.diesel),
        "fuel": {"unit": fuel_unit,
                 "mean": round(float(tr["fuel_measured"].mean()), 3),
                 "mean_true": round(float(tr["fuel_true"].mean()), 3),
                 "idle_mean_true": round(float(tr["fuel_true"][idle].mean()), 3) if idle.any() else None,
                 "total": round(float(np.sum(tr["fuel_measured"]) * fuel.TS_S / 3600.0), 3),
                 "bus": "LFE1.EngFuelRate (SPN 183), LFC1/HRLFC totals" if cfg.diesel
                        else "flow meter capture (.flow.gz); LFE1 has no fuel rate (N/A), as on the paper's "
                             "gas truck"},
        "truth_npz": {"ts_s": fuel.TS_S, "arrays": sorted(tr),
                      "note": MAP_NPZ_NOTE if vecto_engine else PAPER_NPZ_NOTE},
    }


def noise_floor(noise_bin: np.ndarray, unit: str, diesel: bool) -> dict:
    """The truth-file entry of the noise floor: the RMS of the per-bin fuel noise (module docstring)."""
    return {"rms": round(float(np.sqrt(np.mean(noise_bin ** 2))), 6), "unit": unit,
            "definition": "RMS over every Ts bin of the trip of (bin mean of the fuel the bus reports - bin mean "
                          "of the same fuel without the noise H e), before "
                          + ("LFE1's 0.05 L/h quantisation (under 0.015 L/h RMS)" if diesel
                             else "the flow meter's own error (flow_meter)")
                          + "; per bin: truth.npz fuel_noise_bin. No model of the bus signals explains it: a "
                          "model's RMS simulation error on this trip is at least about this"}


PAPER_NPZ_NOTE = ("fuel_model = operating point + Gw W + GT T on the means of the true inputs over "
                  "each bin [t_s, t_s + Ts) (engine_speed_bin_rpm, torque_true_bin_pct; no noise, no "
                  "effects); fuel_true = fuel_model through the "
                  "effects (noise-free truth as the bus reports it, before quantisation); "
                  "fuel_measured = the same with the noise H e; these three and every other array "
                  "sampled at t_s from trip start; fuel_noise_bin = mean of (measured - true) over each bin")
MAP_NPZ_NOTE = ("fuel_model = the map engine's injected fuel (steady-state map at the instantaneous speed and "
                "flywheel torque, times the transient factor) averaged over each bin [t_s, t_s + Ts), no effects; "
                "noise = the fuel noise H e per bin (0 without --noise; added only while fuel is injected); "
                "fuel_true = the injected fuel through the effects and the ECU's LFE1 update, fuel_measured = "
                "the same with the noise, both sampled at t_s (before quantisation); fuel_noise_bin = mean of "
                "(measured - true) over each bin")


def describe_map_truth(vecto_engine, noise: float | None = None) -> dict:
    """The truth-file entry of the map truth."""
    return {"name": MAP_TRUTH, "engine": vecto.describe(vecto_engine),
            "structure": "f = map(n, T_brake + T_aux + T_fan) x k_tr / rho + [f > 0] H e, 0 at or below the "
                         "motoring torque; k_tr = 1 + c_max r/(r + T_max), r = lagged rate of torque increase "
                         "[Nm/s]; LFE1 = mean over each 0.1 s ECU update, held",
            "transient": {"c_max": round(2.0 * max(0.0, vecto_engine.whtc["urban"] - 1.0), 6),
                          "tau_s": mapfuel.TRANSIENT_TAU_S},
            "noise": {"std": noise or 0.0, "spectrum": f"H = C/D of {MAP_NOISE_SPECTRUM} (its H_simulated)",
                      "held_over_s": fuel.TS_S},
            "fuel_density_kg_l": vecto_engine.fuel_density_kg_l, "ecu_update_s": mapfuel.LFE1_UPDATE_S,
            "output": {"unit": "L/h", "signal": "LFE1.EngFuelRate (SPN 183)"},
            "inputs": {"W": {"signal": "EEC1.EngSpeed", "spn": 190, "unit": "rpm"},
                       "T": {"signal": "EEC1.ActualEngPercentTorque", "spn": 513, "unit": "%",
                             "reference_torque_nm": vecto_engine.max_torque_nm}}}


def output_paths(log_path: Path) -> dict:
    """x.log(.gz) -> the trip's files: log, flow capture, truth json and npz."""
    log_path = Path(log_path)
    name = log_path.name
    for suffix in (".log.gz", ".log"):
        if name.endswith(suffix):
            stem = name[: -len(suffix)]
            break
    else:
        raise InputError(f"output must end in .log or .log.gz: {log_path}")
    gz = name.endswith(".gz")
    d = log_path.parent
    return {"log": log_path, "flow": d / (stem + (".flow.gz" if gz else ".flow")),
            "truth_json": d / (stem + ".truth.json"), "truth_npz": d / (stem + ".truth.npz")}


def write(trip: Trip, log_path: Path, progress=None) -> dict:
    """Write the trip's files next to `log_path`; returns {kind: path} and adds frame counts to the summary."""
    tick = progress or (lambda name: None)
    cfg = trip.config
    paths = output_paths(log_path)
    paths["log"].parent.mkdir(parents=True, exist_ok=True)
    tick("frames")
    engine = trip.summary["engine"]
    ec1 = {"EngSpeedAtIdlePoint1": engine["idle_speed_rpm"], "EngReferenceTorque": engine["reference_torque_nm"],
           "EngMomentOfInertia": engine["inertia_kgm2"]}
    rng = np.random.default_rng(np.random.SeedSequence(cfg.seed).spawn(len(STREAMS))[STREAMS.index("gateway")])
    db = gateway.load_dbc()
    blocks = gateway.fms_frames(db, trip.signals, cfg.diesel, cfg.start_unix_s, cfg.duration_s, cfg.dt_s, rng,
                                ec1, cfg.vehicle_id)
    t, ids, data = gateway.merge(blocks)
    tick("log")
    with open_binary(paths["log"]) as f:
        f.write(gateway.candump_lines(t, ids, data).encode("ascii"))
    files = {"log": paths["log"].name}
    if trip.meter is not None:
        meter.write_capture(paths["flow"], trip.meter)
        files["flow"] = paths["flow"].name
        trip.summary["flow_meter"] = {
            "rate_hz": meter.RATE_HZ, "full_scale_kg_h": meter.FULL_SCALE_KG_H,
            "gain_kg_h_per_v": meter.GAIN_KG_H_PER_V, "gain_error": round(trip.meter["gain_error"], 6),
            "offset_error_kg_h": round(trip.meter["offset_error_kg_h"], 6),
            "readings": int(len(trip.meter["volts"])), "garbled_lines": int(trip.meter["garbled"].sum())}
    else:
        paths.pop("flow")
    files.update(truth_json=paths["truth_json"].name, truth_npz=paths["truth_npz"].name)
    trip.summary["files"] = files
    trip.summary["frames"] = {
        "total": int(len(t)),
        "per_message": {f"{b.name}@0x{(b.can_id if b.can_id >= 0 else 0) & 0xFF:02X}": int(len(b.t)) for b in blocks},
        "not_available": {f"{b.name}.{s}": int(np.isnan(v).sum()) for b in blocks for s, v in b.values.items()
                          if s in gateway.NA_SIGNALS.get(b.name, ())},
    }
    tick("truth")
    paths["truth_json"].write_text(json.dumps(trip.summary, indent=1, default=float) + "\n")
    save_npz(paths["truth_npz"], {k: np.asarray(v, np.float32) for k, v in trip.truth.items()})
    return paths
