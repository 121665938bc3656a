"""Routes: the driver's target speed over time (urban, rural, motorway cycles with stops) and the road's
grade and altitude over distance.

A cycle is a sequence of legs: accelerate to a cruise speed, hold it, then either stop (and idle) or slow down
for a junction. Speeds, hold times and stop frequency are drawn from the cycle's ranges. A "mixed" trip chains
urban, rural and motorway blocks like a distribution run.
"""
from dataclasses import dataclass

import numpy as np
from scipy import signal

KMH = 1.0 / 3.6


@dataclass(frozen=True)
class Cycle:
    speed_kmh: tuple        # cruise speed range [km/h]
    hold_s: tuple           # time at cruise speed per leg [s]
    stop_probability: float  # chance that a leg ends in a stop
    dwell_s: tuple          # standstill per stop [s]
    slow_kmh: tuple         # speed of a junction slow-down that is not a stop [km/h]
    accel_m_s2: float       # driver's target acceleration [m/s²]
    decel_m_s2: float       # driver's target deceleration [m/s²]
    grade_std: float        # road grade standard deviation [-] (0.01 = 1 %)
    hill_length_m: float    # correlation length of the road profile [m]


CYCLES = {
    "urban": Cycle((25, 50), (15, 70), 0.55, (8, 45), (10, 25), 0.45, 0.8, 0.012, 250.0),
    "rural": Cycle((55, 80), (60, 300), 0.12, (10, 40), (25, 45), 0.40, 0.7, 0.018, 500.0),
    "motorway": Cycle((80, 89), (200, 700), 0.02, (20, 60), (55, 70), 0.35, 0.5, 0.012, 900.0),
}
MIXED_BLOCKS = ("urban", "rural", "motorway", "rural", "urban")
MIXED_SHARES = (0.12, 0.2, 0.4, 0.16, 0.12)
CYCLE_NAMES = (*CYCLES, "mixed")

START_IDLE_S = 60.0
END_IDLE_S = 45.0


@dataclass
class SpeedProfile:
    """Target speed on the simulation grid. v_ref [m/s], a_ref [m/s²] (its slope), cruise (bool: a steady
    leg above 60 km/h where the driver uses cruise control), block: index into `blocks` per sample."""

    v_ref: np.ndarray
    a_ref: np.ndarray
    cruise: np.ndarray
    block: np.ndarray
    blocks: tuple


def _ramp(v0: float, v1: float, rate: float, dt: float) -> np.ndarray:
    """Samples of a constant-rate change from v0 to v1 [m/s] at `rate` [m/s²], v0 excluded."""
    n = max(1, int(np.ceil(abs(v1 - v0) / rate / dt)))
    return np.linspace(v0, v1, n + 1)[1:]


def _block_legs(cycle: Cycle, duration_s: float, dt: float, rng: np.random.Generator, v_start: float):
    """Target speeds [m/s] and cruise flags of one cycle block lasting about duration_s."""
    pieces, flags, t, v = [], [], 0.0, v_start
    while t < duration_s:
        v_cruise = rng.uniform(*cycle.speed_kmh) * KMH
        up = _ramp(v, v_cruise, cycle.accel_m_s2 if v_cruise > v else cycle.decel_m_s2, dt)
        hold = np.full(int(rng.uniform(*cycle.hold_s) / dt), v_cruise)
        if rng.random() < cycle.stop_probability:
            end = np.concatenate([_ramp(v_cruise, 0.0, cycle.decel_m_s2, dt),
                                  np.zeros(int(rng.uniform(*cycle.dwell_s) / dt))])
            v = 0.0
        else:
            v = rng.uniform(*cycle.slow_kmh) * KMH
            end = _ramp(v_cruise, v, cycle.decel_m_s2, dt)
        pieces += [up, hold, end]
        flags += [np.zeros(len(up), bool), np.full(len(hold), v_cruise > 60 * KMH and len(hold) * dt > 60),
                  np.zeros(len(end), bool)]
        t += (len(up) + len(hold) + len(end)) * dt
    return pieces, flags, v


def speed_profile(cycle: str, duration_s: float, dt: float, rng: np.random.Generator) -> SpeedProfile:
    """The driver's target speed for a trip of `duration_s` [s]: idle (60 s, at most 10 % of the trip), the
    cycle's legs, a final stop and idle (45 s, at most 8 %). Cut to exactly duration_s; it ends at rest."""
    names = MIXED_BLOCKS if cycle == "mixed" else (cycle,)
    shares = MIXED_SHARES if cycle == "mixed" else (1.0,)
    start_idle_s, end_idle_s = min(START_IDLE_S, 0.1 * duration_s), min(END_IDLE_S, 0.08 * duration_s)
    drive_s = duration_s - start_idle_s - end_idle_s
    pieces, flags, blocks = [np.zeros(int(start_idle_s / dt))], [np.zeros(int(start_idle_s / dt), bool)], []
    block_ids = [np.zeros(int(start_idle_s / dt), np.int8)]
    v = 0.0
    for k, (name, share) in enumerate(zip(names, shares)):
        p, f, v = _block_legs(CYCLES[name], share * drive_s, dt, rng, v)
        pieces += p
        flags += f
        block_ids.append(np.full(sum(len(x) for x in p), k, np.int8))
        blocks += [name]
    v_ref = np.concatenate(pieces)
    cruise = np.concatenate(flags)
    block = np.concatenate(block_ids)
    n = int(round(duration_s / dt))
    # Make room for the final stop and idle: cut the drive, then brake to rest at the last cycle's rate.
    stop = _ramp(v_ref[min(len(v_ref), n) - 1], 0.0, CYCLES[names[-1]].decel_m_s2, dt)
    keep = max(0, n - len(stop) - int(end_idle_s / dt))
    v_ref = np.concatenate([v_ref[:keep], stop, np.zeros(n)])[:n]
    cruise = np.concatenate([cruise[:keep], np.zeros(n, bool)])[:n]
    block = np.concatenate([block[:keep], np.full(n, len(names) - 1, np.int8)])[:n]
    a_ref = np.gradient(v_ref, dt)
    return SpeedProfile(v_ref, a_ref, cruise, block, tuple(blocks))


@dataclass
class RoadProfile:
    """The road over distance on a 1 m grid: grade α [rad] and altitude [m] at x = 0, 1, 2, ... m."""

    grade_rad: np.ndarray
    altitude_m: np.ndarray


def road_profile(cycle: str, length_m: float, rng: np.random.Generator, altitude_start_m: float = 60.0,
                 hilliness: float = 1.0) -> RoadProfile:
    """Smooth random hills: white noise on a 10 m grid, low-pass filtered over the cycle's hill length,
    scaled to its grade standard deviation (x hilliness) and clipped to ±6 %."""
    c = CYCLES["rural" if cycle == "mixed" else cycle]
    step_m = 10.0
    n = int(length_m / step_m) + 2
    # Second-order low-pass: a road profile has no steps in grade.
    b, a = signal.butter(2, step_m / c.hill_length_m)
    lead = int(5 * c.hill_length_m / step_m)
    g = signal.lfilter(b, a, rng.normal(size=n + lead))[lead:]
    g = np.clip(g / g.std() * c.grade_std * hilliness, -0.06, 0.06)
    x = np.arange(int(length_m) + 1)
    grade = np.arctan(np.interp(x, np.arange(n) * step_m, g))
    altitude = altitude_start_m + np.concatenate([[0.0], np.cumsum(np.sin(grade[:-1]))])
    return RoadProfile(grade, altitude)
