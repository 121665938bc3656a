"""The shipped replay logs: one TripConfig per file in replay_logs/, each reproducible by one command.

Identification and validation trips after the seed paper (1.5 h identification, a different validation trip),
a gas-truck pair with flow-meter captures, eleven 30-minute diesel drive cycles like the paper's Table I, one
trip per physical effect (three for ambient air), and a one-minute sample for the README's quick start; the
identification, validation and effect trips again on the map engine (VECTO's 325 kW engine).
"""
from dataclasses import replace

from fuelid.errors import InputError
from fuelid.sim.effects import ALL_EFFECTS
from fuelid.sim.trip import TripConfig

CYCLE_ROTATION = ("urban", "rural", "motorway", "mixed")

# Where each effect shows best: hills for the fan and overrun, stop-and-go for inertia and shifts, a cold
# morning for the cold engine. Air density differs between days and places far more than within a 20-minute
# trip, so the ambient effect takes trips identified together: a winter morning in the lowlands (200 m, -2 °C),
# a summer afternoon in the mountains (1400 m, 30 °C), air 23 % thinner, and a spring day in the hills (700 m,
# 12 °C). Three, so that whichever is left out to check that the effect carries over (ident.diagnosis,
# leave-one-trip-out), the other two still differ in their weather.
EFFECT_TRIPS = {
    "fuel_delay": (dict(cycle="mixed"),),
    "inertia": (dict(cycle="urban"),),
    "overrun_cutoff": (dict(cycle="rural", hilliness=1.8),),
    "power_nonlinearity": (dict(cycle="mixed"),),
    "dpf_regeneration": (dict(cycle="mixed"),),
    "cold_engine": (dict(cycle="mixed", ambient_c=2.0),),
    "engine_fan": (dict(cycle="rural", hilliness=1.8, ambient_c=28.0),),
    "gear_shift": (dict(cycle="urban"),),
    "ambient": (dict(cycle="rural", hilliness=1.5, altitude_m=200.0, ambient_c=-2.0),
                dict(cycle="rural", hilliness=1.5, altitude_m=1400.0, ambient_c=30.0),
                dict(cycle="rural", hilliness=1.5, altitude_m=700.0, ambient_c=12.0)),
}
"""Per hidden effect, the routes and weather of the trip(s) that show it (TripConfig fields)."""
# The generic effects (sim.effects.GENERIC_EFFECTS, no entry in fuelid's effect catalogue): hot intake air on a
# hot, hilly day (the intake air 29-41 °C, above 30 °C on the climbs); the auxiliary load on mixed driving.
GENERIC_EFFECT_TRIPS = {
    "hot_intake_air": (dict(cycle="rural", hilliness=1.8, ambient_c=25.0),),
    "auxiliary_load": (dict(cycle="mixed"),),
}
"""Per generic hidden effect, the routes and weather of its trip; made on demand (`--catalog generic_NAME_20min`),
not shipped."""
ALL_EFFECT_TRIPS = {**EFFECT_TRIPS, **GENERIC_EFFECT_TRIPS}
SECOND_TRIP_SEED = 100
"""The k-th trip (k = 0, 1, …) of an effect's set has seed `seed + k * SECOND_TRIP_SEED`: another day."""


def _entries() -> dict:
    c = {
        "sample_diesel_1min": TripConfig(cycle="urban", duration_s=60.0, seed=7),
        "diesel_ident_90min": TripConfig(cycle="mixed", duration_s=5400.0, seed=101, mass_kg=40000.0),
        "diesel_valid_40min": TripConfig(cycle="mixed", duration_s=2400.0, seed=202, mass_kg=42000.0),
        "gas_ident_60min": TripConfig(truth="gas_p340", cycle="mixed", duration_s=3600.0, seed=301, mass_kg=40000.0),
        "gas_valid_30min": TripConfig(truth="gas_p340", cycle="mixed", duration_s=1800.0, seed=402, mass_kg=41000.0),
    }
    for k in range(1, 12):
        c[f"diesel_cycle_{k:02d}"] = TripConfig(cycle=CYCLE_ROTATION[(k - 1) % 4], duration_s=1800.0,
                                                seed=1000 + k, mass_kg=40000.0 + 400.0 * (k - 1))
    # The same routes, days and loads on the map engine (VECTO's 325 kW engine, sim.mapfuel): the paper's set on
    # an engine outside the Box-Jenkins model class.
    c["map_ident_90min"] = TripConfig(truth="map", cycle="mixed", duration_s=5400.0, seed=101, mass_kg=40000.0)
    c["map_valid_40min"] = TripConfig(truth="map", cycle="mixed", duration_s=2400.0, seed=202, mass_kg=42000.0)
    for k in range(1, 12):
        c[f"map_cycle_{k:02d}"] = TripConfig(truth="map", cycle=CYCLE_ROTATION[(k - 1) % 4], duration_s=1800.0,
                                             seed=1000 + k, mass_kg=40000.0 + 400.0 * (k - 1))
    # Other days of the same truck (seed paper 000 builds its baseline map from a week of operations): five
    # 1-hour days for the map engine's baseline map, none of them a trip it is scored on.
    for k in range(1, 6):
        c[f"map_day_{k}"] = TripConfig(truth="map", cycle=CYCLE_ROTATION[k % 4], duration_s=3600.0, seed=5000 + k,
                                       mass_kg=38000.0 + 1000.0 * k)
    for k, (name, trips) in enumerate(ALL_EFFECT_TRIPS.items()):
        for j, extra in enumerate(trips):
            kind = "generic" if name in GENERIC_EFFECT_TRIPS else "effect"
            label = f"{kind}_{name}_20min" + (f"_{j + 1}" if len(trips) > 1 else "")
            c[label] = TripConfig(duration_s=1200.0, seed=2000 + k + j * SECOND_TRIP_SEED,
                                  effects=((name, ALL_EFFECTS[name].default),), **extra)
            if kind == "effect":  # the same trip on the map engine: the hidden effect on top of a real map
                c[f"map_{label}"] = replace(c[label], truth="map")
    return c


CATALOG = _entries()
SHIPPED = tuple(n for n in CATALOG if not n.startswith(("map_cycle_", "map_day_", "generic_")))
"""The entries whose files are in replay_logs/ (`fuelid simulate --all`); the map engine's eleven cycles (17 MB),
five days for its baseline map (about 15 MB) and the generic effects' trips are made on demand by
`--catalog map_cycle_NN` / `map_day_N` / `generic_NAME_20min`."""
DEFAULT = TripConfig()


def on_engine(cfg: TripConfig, engine: str = "", noise: float | None = None) -> TripConfig:
    """`cfg` on another engine (the map truth on a VECTO set: a .veng path or a shipped set's name) and/or with
    another fuel noise std; unchanged when neither is given. The gas truck's trips have no engine set (InputError)."""
    if engine:
        if not cfg.diesel:
            raise InputError("the gas truck's trips run on the paper's gas model; an engine set is a diesel map")
        cfg = replace(cfg, truth="map", engine=engine)
    return cfg if noise is None else replace(cfg, noise=noise)


def validation_pair(seed: int, truth: str = "map", engine: str = "", noise: float | None = None,
                    ident_s: float = 3600.0, valid_s: float = 1800.0) -> tuple[TripConfig, TripConfig]:
    """An identification trip and a validation trip of another day of the same truck: mixed driving, the second
    on day `seed + SECOND_TRIP_SEED` (another route, driver and weather stream) with 2 t more load, as the shipped
    diesel_ident_90min / diesel_valid_40min pair."""
    ident = TripConfig(truth=truth, engine=engine, noise=noise, cycle="mixed", duration_s=ident_s, seed=seed,
                       mass_kg=40000.0)
    return ident, replace(ident, duration_s=valid_s, seed=seed + SECOND_TRIP_SEED, mass_kg=42000.0,
                          start_unix_s=None, vin=ident.vehicle_id)  # its own day's start, the same truck's VIN


def command_line(name: str) -> str:
    """The explicit `fuelid simulate` command that makes catalog entry `name` (flags that differ from the
    defaults only)."""
    cfg = CATALOG[name]
    flags = {"truth": "--truth", "cycle": "--cycle", "duration_s": "--duration", "seed": "--seed",
             "mass_kg": "--mass", "ambient_c": "--ambient", "ambient_drift_c": "--ambient-drift",
             "altitude_m": "--altitude", "hilliness": "--hilliness", "engine": "--engine", "noise": "--noise"}
    parts = ["fuelid simulate"]
    for field, flag in flags.items():
        value = getattr(cfg, field)
        if field in ("truth", "cycle", "duration_s", "seed") or value != getattr(DEFAULT, field):
            parts.append(f"{flag} {value:g}" if isinstance(value, float) else f"{flag} {value}")
    parts += [f"--effect {n}={m:g}" for n, m in cfg.effects]
    parts.append(f"-o replay_logs/{name}.log.gz")
    return " ".join(parts)
