"""Which model `fuelid identify` keeps: the paper's linear Box-Jenkins model, or the engine model (its engine map as a
Hammerstein block under the same dynamics, ident.hammerstein), judged on held-out blocks of the trip.

Blocks: the identification samples (the valid stretches of at least min_segment_s) are cut, in time order, into
`n_blocks` blocks of equal sample count (at most MAX_BLOCKS, each at least MIN_BLOCK_S long; at least MIN_BLOCKS).
Both models are identified on the first half of the blocks (the first half of the trip, in long stretches as the
final fit sees them) and simulated on each block of the second half: per block b the RMS simulation errors e_lin,b
and e_eng,b [fuel unit] of models that never saw its fuel (`block_rmses`: each valid stretch of the trip simulated
as a whole from its speed and torque, from zero state, the stretch's first n_start samples left out), and the paired
relative improvement (the engine model fitted on the first half refined by FOLD_ROUNDS joint rounds, fewer than the
final fit's: if anything, the judge favours the linear model)

    d_b = 1 − e_eng,b / e_lin,b.

The engine model is kept when the mean improvement exceeds the fits' spread and a floor (`paired_improvement`):

    mean(d) > t_{1−α/2}(B − 1) · sd(d)/√B   and   mean(d) > MIN_IMPROVEMENT,

t_{1−α/2}(B − 1) the two-sided Student t quantile at level ALPHA for the B held-out blocks (Student 1908: with 3–8
blocks a fixed 2 SE is narrower than their spread; 2.78 SE for 5 blocks, 2.36 for 8), else the linear model. The
kept model is identified on all the identification samples exactly as `--model linear`
(ident.identify.identify_model) or `--model engine` (`engine_model`: from the linear model) would: the held-out
fits cost one linear and one engine fit on half the data. (A final fit warm-started from a half-data fit is no
cheaper: on the shipped trips PEM then crawls through the flat valley of the paper's near-cancelling orders for its
whole iteration limit and ends above the fit from its own initialisation.)
"""
from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass

import numpy as np
from scipy.special import stdtrit

from fuelid.errors import InputError
from fuelid.ident.hammerstein import JOINT_ROUNDS, MAP_EFFECT
from fuelid.ident.identify import FitMemo, identify_model, training_segments
from fuelid.ident.modeldata import model_data
from fuelid.ident.polymodel import PolyModel, Structure, simulate

MAX_BLOCKS = 16
MIN_BLOCKS = 6
MIN_BLOCK_S = 120.0  # [s]
ALPHA = 0.05  # two-sided level of the paired t margin: a model or lag that is no better is kept at most α/2 of the time
MIN_IMPROVEMENT = 0.02  # [1] the engine model must simulate held-out blocks at least 2 % better on average
FOLD_ROUNDS = 2  # joint rounds of the fold fits' engine models (fewer than the final fit's: a conservative judge)


class ModelKind(str, enum.Enum):
    """`fuelid identify --model`: auto (the held-out choice), linear (the paper's), engine (with the engine map)."""

    AUTO = "auto"
    LINEAR = "linear"
    ENGINE = "engine"


class Reason(str, enum.Enum):
    """Why a model was kept."""

    ASKED = "asked for"
    BETTER = "the engine model simulates held-out blocks better by more than the margin"
    NOT_BETTER = "the engine model does not simulate held-out blocks better by more than the margin"
    TOO_SHORT = "too little data for held-out blocks"
    ENGINE_FAILED = "the engine model could not be identified"


@dataclass(frozen=True)
class PairedImprovement:
    """Two models' RMS simulation errors on the same B held-out blocks [fuel unit], a base's and a new one's, and
    the paired comparison (`paired_improvement`): d per block [1], its mean and standard error [1] and the margin,
    se_factor (the t quantile of the blocks) and min_improvement; mean None when not compared (fewer than two
    blocks, or the errors of one model only)."""

    rmse_base: tuple[float, ...] = ()
    rmse_new: tuple[float, ...] = ()
    d: tuple[float, ...] = ()
    mean: float | None = None
    se: float | None = None
    se_factor: float | None = None
    min_improvement: float = MIN_IMPROVEMENT

    @property
    def better(self) -> bool:
        """mean(d) > se_factor · SE and mean(d) > min_improvement (never when not compared)."""
        return self.mean is not None and self.mean > self.se_factor * self.se and self.mean > self.min_improvement

    def to_json(self, base: str, new: str) -> dict:
        """The "held_out" (None when not compared) and "margin" members of a choice's JSON, the errors named
        rmse_BASE and rmse_NEW."""
        return {"held_out": None if self.mean is None else {
                    "blocks": len(self.d), f"rmse_{base}": list(self.rmse_base), f"rmse_{new}": list(self.rmse_new),
                    "improvement": list(self.d), "improvement_mean": self.mean, "improvement_se": self.se},
                "margin": {"se_factor": self.se_factor, "min_improvement": self.min_improvement}}

    @classmethod
    def from_json(cls, d: dict, base: str, new: str) -> PairedImprovement:
        """The comparison of a `to_json` content."""
        held = d["held_out"] or {}
        return cls(tuple(held.get(f"rmse_{base}", ())), tuple(held.get(f"rmse_{new}", ())),
                   tuple(held.get("improvement", ())), held.get("improvement_mean"), held.get("improvement_se"),
                   d["margin"]["se_factor"], d["margin"]["min_improvement"])

    def text(self, unit: str) -> str:
        """The comparison in words, "held-out RMS error NEW vs BASE UNIT over B blocks: mean ± SE, margin …" (only
        when compared)."""
        return (f"held-out RMS error {np.mean(self.rmse_new):.3g} vs {np.mean(self.rmse_base):.3g} {unit} over "
                f"{len(self.d)} blocks: {100 * self.mean:+.1f} % ± {100 * self.se:.1f} %, margin "
                f"{self.se_factor:.3g} SE and {100 * self.min_improvement:g} %")


@dataclass(frozen=True)
class ModelChoice:
    """The decision, typed: kind kept (LINEAR or ENGINE), asked (the --model value), reason; with the held-out
    figures when judged (held_out: the linear model's errors as the base, the engine model's as the new), and
    detail (the error when the engine model failed)."""

    kind: ModelKind
    asked: ModelKind
    reason: Reason
    held_out: PairedImprovement = PairedImprovement()
    detail: str | None = None

    def to_json(self) -> dict:
        """model.info["model_choice"]."""
        return {"chosen": self.kind.value, "asked": self.asked.value, "reason": self.reason.name.lower(),
                **self.held_out.to_json("linear", "engine"), "detail": self.detail}

    @classmethod
    def from_json(cls, d: dict) -> ModelChoice:
        """The choice of a `to_json` content (model.info["model_choice"])."""
        return cls(ModelKind(d["chosen"]), ModelKind(d["asked"]), Reason[d["reason"].upper()],
                   PairedImprovement.from_json(d, "linear", "engine"), d.get("detail"))

    def kept_errors(self) -> np.ndarray:
        """The kept model's RMS errors on the held-out blocks [fuel unit]."""
        return np.array(self.held_out.rmse_new if self.kind is ModelKind.ENGINE else self.held_out.rmse_base)

    def line(self, unit: str) -> str:
        """One line saying which model was kept and why."""
        kept = "engine model (engine map + the paper's dynamics)" if self.kind is ModelKind.ENGINE \
            else "linear model (the paper's)"
        if self.held_out.mean is None:
            return f"model: {kept}: {self.reason.value}" + (f" ({self.detail})" if self.detail else "")
        return f"model: {kept}: {self.reason.value} ({self.held_out.text(unit)})"


def blocks(ds, min_segment_s: float) -> list[np.ndarray]:
    """The held-out blocks (module docstring): boolean masks over ds's samples; [] when fewer than MIN_BLOCKS fit."""
    segs = training_segments(ds, ds.u, ds.y, min_segment_s)
    if not segs:
        return []
    idx = np.concatenate([np.arange(s.start, s.stop) for s in segs])
    n_blocks = min(MAX_BLOCKS, int(len(idx) * ds.Ts // MIN_BLOCK_S))
    if n_blocks < MIN_BLOCKS:
        return []
    out = []
    for part in np.array_split(idx, n_blocks):
        mask = np.zeros(len(ds.y), bool)
        mask[part] = True
        out.append(mask)
    return out


def _on(ds, mask: np.ndarray):
    """ds with only the samples of mask valid."""
    return dataclasses.replace(ds, valid=ds.valid & mask)


def block_rmses(model: PolyModel, ds, masks) -> tuple[float, ...]:
    """RMS simulation error [fuel unit] of `model` on the samples of each block (a mask over ds's samples): each
    valid stretch of ds simulated once, as a whole from zero state (from the speed and torque alone, never the fuel),
    each block's samples scored after its stretch's first n_start (NaN for a block with none)."""
    u, y = model_data(model, ds)
    scored = np.zeros(len(y), bool)
    err = np.zeros(len(y))
    for s in ds.segments():
        err[s] = y[s] - simulate(model, u[s])
        scored[s] = True
        scored[s.start : s.start + model.structure.n_start] = False
    return tuple(float(np.sqrt(np.mean(err[m & scored] ** 2))) if (m & scored).any() else np.nan for m in masks)


def engine_model(ds, structure: Structure, effects, linear: PolyModel, *, min_segment_s: float, files=(),
                 defined=(), joint_rounds: int = JOINT_ROUNDS) -> PolyModel:
    """The engine model (engine_map, then the linear model's effects), its map started from the static fit on ds:
    without other effects identified from `linear` (the linear model on the same samples: its dynamics, the map's
    inputs at zero), with them as identify_model does (its initialisation and the effects added in turn); then
    jointly with its map (ident.hammerstein, at most joint_rounds rounds)."""
    base = linear if not effects else None
    return identify_model(ds, structure, [MAP_EFFECT, *effects], min_segment_s=min_segment_s, files=files,
                          defined=defined, base=base, memo=FitMemo(), initialisation=bool(effects),
                          joint_rounds=joint_rounds)


def identify_chosen(ds, structure: Structure, effects=(), *, kind: ModelKind = ModelKind.AUTO,
                    min_segment_s: float, files=(), defined=(), init: PolyModel | None = None,
                    base: PolyModel | None = None) -> PolyModel:
    """The model `fuelid identify --model KIND` writes (module docstring), its info["model_choice"] the decision
    (`ModelChoice.to_json`). effects: the other effects asked for (engine_map among them asks for the engine model;
    InputError with kind LINEAR). init, base: as ident.identify.identify_model's, for the linear model on all of ds
    (e.g. a truck's previous model to start from; ignored when of another structure)."""
    kind, effects = asked_kind(kind, effects)
    if kind is not ModelKind.AUTO:
        choice = ModelChoice(kind, kind, Reason.ASKED)
    elif masks := blocks(ds, min_segment_s):
        choice = held_out_choice(ds, masks, structure, effects, kind, min_segment_s=min_segment_s, files=files,
                                 defined=defined)
    else:
        choice = ModelChoice(ModelKind.LINEAR, kind, Reason.TOO_SHORT)
    return chosen_model(ds, structure, effects, choice, min_segment_s=min_segment_s, files=files, defined=defined,
                        init=init, base=base)


def asked_kind(kind: ModelKind, effects) -> tuple[ModelKind, list[str]]:
    """(kind, the other effects): engine_map among the effects asks for the engine model (InputError with LINEAR)."""
    if MAP_EFFECT in effects:
        if kind is ModelKind.LINEAR:
            raise InputError("--effect engine_map asks for the engine model, --model linear for the linear one")
        kind = ModelKind.ENGINE
    return kind, [e for e in effects if e != MAP_EFFECT]


def held_out_choice(ds, masks: list[np.ndarray], structure: Structure, effects, kind: ModelKind, *,
                    min_segment_s: float, files=(), defined=()) -> ModelChoice:
    """The held-out stage on the blocks `masks` (module docstring): the models fitted on the first half of the
    blocks and their RMS simulation errors on each block of the second half. kind AUTO: the decision; LINEAR or
    ENGINE: that model, reason ASKED, with its errors (rmse_linear or rmse_engine) and no decision."""
    fit = dict(min_segment_s=min_segment_s, files=files, defined=defined)
    half = len(masks) // 2
    fitted_on = _on(ds, np.any(masks[:half], axis=0))
    rmse_lin = ()
    try:
        lin = identify_model(fitted_on, structure, effects, **fit)
        rmse_lin = block_rmses(lin, ds, masks[half:]) if kind is not ModelKind.ENGINE else ()
        if kind is ModelKind.LINEAR:
            return ModelChoice(kind, kind, Reason.ASKED, PairedImprovement(rmse_lin))
        eng = engine_model(fitted_on, structure, effects, lin, joint_rounds=FOLD_ROUNDS, **fit)
    except InputError as exc:
        if kind is not ModelKind.AUTO:
            raise
        return ModelChoice(ModelKind.LINEAR, kind, Reason.ENGINE_FAILED, PairedImprovement(rmse_lin), str(exc))
    rmse_eng = block_rmses(eng, ds, masks[half:])
    if kind is not ModelKind.AUTO:
        return ModelChoice(kind, kind, Reason.ASKED, PairedImprovement(rmse_lin, rmse_eng))
    p = paired_improvement(rmse_lin, rmse_eng)
    return ModelChoice(ModelKind.ENGINE if p.better else ModelKind.LINEAR, kind,
                       Reason.BETTER if p.better else Reason.NOT_BETTER, p)


def paired_improvement(e_base, e_new) -> PairedImprovement:
    """Two models' RMS errors on the same B held-out blocks compared (module docstring): d_b = 1 − e_new,b / e_base,b
    [1], SE = sd(d)/√B, and better when mean(d) > t_{1−ALPHA/2}(B − 1) · SE and mean(d) > MIN_IMPROVEMENT (a one-sided
    paired t-test at level ALPHA/2 with a floor; never with a NaN, and with fewer than two blocks no figures at all)."""
    e_base, e_new = tuple(float(v) for v in e_base), tuple(float(v) for v in e_new)
    d = 1.0 - np.asarray(e_new) / np.asarray(e_base)
    if len(d) < 2:
        return PairedImprovement(e_base, e_new, tuple(float(v) for v in d))
    mean, se = float(d.mean()), float(d.std(ddof=1) / np.sqrt(len(d)))
    factor = float(stdtrit(len(d) - 1, 1.0 - ALPHA / 2))
    return PairedImprovement(e_base, e_new, tuple(float(v) for v in d), mean, se, factor)


def chosen_model(ds, structure: Structure, effects, choice: ModelChoice, *, min_segment_s: float, files=(),
                 defined=(), init: PolyModel | None = None, base: PolyModel | None = None) -> PolyModel:
    """The model of choice.kind identified on all of ds (`identify_chosen`'s), with the choice in its info."""
    fit = dict(min_segment_s=min_segment_s, files=files, defined=defined)
    linear = identify_model(ds, structure, effects, init=init, base=base, **fit)
    if choice.kind is ModelKind.LINEAR:
        return _chosen(linear, choice)
    return _chosen(engine_model(ds, structure, effects, linear, **fit), choice)


def _chosen(model: PolyModel, choice: ModelChoice) -> PolyModel:
    model.info["model_choice"] = choice.to_json()
    return model
