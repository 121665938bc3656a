"""Synthetic datasets with a known Box-Jenkins fuel model and optionally hidden physical effects
(tests of ident.effects and ident.diagnosis).

Truth: y = y0 + Gn ñ + GT T̃ + C/D e at Ts = 0.3 s, ñ [rpm] and T̃ [Nm] deviations from idle (600 rpm,
112 Nm), Gn = 0.0019 q⁻² (1 − 0.5)/(1 − 0.5 q⁻¹) [L/h per rpm], GT = 0.03 (0.6 + 0.4 q⁻¹)/(1 − 0.2 q⁻¹)·0.8
[L/h per Nm] (steady gains 0.0019 and 0.03), noise C/D = (1 + 0.3 q⁻¹)/(1 − 0.6 q⁻¹) with std ≈ 0.5 L/h.
The bus extras are those a real FMS gateway sends (DBC names), plus unknown signals (random walks) that
should never be flagged. Hidden effects:

- "dpf_regeneration": fuel +11 % while DPFC1.DPFActiveRegenStatus = 1 (two 4-minute regenerations);
- "inertia": the bus torque is net of J dω/dt (J = 3.2 kg·m², EC1 SPN 1794), fuel follows the indicated one;
- "cold_engine": +0.04 L/h per K of coolant below 80 °C (a cold start warming up);
- "fuel_delay": the fuel signal lags by `delay_s` (fractional, spline-interpolated);
- "unlisted": +1.5 L/h while XX.UnknownState = 2 (an auxiliary load no built-in effect describes).

`simulated` gives the same from the truck simulator (fuelid/sim/) through the bus and fuelid's own decoder, with the
simulator's truth, for the acceptance tests of issue 7 (tests/ident/diagnosis/test_hidden_effects.py).
"""
from __future__ import annotations

import dataclasses
import functools
import tempfile
import warnings
from pathlib import Path

import numpy as np
from scipy.ndimage import shift as spline_shift
from scipy.signal import lfilter

from fuelid.ident.dataset import Dataset
from fuelid.ident.diagnosis.settings import Settings
from fuelid.ident.diagnosis.yardstick import held_out_summary, make_folds, refits
from fuelid.ident.identify import effect_definitions, effect_inputs
from fuelid.ident.pem import pem
from fuelid.ident.polymodel import PolyModel, Structure

TS = 0.3
J = 3.2  # kg·m²
TRUE = PolyModel(A=[1.0], B=[[0, 0, 0.0019 * 0.5], [0.03 * 0.8 * 0.6, 0.03 * 0.8 * 0.4]],
                 F=[[1, -0.5], [1, -0.2]], C=[1, 0.3], D=[1, -0.6], Ts=TS, nk=(2, 0),
                 u0=(600.0, 112.0), y0=2.5)
STRUCTURE = Structure(nb=(1, 2), nf=(1, 1), nk=(2, 0), nc=1, nd=1)


def _lag(x, tau):
    a = np.exp(-TS / tau)
    return lfilter([1 - a], [1, -a], x, zi=[a * x[0]])[0]


def _held(n, rng, lo, hi, hold=(3.0, 40.0)):
    out = np.empty(n)
    i = 0
    while i < n:
        k = int(rng.uniform(*hold) / TS)
        out[i:i + k] = rng.uniform(lo, hi)
        i += k
    return out


def make(effect: str | tuple[str, ...] | None = None, n: int = 8000, seed: int = 0, noise: float = 0.5,
         size: float | None = None, delay_s: float = 0.4) -> Dataset:
    """A Dataset of n samples (n·0.3 s) with the hidden `effect` (module docstring) of magnitude `size`; a tuple
    of ids hides them all (each of its default magnitude)."""
    hidden = set(effect) if isinstance(effect, tuple) else {effect}
    size = None if len(hidden) > 1 else size
    rng = np.random.default_rng(seed)
    speed = np.clip(600 + _lag(_held(n, rng, 0, 1300), 2.0) + _lag(rng.normal(0, 30, n), 1.0), 550, 2000)
    torque = np.clip(112 + _lag(_held(n, rng, -100, 1500), 0.6) + _lag(rng.normal(0, 60, n), 0.5), -150, 1700)
    domega = np.gradient(speed * 2 * np.pi / 60, TS)
    t = np.arange(n) * TS
    regen = np.zeros(n)
    for start in (0.2, 0.65):
        a = int(start * n)
        regen[a:a + int(240 / TS)] = 1.0
    coolant = 85 + 3 * np.sin(2 * np.pi * t / 900)
    if "cold_engine" in hidden:
        coolant = 85 - 60 * np.exp(-t / 600)
    indicated = torque + (J * domega if "inertia" in hidden else 0.0)
    clean = TRUE.y0 + lfilter(TRUE.B[0], TRUE.F[0], speed - 600) + lfilter(TRUE.B[1], TRUE.F[1], indicated - 112)
    if "dpf_regeneration" in hidden:
        clean = clean * (1 + (0.11 if size is None else size) * regen)
    if "cold_engine" in hidden:
        clean = clean + (0.04 if size is None else size) * np.maximum(80 - coolant, 0)
    e = rng.normal(0, noise / 1.3, n)
    y = clean + lfilter(TRUE.C, TRUE.D, e)
    if "fuel_delay" in hidden:
        y = spline_shift(y, delay_s / TS, order=3, mode="nearest")
    walk = lambda s: np.cumsum(rng.normal(0, s, n))  # noqa: E731
    extra = {
        "CCVS1.WheelBasedVehicleSpeed": np.clip((speed - 600) / 15, 0, 90),
        "EEC2.AccelPedalPos1": np.clip(torque / 16, 0, 100),
        "ETC2.TransCurrentGear": np.floor(_held(n, rng, 1, 12, (5, 60))),
        "DPFC1.DPFActiveRegenStatus": regen,
        "ET1.EngCoolantTemp": np.round(coolant),
        "ET1.EngOilTemp1": np.round(coolant + 5 + walk(0.02), 1),
        "AMB.AmbientAirTemp": 18 + walk(0.002),
        "AMB.BarometricPress": np.full(n, 99.0),
        "EC1.EngMomentOfInertia": np.full(n, J),
        "EC1.EngReferenceTorque": np.full(n, 1600.0),
        "FD.EstPercentFanSpeed": np.clip(_held(n, rng, -60, 100, (20, 120)), 0, 100),
        "XX.UnknownSignal": walk(1.0),
        "XX.UnknownState": np.floor(_held(n, rng, 0, 3, (5, 60))),
    }
    if "unlisted" in hidden:
        y = y + (1.5 if size is None else size) * (extra["XX.UnknownState"] == 2)
    return Dataset(Ts=TS, t=t, u=np.column_stack([speed, torque]), y=y, input_names=("EEC1.EngSpeed", "EngTorque"),
                   input_units=("rpm", "Nm"), output_name="LFE1.EngFuelRate", output_unit="L/h",
                   u0=np.array([600.0, 112.0]), y0=2.5, valid=np.ones(n, bool),
                   cycle=(np.arange(n) // int(600 / TS)).astype(np.int64), extra=extra)


# ---- the truck simulator through the bus ------------------------------------------------------------------

PAPER = Structure(nb=(4, 5), nf=(5, 5), nk=(3, 0), nc=11, nd=11)  # the paper's orders (fuelid identify)


class _Records:
    """A Recorder's writer that keeps the decoded records in memory (no MCAP file: 3× faster for tests)."""

    columns = None  # no message columns (logger.columns): the records are the data

    def __init__(self):
        self.records = []

    def add_channel(self, topic, schema):
        pass

    def set_metadata(self, metadata):
        pass

    def write(self, topic, log_time_ns, record):
        if topic != "/can/raw":
            self.records.append((topic, log_time_ns, record))


def _records(cfg):
    """The decoded records of the simulated trip cfg (fuelid's recorder on its bus log) and its truth."""
    from fuelid.logger.readers import read_frames
    from fuelid.logger.recorder import Recorder
    from fuelid.sim.trip import simulate, write

    trip = simulate(cfg)
    with tempfile.TemporaryDirectory() as tmp:
        paths = write(trip, Path(tmp) / "trip.log.gz")
        sink = _Records()
        recorder = Recorder(sink)
        for frame in read_frames(paths["log"]):
            recorder.on_message_received(frame)
    return sink.records, trip


@functools.lru_cache(maxsize=None)
def simulated(effect: str | tuple[str, ...] | None, seed: int, duration_s: float = 1200.0,
              magnitude: float | None = None, routes_of: str | None = None, truth: str = "diesel_p320",
              engine: str = "", days: int = 1, fuel_lag_s: float = 0.0):
    """(Dataset, truth arrays at Ts (truth.npz), truth summary (truth.json)) of simulated diesel trips with the
    hidden `effect` (its default magnitude unless given; a catalogued or a generic one, sim.effects.ALL_EFFECTS;
    a tuple of ids hides them all) on the routes the trips of effect `routes_of` (default: `effect`, the first of
    them) use (sim.catalog.ALL_EFFECT_TRIPS: one trip, three for ambient air; one mixed cycle when neither is
    given), each driven on `days` days, the trips on days seed, seed + SECOND_TRIP_SEED, … (the routes of one day,
    then the next day's), decoded by fuelid's recorder; the truth
    arrays of several trips are concatenated, the summary is the first trip's; cached. `truth`: the engine's
    fuel truth (the paper's diesel model, or "map": a VECTO engine's map, sim.mapfuel); `engine`: the map truth's
    VECTO engine set (a .veng path or a shipped set's name; default the 325 kW engine); fuel_lag_s [s]: the dataset's
    (ident.dataset.build_dataset)."""
    from fuelid.ident.dataset import build_dataset

    records, trips = _trip_records(effect, seed, duration_s, magnitude, routes_of, truth, engine, days)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = build_dataset(records, fuel_lag_s=fuel_lag_s)
    arrays = {k: np.concatenate([t.truth[k] for t in trips]) for k in trips[0].truth}
    return ds, arrays, trips[0].summary


@functools.lru_cache(maxsize=2)  # records are large: the last two trip sets, for the datasets of another fuel lag
def _trip_records(effect, seed, duration_s, magnitude, routes_of, truth, engine, days) -> tuple[list, list]:
    """(records, trips) of `simulated`'s trips."""
    from fuelid.sim.catalog import ALL_EFFECT_TRIPS, SECOND_TRIP_SEED
    from fuelid.sim.effects import ALL_EFFECTS
    from fuelid.sim.trip import TripConfig

    names = effect if isinstance(effect, tuple) else (effect,) if effect else ()
    routes = ALL_EFFECT_TRIPS[routes_of or names[0]] if routes_of or names else ({"cycle": "mixed"},)
    effects = tuple((e, ALL_EFFECTS[e].default if magnitude is None else magnitude) for e in names)
    records, trips = [], []
    for j, route in enumerate(routes * days):
        recs, trip = _records(TripConfig(truth=truth, duration_s=duration_s, seed=seed + j * SECOND_TRIP_SEED,
                                         effects=effects, engine=engine, **route))
        records += recs
        trips.append(trip)
    return records, trips


def first_trips(ds, n: int = 1, break_s: float = 600.0):
    """ds up to its n-th break of the log of at least break_s [s]: the first n trips of a set (`simulated`)."""
    k = int(np.flatnonzero(np.diff(ds.t) >= break_s)[n - 1]) + 1
    return dataclasses.replace(ds, t=ds.t[:k], u=ds.u[:k], y=ds.y[:k], valid=ds.valid[:k], cycle=ds.cycle[:k],
                               extra={name: x[:k] for name, x in ds.extra.items()})


def identify(ds, structure: Structure = PAPER, effects=(), defined=()) -> PolyModel:
    """The model `fuelid identify` makes of ds (paper orders by default) with the effects added (built-in, or
    among `defined`, effects an engineer defined: ident.effectfile)."""
    fx = effect_inputs(ds, list(effects), structure, defined)
    u = np.hstack([ds.u, fx.u])
    segs = [s for s in ds.segments() if s.stop - s.start > 100]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = pem(u, fx.y, fx.extend(structure), ds.Ts, segments=segs, u0=np.r_[ds.u0, np.zeros(fx.u.shape[1])],
                y0=ds.y0)
    return dataclasses.replace(m, input_names=ds.input_names + fx.names, input_units=ds.input_units + fx.units,
                               output_name=ds.output_name, output_unit=ds.output_unit, effects=fx.effects,
                               info={**m.info, "effect_parameters": fx.parameters,
                                     **effect_definitions(fx.effects, defined)})


def held_out_rmse(model: PolyModel, ds) -> float:
    """The model's RMS simulation error [output unit] on held-out folds, refitted without each (the diagnosis's
    yardstick, ident.diagnosis.yardstick)."""
    settings = Settings()
    return held_out_summary(refits(model, ds, make_folds(ds, settings), [], settings), ds)["rmse"]


def fitted(ds) -> PolyModel:
    """The model of STRUCTURE fitted to ds by PEM, named with ds's signals and units."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = pem(ds.u, ds.y, STRUCTURE, ds.Ts, u0=ds.u0, y0=ds.y0)
    return dataclasses.replace(m, input_names=ds.input_names, input_units=ds.input_units,
                               output_name=ds.output_name, output_unit=ds.output_unit)
