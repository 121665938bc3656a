"""Which fuel lag `fuelid identify --fuel-lag auto` keeps: the fuel as logged, or the fuel binned one report
period earlier, judged on held-out blocks by the model `fuelid identify` builds.

An ECU that reports the mean fuel rate of the interval since its last report (J1939 LFE1 every 100 ms) sends the
fuel of [t − p, t] at t: binned at its log time, a 0.3 s bin mixes two intervals, and no model of the bins'
means recovers it. Binned at t − p, the reports of a bin tile the bin's own interval (ident.dataset, `fuel_lag_s`).
Whether an ECU averages so is not on the bus; an ECU (or a meter) that samples its fuel at t is right as logged.
So the data decide between two lags, 0 and the candidate p = the fuel signal's median report period
(`Dataset.fuel_period_s`, when 0 < p < Ts), by the yardstick of ident.modelchoice:

Both datasets are cut into the same held-out blocks (the blocks of the dataset as logged, `modelchoice.blocks`;
the same bins of the other). On the fuel as logged, the held-out stage of `identify --model KIND` decides the model's
kind (ident.modelchoice.held_out_choice: with --model auto, the linear or the engine model); at the lag p the model
of that kind is fitted on the first half of the blocks too. Each is simulated on each block of the second half; per
block b the paired improvement of the lagged model over the one as logged, each scored against its own dataset's
fuel (the same measured samples, binned at other times),

    d_b = 1 − e_p,b / e_0,b,

and the lag p is kept when mean(d) > t_{1−α/2}(B − 1) · sd(d)/√B and mean(d) > MIN_IMPROVEMENT (the margins of
ident.modelchoice.paired_improvement), else the fuel as logged. The kept lag's model is then identified on all of
its dataset as `fuelid identify --fuel-lag S` would, with the kind decided on the fuel as logged. The lag costs one
more half-data fit of the kept kind than `--model auto` (an engine model's includes the linear model it starts from).
The kind is not judged again at the lag: a lag of one report period moves the fuel's dynamics, not the engine's map.
"""
from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fuelid.errors import InputError
from fuelid.ident.dataset import Dataset
from fuelid.ident.modelchoice import (ModelKind, PairedImprovement, asked_kind, blocks, chosen_model,
                                      held_out_choice, identify_chosen, paired_improvement)
from fuelid.ident.polymodel import PolyModel, Structure


class LagReason(str, enum.Enum):
    """Why a fuel lag was kept."""

    BETTER = "the fuel binned one report period earlier simulates held-out blocks better by more than the margin"
    NOT_BETTER = "the fuel binned one report period earlier does not simulate held-out blocks better by more than " \
                 "the margin"
    TOO_SHORT = "too little data for held-out blocks"
    NO_CANDIDATE = "the fuel signal's report period is not below Ts"
    FAILED = "the model could not be identified with the fuel binned one report period earlier"


@dataclass(frozen=True)
class LagChoice:
    """The decision, typed: lag_s kept [s], candidate_s (the fuel signal's report period [s], None without one),
    reason; with the held-out figures when judged (held_out: the errors as logged as the base, lagged as the new)."""

    lag_s: float
    candidate_s: float | None
    reason: LagReason
    held_out: PairedImprovement = PairedImprovement()

    def to_json(self) -> dict:
        """model.info["fuel_lag_choice"]."""
        return {"lag_s": self.lag_s, "candidate_s": self.candidate_s, "reason": self.reason.name.lower(),
                **self.held_out.to_json("logged", "lagged")}

    @classmethod
    def from_json(cls, d: dict) -> LagChoice:
        """The choice of a `to_json` content."""
        return cls(d["lag_s"], d["candidate_s"], LagReason[d["reason"].upper()],
                   PairedImprovement.from_json(d, "logged", "lagged"))

    def line(self, unit: str) -> str:
        """One line saying which lag was kept and why."""
        kept = f"fuel lag {self.lag_s:g} s" + (" (as logged)" if self.lag_s == 0 else "")
        if self.held_out.mean is None:
            return f"{kept}: {self.reason.value}"
        return f"{kept}: {self.reason.value} (report period {self.candidate_s:g} s; {self.held_out.text(unit)})"


def candidate_lag_s(ds: Dataset) -> float | None:
    """The lag worth judging [s]: the fuel signal's median report period, to the millisecond (a logger's clock
    jitters by microseconds; J1939 periods are whole milliseconds), when it is above 0 and below Ts."""
    period = round(ds.fuel_period_s, 3)
    return period if 0.0 < period < ds.Ts else None


def at_times(ds: Dataset, t: np.ndarray) -> np.ndarray:
    """The mask over ds's samples of the bins that start at the times t [s] (ascending, on ds's Ts grid)."""
    k = np.rint(ds.t / ds.Ts).astype(np.int64)
    wanted = np.rint(np.asarray(t) / ds.Ts).astype(np.int64)
    at = np.clip(np.searchsorted(wanted, k), 0, max(len(wanted) - 1, 0))
    return (wanted[at] == k) if len(wanted) else np.zeros(len(k), bool)


def identify_lag_chosen(build: Callable[[float], Dataset], structure: Structure, effects=(), *,
                        kind: ModelKind = ModelKind.AUTO, min_segment_s: float, files=(), defined=(),
                        init: PolyModel | None = None) -> tuple[PolyModel, Dataset]:
    """(model, its dataset) of `fuelid identify --fuel-lag auto --model KIND` (module docstring): build(lag_s) gives
    the dataset with the fuel binned lag_s [s] earlier (called again for 0 when the fuel as logged is kept: at most
    one dataset is held at a time); the model's info["fuel_lag_choice"] is the decision
    (`LagChoice.to_json`) and info["model_choice"] the model choice made on the fuel as logged. init: as
    identify_chosen's, for the final fit."""
    kind, effects = asked_kind(kind, effects)
    fit = dict(min_segment_s=min_segment_s, files=files, defined=defined)
    logged = build(0.0)
    candidate = candidate_lag_s(logged)
    masks = blocks(logged, min_segment_s) if candidate is not None else []
    if not masks:
        reason = LagReason.NO_CANDIDATE if candidate is None else LagReason.TOO_SHORT
        model = identify_chosen(logged, structure, effects, kind=kind, init=init, **fit)
        return _with_lag(model, LagChoice(0.0, candidate, reason)), logged
    # one dataset at a time (a truck-week's costs a fleet job most of its memory): the blocks travel as bin times
    times = [logged.t[m] for m in masks]
    choice = held_out_choice(logged, masks, structure, effects, kind, **fit)
    del logged, masks
    lagged = build(candidate)
    try:
        at_lag = held_out_choice(lagged, [at_times(lagged, t) for t in times], structure, effects, choice.kind, **fit)
    except InputError:  # the kind kept as logged is not identifiable at the lag: the fuel as logged
        decision = LagChoice(0.0, candidate, LagReason.FAILED)
    else:
        e0, ep = choice.kept_errors(), at_lag.kept_errors()
        scored = np.isfinite(e0) & np.isfinite(ep)  # a block with no sample left to score at one lag is left out
        p = paired_improvement(e0[scored], ep[scored])
        decision = LagChoice(candidate if p.better else 0.0, candidate,
                             LagReason.BETTER if p.better else LagReason.NOT_BETTER, p)
    if decision.lag_s:
        ds = lagged
    else:
        del lagged
        ds = build(0.0)
    return _with_lag(chosen_model(ds, structure, effects, choice, init=init, **fit), decision), ds


def _with_lag(model: PolyModel, decision: LagChoice) -> PolyModel:
    model.info["fuel_lag_choice"] = decision.to_json()
    return model
