"""Live online identification inside the logger daemon: decoded J1939/flow-meter records in, /ident/* out.

`LiveEstimator.feed(topic, t, record)` takes the records the daemon writes (`/j1939/EEC1`, `/j1939/EC1`,
`/j1939/LFE1`, `/flowmeter`; t the receive time [s]) and resamples them on the fly to the estimator's grid,
as ident.dataset does offline: bins [t0 + kTs, t0 + (k+1)Ts), each signal averaged over its valid samples in
the bin, a bin without one not available (NaN; the estimator holds inputs for up to max_gap_s). Torque [Nm] =
EEC1.ActualEngPercentTorque [%] × EC1.EngReferenceTorque [Nm] / 100 (a model in % uses the percentage). Fuel:
/flowmeter flow_kg_h for a model in kg/h, else LFE1.EngFuelRate [L/h], each record in the bin of its receive time
minus the fuel signal's reporting lag `fuel_lag_s` (a prior model's `training.fuel_lag_s`), so a bin
closes that much later. Only the engine's records (source
address engine_sa, default 0x00) are used; null (not available) values are no sample. A silence longer than
max_gap_s (engine off, logger restart) restarts the estimator's filters; so does an engine turning below half its
idle speed (off, cranking or stalling) for longer than max_gap_s: its bins are not available, as offline.

Replay at `speed` × real time (fuelid replay --speed): receive times run `speed` times faster than the
recording, so the grid step and max_gap_s are divided by `speed` on the receive-time axis; the estimator still
sees Ts-spaced samples of the recorded trip.

Starting from a prior model (`from_model`) the estimator runs from the first bin. From scratch
(`from_scratch`) the operating point (u0, y0) the model's deviations are taken from (ident.dataset: the idle
point) is not known yet: bins are only watched until idle_min_s of complete bins with the engine speed within
idle_tol_rpm of idle_rpm, whose mean inputs and fuel become (u0, y0); then the RPEM starts from θ = 0 with P0 in
the parameters' units (ident.rpem.scaled_P0: fuel per rpm scaled by the idle fuel over the idle speed, fuel per
N·m by the idle fuel over the reference torque), not the unit-blind 100 I, which let one disturbed bin early on
throw the estimate into a wrong minimum it never left.

Every closed bin once the estimator runs gives records for the daemon to write (topic, receive time [s], record):

    /ident/prediction  {t, predicted, simulated, measured, unit}   ŷ(t|t−1), the model's simulation and the
                       measured fuel [output unit] (null when not available)
    /ident/residual    {t, eps, status, unit}                       ε = measured − predicted; status as
                       ident.rpem.Trace (−1 no state, 0 no update, 1 updated, 2 shrunk step, 3 rejected)
    /ident/parameters  {t, names, theta, dc_gain, fuel_change_pct, fuel_change_ci95_pct, lam, trace_P, dtheta,
                        fit_prediction_pct, fit_simulation_pct, updates, noise_variance}   every parameters_every_s
    /ident/engine_map  {t, map_fuel, map_beyond_plane, torque_rise, torque_rise_x_map_fuel, fuel_unit, rise_unit}
                       an engine model's map inputs (below), every bin: the map's fuel s(n, T) and its part
                       beyond the plane [fuel_unit], the torque rise r and r·s/f_scale [rise_unit: kNm/s or 100 %/s]

An engine model (a prior with the `engine_map` effect: ident.hammerstein) runs with its map fixed: each bin's map
inputs are computed from its speed and torque by the definition the offline model uses (ident.effects:
`engine_map_columns`; the torque rise `torque_rise`, a central difference on the held torque, needs the next bin's
torque, so each bin runs and its records are written when the next one closes, 0.3 s later), and only the
dynamics' parameters (or the common fuel gain) adapt.

dc_gain G_i(1) = B_i(1)/F_i(1) [output unit per input unit]; fuel_change_pct how much the steady-state fuel
at the mean operating point has moved since the prior, 100 (Σ_i G_i(1) ū_i / Σ_i G⁰_i(1) ū_i − 1) with ū the
mean deviation inputs so far and G⁰ the prior's gains (null from scratch): the drift of the fuel system
(injector wear, fuel quality, meter calibration) the estimator tracks; fuel_change_ci95_pct its 95 %
confidence half-width from the estimator's parameter covariance (`fuel_change`). From a prior the default
estimator (`from_model`, adapt='gain') is ident.kalman.GainTracker: only the common fuel gain adapts, so
fuel_change_pct = 100 (g − 1) at any operating point.

Every snapshot_every_s (receive time) the current model is written to snapshot_path (model.json, atomically);
`snapshot()` writes it on demand (the daemon at shutdown). This module loads no SciPy; ident.rpem and
ident.kalman (numba) come with the estimator.

`live_estimator` makes the LiveEstimator the `fuelid log --identify` settings ask for, which the command line
hands to the daemon (fuelid.logger.daemon.Estimator: the daemon imports nothing from here); `check_online` is
the one check that a model or orders can run online (the daemon's settings, `fuelid online`).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from fuelid.errors import FuelidError
from fuelid.ident.dataset import RUNNING_SHARE
from fuelid.ident.modelfile import load_model, save_model
from fuelid.ident.polymodel import Structure, parameter_names, parse_orders

PREDICTION_SCHEMA = {"type": "object", "properties": {
    "t": {"type": "number"}, "predicted": {"type": ["number", "null"]}, "simulated": {"type": ["number", "null"]},
    "measured": {"type": ["number", "null"]}, "unit": {"type": "string"}}}
RESIDUAL_SCHEMA = {"type": "object", "properties": {
    "t": {"type": "number"}, "eps": {"type": ["number", "null"]}, "status": {"type": "integer"},
    "unit": {"type": "string"}}}
PARAMETERS_SCHEMA = {"type": "object", "properties": {
    "t": {"type": "number"}, "names": {"type": "array", "items": {"type": "string"}},
    "theta": {"type": "array", "items": {"type": "number"}},
    "dc_gain": {"type": "array", "items": {"type": ["number", "null"]}},
    "fuel_change_pct": {"type": ["number", "null"]}, "fuel_change_ci95_pct": {"type": ["number", "null"]},
    "lam": {"type": "number"}, "trace_P": {"type": "number"}, "dtheta": {"type": "number"},
    "fit_prediction_pct": {"type": ["number", "null"]}, "fit_simulation_pct": {"type": ["number", "null"]},
    "updates": {"type": "integer"}, "noise_variance": {"type": ["number", "null"]}}}
ENGINE_MAP_SCHEMA = {"type": "object", "properties": {
    "t": {"type": "number"}, "map_fuel": {"type": ["number", "null"]},
    "map_beyond_plane": {"type": ["number", "null"]}, "torque_rise": {"type": ["number", "null"]},
    "torque_rise_x_map_fuel": {"type": ["number", "null"]}, "fuel_unit": {"type": "string"},
    "rise_unit": {"type": "string"}}}
SCHEMAS = {"/ident/prediction": PREDICTION_SCHEMA, "/ident/residual": RESIDUAL_SCHEMA,
           "/ident/parameters": PARAMETERS_SCHEMA, "/ident/engine_map": ENGINE_MAP_SCHEMA}


def _num(x):
    """A float for JSON, None for NaN/inf."""
    x = float(x)
    return x if math.isfinite(x) else None


def _blocks(structure):
    """Index ranges of the B_i and F_i coefficients in θ (order of ident.polymodel.parameter_names, na = 0)."""
    nb = np.cumsum([0, *structure.nb])
    nf = nb[-1] + np.cumsum([0, *structure.nf])
    return [(slice(nb[i], nb[i + 1]), slice(nf[i], nf[i + 1])) for i in range(structure.n_inputs)]


def dc_gains(theta, structure) -> np.ndarray:
    """G_i(1) = B_i(1)/F_i(1) per input from θ [output unit per input unit]."""
    return np.array([theta[b].sum() / (1.0 + theta[f].sum()) for b, f in _blocks(structure)])


def fuel_change(theta, cov, structure, gain0, du) -> tuple[float, float]:
    """The steady-state fuel change c = Σ_i G_i(1) ū_i / Σ_i G⁰_i(1) ū_i − 1 [%] at mean deviation inputs ū,
    and its 95 % confidence half-width 1.96 √(∇cᵀ Σ_θ ∇c) [%] (delta method, Σ_θ = cov the θ covariance):
    ∂c/∂b_i,l = ū_i / (F_i(1) S⁰),  ∂c/∂f_i,k = −G_i(1) ū_i / (F_i(1) S⁰),  S⁰ = Σ_i G⁰_i(1) ū_i."""
    gains = dc_gains(theta, structure)
    s0 = gain0 @ du
    grad = np.zeros(len(theta))
    for (b, f), g, u in zip(_blocks(structure), gains, du):
        f1 = 1.0 + theta[f].sum()
        grad[b], grad[f] = u / (f1 * s0), -g * u / (f1 * s0)
    return 100.0 * (gains @ du / s0 - 1.0), 196.0 * math.sqrt(max(grad @ cov @ grad, 0.0))


def input_scales(idle_speed: float, torque_ref: float) -> np.ndarray:
    """The magnitudes [rpm, torque unit] the RPEM from scratch scales its P0 by (ident.rpem.scaled_P0), known
    before the engine has moved: the idle speed [rpm] and the reference torque [Nm] (100 for a torque in %).
    FuelidError when either is not a positive number (a torque that never moved from 0 gives nothing to scale)."""
    if not (idle_speed > 0 and torque_ref is not None and torque_ref > 0):
        raise FuelidError(f"no scale for the RPEM from scratch: idle speed {idle_speed} rpm, reference torque "
                          f"{torque_ref} (the torque must be known and move from 0)")
    return np.array([idle_speed, torque_ref], float)


def fuel_scale(y0: float) -> float:
    """The output magnitude [output unit] the RPEM from scratch scales its P0 by: the idle fuel y0; an idle engine
    burns fuel, so a fuel signal reading ≤ 0 there is taken as 1 L/h (or kg/h), an idle's order."""
    return y0 if y0 > 0 else 1.0


ONLINE_EFFECTS = {"engine_map": 3}  # effects the online estimators run: id -> its input columns


def check_online(structure: Structure, effects=(), source: str | None = None) -> None:
    """FuelidError unless the online estimators (the daemon's, `fuelid online`) can run a model of this structure
    and these effects: BJ/OE orders (na = 0) of engine speed and torque, and the engine model, its map fixed and its
    inputs computed from speed and torque sample by sample (ONLINE_EFFECTS); no other effect inputs. source (a file
    name) starts the message."""
    where = f"{source}: " if source else ""
    unsupported = [e for e in effects if e not in ONLINE_EFFECTS]
    if unsupported:
        raise FuelidError(f"{where}the model includes effects {unsupported}; the online estimator has speed and "
                          "torque only (and the engine map computed from them)")
    extra = sum(ONLINE_EFFECTS[e] for e in effects)
    if structure.na or structure.n_inputs != 2 + extra:
        raise FuelidError(f"{where}the online estimator takes BJ/OE orders for engine speed and torque (na = 0)")


def prior_estimator(model, *, method: str = "rpem", forgetting: float | None = 0.9995, drift: float = 3e-4,
                    adapt: str = "gain"):
    """The recursive estimator that starts from `model` (LiveEstimator.from_model explains the options)."""
    # numba-compiled (seconds to load on the in-cab box): loaded with an estimator, not with this module
    from fuelid.ident.kalman import GainTracker, ParameterKalman
    from fuelid.ident.rpem import RPEM

    if method not in ("rpem", "kalman") or adapt not in ("gain", "all"):
        raise ValueError(f"method must be 'rpem' or 'kalman' and adapt 'gain' or 'all', got {method!r}, {adapt!r}")
    if adapt == "gain":
        return GainTracker(model, lam=forgetting or 1.0) if method == "rpem" else GainTracker(model, rate=drift)
    return RPEM(prior=model, lam=forgetting) if method == "rpem" else ParameterKalman(prior=model, rate=drift)


class LiveEstimator:
    """Resample decoded records to Ts and run an ident.rpem estimator on them (module docstring); the daemon's
    fuelid.logger.daemon.Estimator.

    estimator       an ident.rpem.RPEM, ident.kalman.ParameterKalman or ident.kalman.GainTracker (its Ts is the
                    grid step); or None with
    start           a function (u0 [input units], y0 [output unit], u_scale [input units]) -> estimator, called
                    once the idle operating point is known (from scratch; u_scale as `input_scales`), and Ts [s]
    torque_unit     'Nm' or '%': the unit of the model's torque input
    fuel            'lfe1' (LFE1.EngFuelRate, L/h) or 'flowmeter' (flow_kg_h, kg/h)
    names           parameter names for /ident/parameters (default θ0, θ1, …)
    speed           the records arrive `speed` times faster than recorded (a sped-up replay)
    engine_map      the engine model's map (ident.enginemap.EngineMap) whose inputs follow speed and torque
                    (module docstring; `from_model` takes it from the model), or None
    idle_rpm, idle_tol_rpm, idle_min_s   the idle operating point from scratch [rpm], [rpm], [s]
    """

    schemas = SCHEMAS  # the channels `feed` writes: topic -> JSON schema

    def __init__(self, estimator=None, *, start=None, Ts: float | None = None, torque_unit: str = "Nm",
                 fuel: str = "lfe1", engine_sa: int = 0, names=None, snapshot_path=None,
                 snapshot_every_s: float = 600.0, parameters_every_s: float = 10.0, max_gap_s: float = 1.0,
                 speed: float = 1.0, idle_rpm: float = 600.0, idle_tol_rpm: float = 50.0, idle_min_s: float = 3.0,
                 engine_map=None, fuel_lag_s: float = 0.0):
        if torque_unit not in ("Nm", "%") or fuel not in ("lfe1", "flowmeter"):
            raise ValueError("torque_unit must be 'Nm' or '%', fuel 'lfe1' or 'flowmeter'")
        if (estimator is None) == (start is None) or (start is not None and Ts is None):
            raise ValueError("give an estimator, or a start function and Ts")
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        self.est, self._start = estimator, start
        self.Ts = estimator.Ts if estimator is not None else float(Ts)
        if not 0.0 <= fuel_lag_s < self.Ts:
            raise ValueError(f"fuel_lag_s must be in [0, Ts = {self.Ts} s), got {fuel_lag_s}")
        self.torque_unit, self.fuel, self.engine_sa = torque_unit, fuel, engine_sa
        self.unit = "kg/h" if fuel == "flowmeter" else "L/h"
        self.names = list(names) if names is not None else None
        self.snapshot_path, self.snapshot_every_s = snapshot_path, snapshot_every_s
        self.parameters_every_s = parameters_every_s
        # the grid on the receive-time axis in integer ns (log times are ns): a record on a bin edge is never
        # put in the bin before by float rounding
        self._step_ns, self._max_gap = round(self.Ts / speed * 1e9), max_gap_s / speed
        self._lag_ns = round(fuel_lag_s / speed * 1e9)  # a fuel record at t is the fuel of t − lag
        self._idle = (idle_rpm, idle_tol_rpm, max(1, math.ceil(idle_min_s / self.Ts)))
        self._idle_bins: list[np.ndarray] = []  # [speed, torque, fuel] of the current idle stretch (from scratch)
        self._gain0 = None  # the prior's G_i(1), the reference of fuel_change_pct
        if estimator is not None and estimator.prior is not None:
            self._gain0 = dc_gains(estimator.prior.theta, estimator.structure)
        self._du_sum, self._du_n = 0.0, 0  # Σ ũ and its count, for the mean operating point ū
        self.ref_torque = None  # [Nm], from EC1
        self._bin = None  # index k of the open bin
        self._t0_ns = None
        # speed, torque %, fuel of the open bin k (row 0) and bin k + 1 (row 1: speed and torque that arrive
        # while bin k still waits for its fuel, up to the fuel's lag later)
        self._sums = np.zeros((2, 3))
        self._counts = np.zeros((2, 3))
        self._last_data_t = -math.inf
        self._next_parameters = self._next_snapshot = None
        self.engine_map = engine_map
        self._torque_held = math.nan  # the last finite torque of this stretch before the pending bin
        self._pending = None  # an engine model's bin (k, [speed, torque], fuel) waiting for the next one

    @classmethod
    def from_model(cls, model, *, method: str = "rpem", forgetting: float | None = 0.9995, drift: float = 3e-4,
                   adapt: str = "gain", **kwargs):
        """A LiveEstimator starting from a PolyModel (e.g. load_model('fleet.json')), units and the fuel signal's
        reporting lag (training.fuel_lag_s) from the model.

        method 'rpem' (constant forgetting λ = forgetting; None: λ = 1) or 'kalman' (random-walk fuel gain,
        relative drift per sample `drift`); adapt 'gain' (ident.kalman.GainTracker: only the common fuel gain,
        the model's dynamics and noise model held) or 'all' (every parameter: ident.rpem.RPEM or
        ident.kalman.ParameterKalman)."""
        est = prior_estimator(model, method=method, forgetting=forgetting, drift=drift, adapt=adapt)
        fuel = "flowmeter" if model.output_unit == "kg/h" else "lfe1"
        emap = None
        if "engine_map" in model.effects:  # SciPy (the map's splines) only for an engine model
            from fuelid.ident.enginemap import EngineMap
            emap = EngineMap.from_dict(model.info["effect_parameters"]["engine_map"])
        kwargs.setdefault("fuel_lag_s", model.fuel_lag_s)
        return cls(est, torque_unit=model.input_units[1] or "Nm", fuel=fuel,
                   names=parameter_names(model.structure), engine_map=emap, **kwargs)

    @classmethod
    def from_scratch(cls, structure, Ts: float = 0.3, *, forgetting: float | None = None, **kwargs):
        """A LiveEstimator whose RPEM starts from θ = 0 at the idle operating point (module docstring);
        forgetting: constant λ, or None for λ growing towards 1 (ident.rpem)."""
        from fuelid.ident.rpem import RPEM, scaled_P0  # numba-compiled: loaded with the estimator (prior_estimator)

        def start(u0, y0, u_scale):
            return RPEM(structure, Ts, lam=forgetting, u0=u0, y0=y0, P0=scaled_P0(structure, u_scale, fuel_scale(y0)))

        return cls(start=start, Ts=Ts, names=parameter_names(structure), **kwargs)

    def prepare(self) -> None:
        """Load the estimator's compiled loop now (seconds on a first run), not with the first bin."""
        est = self.est or self._start(np.zeros(2), 0.0, np.ones(2))
        est.update(np.empty((0, est.structure.n_inputs)), np.empty(0))

    def feed(self, topic: str, t: float, record: dict) -> list[tuple[str, float, dict]]:
        """One decoded record received at t [s]; returns the /ident/* records of the bins it closed."""
        values = self._values(topic, record)
        if not values:
            return []
        out = []
        if self._t0_ns is None:
            self._t0_ns, self._bin = round(t * 1e9), 0
            self._next_parameters = t + self.parameters_every_s
            self._next_snapshot = t + self.snapshot_every_s
        since_ns = round(t * 1e9) - self._t0_ns
        # bin k is complete once its fuel can no longer come: at (k + 1) Ts + lag
        k = (since_ns - self._lag_ns) // self._step_ns
        if k > self._bin:
            out += self._close(self._bin)
            if t - self._last_data_t > self._max_gap:  # silence: no bins in between, filters restart
                out += self._flush()
                self._restart()
                self._sums[:], self._counts[:] = 0.0, 0.0
            else:
                for empty in range(self._bin + 1, k):
                    out += self._close(empty)
            self._bin = k
        k_inputs = since_ns // self._step_ns  # speed and torque are the bin's of their own receive time
        for channel, v in values:
            row = (k if channel == 2 else k_inputs) - self._bin
            if row in (0, 1):  # a record from an already closed bin (out of order) is dropped
                self._sums[row, channel] += v
                self._counts[row, channel] += 1
        self._last_data_t = max(self._last_data_t, t)
        return out

    def _restart(self) -> None:
        if self.est is not None:
            self.est.reset()
        self._idle_bins.clear()
        self._torque_held = math.nan

    def _values(self, topic, record) -> list[tuple[int, float]]:
        """[(channel, value)] of a record: 0 speed [rpm], 1 torque [%], 2 fuel; EC1 sets the reference torque."""
        if topic == "/flowmeter":
            v = record.get("flow_kg_h") if self.fuel == "flowmeter" else None
            return [] if v is None else [(2, float(v))]
        if not topic.startswith("/j1939/") or record.get("sa") != self.engine_sa:
            return []
        name = topic[7:]
        if name == "EC1" and record.get("EngReferenceTorque") is not None:
            self.ref_torque = float(record["EngReferenceTorque"])
        elif name == "EEC1":
            pairs = [(0, record.get("EngSpeed")), (1, record.get("ActualEngPercentTorque"))]
            return [(c, float(v)) for c, v in pairs if v is not None]
        elif name == "LFE1" and self.fuel == "lfe1" and record.get("EngFuelRate") is not None:
            return [(2, float(record["EngFuelRate"]))]
        return []

    def _close(self, k: int) -> list[tuple[str, float, dict]]:
        """Run the estimator on bin k and make its records."""
        mean = np.where(self._counts[0] > 0, self._sums[0] / np.maximum(self._counts[0], 1), np.nan)
        self._sums[0], self._counts[0] = self._sums[1], self._counts[1]
        self._sums[1], self._counts[1] = 0.0, 0.0
        speed, pct, fuel = mean
        if self.torque_unit == "%":
            torque = pct
        else:
            torque = pct * self.ref_torque / 100.0 if self.ref_torque is not None else math.nan
        u = np.array([speed, torque])
        if speed < RUNNING_SHARE * self._idle[0]:  # the engine off or starting: a gap, as offline (ident.dataset)
            u, fuel = np.full(2, np.nan), math.nan
        if self.est is None and not self._watch_idle(u, fuel):
            return []
        if self.engine_map is None:
            return self._run(k, u, fuel)
        # an engine model: the torque rise of bin k needs bin k + 1's torque, so bin k runs when k + 1 closes
        out = [] if self._pending is None else self._run_engine(*self._pending, torque)
        self._pending = (k, u, fuel)
        return out

    def _flush(self) -> list[tuple[str, float, dict]]:
        """Run an engine model's pending bin, the last of its stretch (its torque rise one-sided, as offline)."""
        out = [] if self._pending is None else self._run_engine(*self._pending, None)
        self._pending = None
        return out

    def _run_engine(self, k: int, u: np.ndarray, fuel: float, next_torque: float | None):
        """Run the estimator on bin k of an engine model, its map inputs from its speed and torque u and the next
        bin's torque (None: the stretch ends with bin k)."""
        map_inputs = self._map_inputs(u[0], u[1], next_torque)
        t = (self._t0_ns + (k + 1) * self._step_ns) * 1e-9
        return [("/ident/engine_map", t, self._map_record(t, map_inputs))] + self._run(k, np.r_[u, map_inputs[1:]],
                                                                                         fuel)

    def _run(self, k: int, u: np.ndarray, fuel: float) -> list[tuple[str, float, dict]]:
        """Run the estimator on bin k (inputs u, fuel) and make its records."""
        t = (self._t0_ns + (k + 1) * self._step_ns) * 1e-9
        out = []
        trace = self.est.update(u[None, :], np.array([fuel]))
        if np.isfinite(u).all():
            self._du_sum = self._du_sum + (u - self.est.u0)
            self._du_n += 1
        out += [("/ident/prediction", t, {"t": t, "predicted": _num(trace.yhat[0]), "simulated": _num(trace.ysim[0]),
                                          "measured": _num(fuel), "unit": self.unit}),
                ("/ident/residual", t, {"t": t, "eps": _num(trace.eps[0]), "status": int(trace.status[0]),
                                        "unit": self.unit})]
        if t >= self._next_parameters:
            self._next_parameters = t + self.parameters_every_s
            out.append(("/ident/parameters", t, self.parameters(t, float(trace.dtheta[0]))))
        if self.snapshot_path is not None and t >= self._next_snapshot:
            self._next_snapshot = t + self.snapshot_every_s
            self.snapshot()
        return out

    def _map_inputs(self, speed: float, torque: float, next_torque: float | None) -> np.ndarray:
        """[s(n, T), m(n, T), r, r·s/f_scale] of a bin: the map's fuel and its input columns (ident.effects'
        engine_map_columns), the torque rise over the last finite torque before the bin and the next bin's
        (`torque_rise`'s central difference; without a next bin, its one-sided difference at the end)."""
        from fuelid.ident.effects import engine_map_columns, torque_rise  # with the map (SciPy)

        window = [self._torque_held, torque] + ([] if next_torque is None else [next_torque])
        rise = torque_rise(np.array(window), self.Ts * np.arange(len(window)), self.torque_unit)[1:2]
        if math.isfinite(torque):
            self._torque_held = torque
        cols = engine_map_columns(self.engine_map, np.array([speed]), np.array([torque]), rise)[0]
        return np.r_[cols[0] + self.engine_map.plane_at(speed, torque), cols]

    def _map_record(self, t: float, x: np.ndarray) -> dict:
        """The /ident/engine_map record of `_map_inputs` x."""
        from fuelid.ident.effects import map_column_units

        fuel_unit, rise_unit, _ = map_column_units(self.torque_unit, self.unit)
        return {"t": t, "map_fuel": _num(x[0]), "map_beyond_plane": _num(x[1]), "torque_rise": _num(x[2]),
                "torque_rise_x_map_fuel": _num(x[3]), "fuel_unit": fuel_unit, "rise_unit": rise_unit}

    def _watch_idle(self, u, fuel) -> bool:
        """From scratch: collect a lasting idle stretch; start the estimator at its mean. True once started."""
        idle_rpm, tol, n = self._idle
        if not (np.isfinite(u).all() and math.isfinite(fuel) and abs(u[0] - idle_rpm) <= tol):
            self._idle_bins.clear()
            return False
        self._idle_bins.append(np.r_[u, fuel])
        if len(self._idle_bins) < n:
            return False
        u0y0 = np.mean(self._idle_bins, axis=0)
        torque_ref = 100.0 if self.torque_unit == "%" else self.ref_torque  # known: the torque in Nm needs it
        self.est = self._start(u0y0[:2], float(u0y0[2]), input_scales(u0y0[0], torque_ref))
        self._idle_bins.clear()
        return True

    def parameters(self, t: float, dtheta: float = 0.0) -> dict:
        """The /ident/parameters record: θ, DC gains B_i(1)/F_i(1), fuel change, λ, trace(P), running fits."""
        est = self.est
        theta = est.theta
        gains = dc_gains(theta, est.structure)
        change = ci = None
        if self._gain0 is not None and self._du_n:
            change, ci = map(_num, fuel_change(theta, est.covariance(), est.structure, self._gain0,
                                               self._du_sum / self._du_n))
        rep = est.report()
        names = self.names or [f"theta{j}" for j in range(theta.size)]
        return {"t": t, "names": names, "theta": [float(v) for v in theta], "dc_gain": [_num(g) for g in gains],
                "fuel_change_pct": change, "fuel_change_ci95_pct": ci, "lam": rep["lam"], "trace_P": rep["trace_P"],
                "dtheta": dtheta,
                "fit_prediction_pct": _num(rep["running_fit_prediction_pct"]),
                "fit_simulation_pct": _num(rep["running_fit_simulation_pct"]), "updates": rep["updates"],
                "noise_variance": _num(rep["noise_variance"])}

    def snapshot(self) -> bool:
        """Write the current model to snapshot_path (atomically); False while there is none yet."""
        if self.est is None or self.snapshot_path is None:
            return False
        model = self.est.model()
        if self.est.prior is None:
            model = dataclasses.replace(model, input_names=("EEC1.EngSpeed", "EngTorque"),
                                        input_units=("rpm", self.torque_unit),
                                        output_name="flowmeter.flow_kg_h" if self.fuel == "flowmeter"
                                        else "LFE1.EngFuelRate", output_unit=self.unit)
        save_model(model, self.snapshot_path)
        return True

    def status(self) -> dict:
        """For the daemon's status file: waiting for the idle operating point (from scratch) or running, the
        snapshot's path, and once running the estimator's samples, updates, rejected steps, λ and running
        simulation fit [%] (null when not finite)."""
        out = {"state": "running" if self.est is not None else "waiting for idle", "snapshot": str(self.snapshot_path)}
        if self.est is not None:
            rep = self.est.report()
            fit = rep["running_fit_simulation_pct"]
            out.update(samples=rep["samples"], updates=rep["updates"], rejected_steps=rep["rejected_steps"],
                       lam=rep["lam"], fit_simulation_pct=round(fit, 2) if math.isfinite(fit) else None)
        return out


def live_estimator(*, model=None, orders: str | None = None, method: str = "rpem", forgetting: float | None = None,
                   **kwargs) -> LiveEstimator:
    """The LiveEstimator of the daemon's identify settings: from the prior model file `model` (forgetting λ
    default 0.9995), else from scratch with `orders` ('paper' or a SPEC as `fuelid identify --orders`; default
    paper; forgetting None: λ growing to 1). kwargs as LiveEstimator (snapshot_path, snapshot_every_s, speed).
    FuelidError for a model or orders the online estimator cannot run."""
    if model:
        prior = load_model(model)
        check_online(prior.structure, prior.effects, str(model))
        return LiveEstimator.from_model(prior, method=method, forgetting=0.9995 if forgetting is None else forgetting,
                                        **kwargs)
    structure = Structure(**parse_orders(orders or "paper"))
    check_online(structure)
    return LiveEstimator.from_scratch(structure, forgetting=forgetting, **kwargs)
