"""The decisions of the diagnosis as typed state: a candidate's `Status` (and its `Reason` when named but not
recommended), its evidence (`Screening`, `HeldOut`) and the engine map's own `MapStatus`. Every text, the JSON and
the report are rendered from these (ident.diagnosis.render), never the other way round."""
from __future__ import annotations

import enum
import math
from dataclasses import asdict, dataclass

from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.size import EffectSize


class Status(enum.Enum):
    """What the diagnosis concludes of one candidate effect."""

    RECOMMENDED = "recommended"  # screened, built, and the model with it lowers the held-out error beyond the margin
    NAMED_NOT_RECOMMENDED = "named, not recommended"  # significant in the screening; not recommended (Reason)
    EXPLAINED_BY = "explained by"  # passed the screening, not once another was accepted (explained_by)
    NOT_SIGNIFICANT = "not significant"  # the screening does not reject "no such effect" (Holm at alpha)
    TOO_SMALL = "too small"  # significant, but explains less than min_effect_percent of the simulation error
    NOT_TESTABLE = "not testable"  # its bus signals are not in the data, or its columns are the model's own
    ALREADY_IN_MODEL = "already in the model"


class Reason(enum.Enum):
    """Why a candidate named by the screening is not recommended."""

    NO_HELD_OUT_GAIN = "the model built with it does not lower the held-out error beyond the margin"
    AGAINST_ITS_PHYSICS = ("the model built with it lowers the held-out error, but fits it against its stated "
                           "physics: what it gains is not this effect")
    BUILD_FAILED = "the model could not be identified with it"
    NOT_BUILT = "candidates that explain more used this round's builds"
    SELECTION_STOPPED = "forward selection reached its round limit before re-testing it"
    DETERMINED_BY_INPUTS = ("engine speed and torque determine its bus signal: what it explains is the engine's own "
                            "fuelling at its operating point, not a hidden effect")


class MapStatus(enum.Enum):
    """The engine's own curvature (effects engine_map, power_nonlinearity): part of the engine model, never a
    hidden-effect candidate."""

    IN_MODEL = "in the model"  # the base model is the engine model (or has a curvature term)
    ADVISED = "advised"  # base linear, and the engine model lowers the held-out error beyond the margin
    NOT_NEEDED = "not needed"  # base linear; the curvature test or the yardstick does not call for the map
    NOT_TESTABLE = "not testable"


CURVATURE = ("engine_map", "power_nonlinearity")  # the engine's own map, never a hidden-effect candidate
MAP_EFFECT = "engine_map"  # what the engine model adds to the linear one (`fuelid identify --effect engine_map`)
# what the engine model carries beside its curvature: the injection cut (its map is 0 fuel at and below zero torque,
# ident.enginemap.CUT_TORQUE), a candidate on a linear model only
IN_ENGINE_MODEL = ("overrun_cutoff",)


@dataclass(frozen=True)
class Screening:
    """A candidate's screening (ident.diagnosis.screening): the larger LM statistic of its two score tests, its
    degrees of freedom, the Bonferroni p-value over the two (log10 too: it does not underflow), Holm's adjusted
    p-value in its round's family, whether Holm rejects, and the share [%] of the simulation error its
    least-squares fit explains. coef: the coefficients of its columns (the fuel delay's τ is read from them)."""

    statistic: float
    df: int
    p_value: float
    log10_p: float
    p_holm: float
    significant: bool
    explains_percent: float
    coef: tuple = ()

    def to_json(self) -> dict:
        out = asdict(self)
        out.pop("coef")
        return out


@dataclass(frozen=True)
class HeldOut:
    """The yardstick (ident.diagnosis.yardstick) of one model against the base: RMS held-out simulation error
    [output unit] without and with, its drop [%], the RMS of the fuel it explains beyond the base as a share of the
    mean fuel there [%], the per-block paired improvement's mean and its standard error [(output unit)²], the number
    of blocks, the folds ("blocks" or "trips"), whether it passes (the mean, the trimmed mean or the mean beyond a
    placebo's > k·SE, and both floors), the improvement's trimmed mean and its standard error [(output unit)²],
    whether both floors are met, and the placebo's (ident.diagnosis.yardstick.placebo) mean improvement and its
    standard error [(output unit)²] (NaN when no placebo was built)."""

    rmse_without: float
    rmse_with: float
    drop_percent: float
    fuel_percent: float
    mean_gain: float
    gain_se: float
    n_blocks: int
    folds: str
    passes: bool
    trimmed_gain: float = 0.0
    trimmed_se: float = float("inf")
    floors_met: bool = False
    null_gain: float = float("nan")
    null_se: float = float("nan")

    @property
    def gain_in_se(self) -> float:
        return _in_se(self.mean_gain, self.gain_se)

    @property
    def trimmed_in_se(self) -> float:
        return _in_se(self.trimmed_gain, self.trimmed_se)

    @property
    def beyond_null_in_se(self) -> float:
        """(d̄ − d̄_p) / (√2 SE(d̄_p)): the mean gain beyond the placebo's in standard errors of the difference of two
        draws of the placebo's mean (NaN without a placebo)."""
        if not (math.isfinite(self.null_se) and self.null_se > 0):  # none, or one that changed nothing
            return float("nan")
        return _in_se(self.mean_gain - self.null_gain, math.sqrt(2.0) * self.null_se)

    def to_json(self) -> dict:
        return {**asdict(self), "gain_in_se": self.gain_in_se, "trimmed_in_se": self.trimmed_in_se,
                "beyond_null_in_se": self.beyond_null_in_se}


def _in_se(gain: float, se: float) -> float:
    return gain / se if se > 0 else float("inf") * (gain > 0)


@dataclass(eq=False)  # one candidate is one object: `in` and remove() go by identity
class Candidate:
    """One candidate effect and what the diagnosis concluded (status, reason, explained_by), with its evidence.
    spec: what `fuelid identify --effect` takes (a fuel delay with its τ); round: the forward-selection round of its
    last screening (1 the model as given); size: its size (ident.diagnosis.size) in the model built with it once it
    passed the yardstick, in the model with everything recommended once recommended; together_with: the candidate
    it was accepted with, when neither passed alone and the two together do, each beyond the other
    (ident.diagnosis.selection; held_out is then its gain beyond the other); alternatives: the candidates that passed
    in the round it was accepted in whose models neither beat nor are beaten by its own beyond the margin (these
    data cannot tell them apart)."""

    definition: fx.Effect
    status: Status = Status.NOT_TESTABLE
    reason: Reason | None = None
    explained_by: str | None = None
    screening: Screening | None = None
    held_out: HeldOut | None = None
    spec: str | None = None
    round: int = 0
    size: EffectSize | None = None  # once built and passed (class docstring)
    together_with: str | None = None
    alternatives: tuple[str, ...] = ()

    def decide(self, status: Status, reason: Reason | None = None, explained_by: str | None = None) -> None:
        """Set the status, with its reason (NAMED_NOT_RECOMMENDED) or the candidate that explains it (EXPLAINED_BY;
        ALREADY_IN_MODEL: MAP_EFFECT when the engine model carries it, `carried_by_engine_model`) and nothing else."""
        self.status, self.reason, self.explained_by = status, reason, explained_by

    @property
    def effect(self) -> str:
        return self.definition.id

    @property
    def recommended(self) -> bool:
        return self.status is Status.RECOMMENDED

    @property
    def named(self) -> bool:
        return self.status in (Status.RECOMMENDED, Status.NAMED_NOT_RECOMMENDED)


@dataclass(frozen=True)
class EngineMap:
    """The engine map's status and, when tested, its evidence (as a candidate's)."""

    status: MapStatus
    screening: Screening | None = None
    held_out: HeldOut | None = None


def confirmed_effects(candidates: list[dict]) -> list[str]:
    """The effects a diagnosis (its JSON `candidates`) recommends adding, exactly those with `recommended` true, in
    the order accepted, as `fuelid identify --effect` and identify_model take them (a fuel delay with its τ:
    fuel_delay=0.36)."""
    return [c.get("spec") or c.get("id") or c["effect"] for c in candidates if c.get("recommended") is True]


def effects_to_add(result: dict) -> list[str]:
    """What `fuelid identify --effects-from` adds for a saved `fuelid diagnose --json` result: the engine map first
    when the diagnosis advises the engine model, then the recommended effects (`confirmed_effects`)."""
    engine_map = result.get("engine_map")
    advised = isinstance(engine_map, dict) and engine_map.get("status") == MapStatus.ADVISED.value
    return [MAP_EFFECT] * advised + confirmed_effects(result["candidates"])


def carried_by_engine_model(candidates: list[Candidate]) -> list[Candidate]:
    """The candidates of IN_ENGINE_MODEL not already in the model, decided ALREADY_IN_MODEL explained by the engine
    map (on an engine model, or once the map is accepted)."""
    carried = [c for c in candidates if c.effect in IN_ENGINE_MODEL and c.status is not Status.ALREADY_IN_MODEL]
    for c in carried:
        c.decide(Status.ALREADY_IN_MODEL, explained_by=MAP_EFFECT)
    return carried
