"""Live online identification inside the logger daemon: decoded J1939/flow-meter records in, /ident/* out.

`LiveEstimator.feed(topic, t, record)` takes the records the daemon writes (`/j1939/EEC1`, `/j1939/EC1`,
`/j1939/LFE1`, `/flowmeter`; t the receive time [s]) and resamples them on the fly to the estimator's grid,
as ident.dataset does offline: bins [t0 + kTs, t0 + (k+1)Ts), each signal averaged over its valid samples in
the bin, a bin without one not available (NaN; the estimator holds inputs for up to max_gap_s). Torque [Nm] =
EEC1.ActualEngPercentTorque [%] × EC1.EngReferenceTorque [Nm] / 100 (a model in % uses the percentage). Fuel:
/flowmeter flow_kg_h for a model in kg/h, else LFE1.EngFuelRate [L/h]. Only the engine's records (source
address engine_sa, default 0x00) are used; null (not available) values are no sample. A silence longer than
max_gap_s (engine off, logger restart) restarts the estimator's filters.

Every closed bin gives records for the daemon to write (topic, log time [s], record):

    /ident/prediction  {t, predicted, simulated, measured, unit}   ŷ(t|t−1), the model's simulation and the
                       measured fuel [output unit] (null when not available)
    /ident/residual    {t, eps, status, unit}                       ε = measured − predicted; status as
                       ident.rpem.Trace (−1 no state, 0 no update, 1 updated, 2 shrunk step, 3 rejected)
    /ident/parameters  {t, names, theta, dc_gain, lam, trace_P, dtheta, fit_prediction_pct,
                        fit_simulation_pct, updates, noise_variance}   every parameters_every_s

and every snapshot_every_s the current model is written to snapshot_path (model.json, atomically).
This module imports numpy and ident.rpem only; model files are read and written through ident.modelfile,
imported when a snapshot is first written.
"""
from __future__ import annotations

import math

import numpy as np

PREDICTION_SCHEMA = {"type": "object", "properties": {
    "t": {"type": "number"}, "predicted": {"type": ["number", "null"]}, "simulated": {"type": ["number", "null"]},
    "measured": {"type": ["number", "null"]}, "unit": {"type": "string"}}}
RESIDUAL_SCHEMA = {"type": "object", "properties": {
    "t": {"type": "number"}, "eps": {"type": ["number", "null"]}, "status": {"type": "integer"},
    "unit": {"type": "string"}}}
PARAMETERS_SCHEMA = {"type": "object", "properties": {
    "t": {"type": "number"}, "names": {"type": "array", "items": {"type": "string"}},
    "theta": {"type": "array", "items": {"type": "number"}}, "dc_gain": {"type": "array", "items": {"type": "number"}},
    "lam": {"type": "number"}, "trace_P": {"type": "number"}, "dtheta": {"type": "number"},
    "fit_prediction_pct": {"type": ["number", "null"]}, "fit_simulation_pct": {"type": ["number", "null"]},
    "updates": {"type": "integer"}, "noise_variance": {"type": ["number", "null"]}}}
SCHEMAS = {"/ident/prediction": PREDICTION_SCHEMA, "/ident/residual": RESIDUAL_SCHEMA,
           "/ident/parameters": PARAMETERS_SCHEMA}


def _num(x):
    """A float for JSON, None for NaN/inf."""
    x = float(x)
    return x if math.isfinite(x) else None


class LiveEstimator:
    """Resample decoded records to Ts and run an ident.rpem estimator on them (module docstring).

    estimator       an ident.rpem.RPEM or ident.kalman.ParameterKalman (its Ts is the grid step)
    torque_unit     'Nm' or '%': the unit of the model's torque input
    fuel            'lfe1' (LFE1.EngFuelRate, L/h) or 'flowmeter' (flow_kg_h, kg/h)
    names           parameter names for /ident/parameters (default θ0, θ1, …)
    """

    def __init__(self, estimator, *, torque_unit: str = "Nm", fuel: str = "lfe1", engine_sa: int = 0,
                 names=None, snapshot_path=None, snapshot_every_s: float = 600.0,
                 parameters_every_s: float = 10.0, max_gap_s: float = 1.0):
        if torque_unit not in ("Nm", "%") or fuel not in ("lfe1", "flowmeter"):
            raise ValueError("torque_unit must be 'Nm' or '%', fuel 'lfe1' or 'flowmeter'")
        self.est = estimator
        self.Ts = estimator.Ts
        self.torque_unit, self.fuel, self.engine_sa = torque_unit, fuel, engine_sa
        self.unit = "kg/h" if fuel == "flowmeter" else "L/h"
        self.names = list(names) if names is not None else [f"theta{j}" for j in range(estimator.theta.size)]
        self.snapshot_path, self.snapshot_every_s = snapshot_path, snapshot_every_s
        self.parameters_every_s, self.max_gap_s = parameters_every_s, max_gap_s
        self.ref_torque = None  # [Nm], from EC1
        self._bin = None  # index k of the open bin
        self._t0 = None
        self._sums = np.zeros(3)  # speed, torque %, fuel
        self._counts = np.zeros(3)
        self._last_data_t = -math.inf
        self._next_parameters = self._next_snapshot = None

    @classmethod
    def from_model(cls, model, *, method: str = "rpem", forgetting: float | None = 0.9995, **kwargs):
        """A LiveEstimator starting from a PolyModel (e.g. load_model('fleet.json')), units from the model."""
        from ident.polymodel import parameter_names

        if method == "kalman":
            from ident.kalman import ParameterKalman

            est = ParameterKalman(prior=model)
        else:
            from ident.rpem import RPEM

            est = RPEM(prior=model, lam=forgetting)
        fuel = "flowmeter" if model.output_unit == "kg/h" else "lfe1"
        return cls(est, torque_unit=model.input_units[1] or "Nm", fuel=fuel,
                   names=parameter_names(model.structure), **kwargs)

    def feed(self, topic: str, t: float, record: dict) -> list[tuple[str, float, dict]]:
        """One decoded record received at t [s]; returns the /ident/* records of the bins it closed."""
        values = self._values(topic, record)
        if not values:
            return []
        out = []
        if self._t0 is None:
            self._t0, self._bin = t, 0
            self._next_parameters = t + self.parameters_every_s
            self._next_snapshot = t + self.snapshot_every_s
        k = int((t - self._t0) // self.Ts)
        if k > self._bin:
            out += self._close(self._bin)
            if t - self._last_data_t > self.max_gap_s:  # silence: no bins in between, filters restart
                self.est.reset()
            else:
                for empty in range(self._bin + 1, k):
                    out += self._close(empty)
            self._bin = k
        if k >= self._bin:  # a record from an already closed bin (out of order) is dropped
            for channel, v in values:
                self._sums[channel] += v
                self._counts[channel] += 1
        self._last_data_t = max(self._last_data_t, t)
        return out

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
        mean = np.where(self._counts > 0, self._sums / np.maximum(self._counts, 1), np.nan)
        self._sums[:], self._counts[:] = 0.0, 0.0
        speed, pct, fuel = mean
        if self.torque_unit == "%":
            torque = pct
        else:
            torque = pct * self.ref_torque / 100.0 if self.ref_torque is not None else math.nan
        trace = self.est.update(np.array([[speed, torque]]), np.array([fuel]))
        t = self._t0 + (k + 1) * self.Ts
        out = [("/ident/prediction", t, {"t": t, "predicted": _num(trace.yhat[0]), "simulated": _num(trace.ysim[0]),
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

    def parameters(self, t: float, dtheta: float = 0.0) -> dict:
        """The /ident/parameters record: θ, DC gains B_i(1)/F_i(1), λ, trace(P), running fits."""
        est, s = self.est, self.est.structure
        theta = est.theta
        nb, nf = np.cumsum([0, *s.nb]), sum(s.nb) + np.cumsum([0, *s.nf])
        dc = [theta[nb[i]:nb[i + 1]].sum() / (1.0 + theta[nf[i]:nf[i + 1]].sum()) for i in range(s.n_inputs)]
        rep = est.report()
        return {"t": t, "names": self.names, "theta": [float(v) for v in theta], "dc_gain": [_num(g) for g in dc],
                "lam": rep["lam"], "trace_P": rep["trace_P"], "dtheta": dtheta,
                "fit_prediction_pct": _num(rep["running_fit_prediction_pct"]),
                "fit_simulation_pct": _num(rep["running_fit_simulation_pct"]), "updates": rep["updates"],
                "noise_variance": _num(rep["noise_variance"])}

    def snapshot(self) -> None:
        """Write the current model to snapshot_path (atomically)."""
        import dataclasses

        from ident.modelfile import save_model

        model = self.est.model()
        if self.est.prior is None:
            model = dataclasses.replace(model, input_names=("EEC1.EngSpeed", "EngTorque"),
                                        input_units=("rpm", self.torque_unit),
                                        output_name="flowmeter.flow_kg_h" if self.fuel == "flowmeter"
                                        else "LFE1.EngFuelRate", output_unit=self.unit)
        save_model(model, self.snapshot_path)
