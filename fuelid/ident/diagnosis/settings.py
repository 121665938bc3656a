"""Every threshold of the diagnosis, with its meaning, in one frozen object (`Settings`)."""
from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class Settings:
    """The diagnosis's thresholds (docs/explanation/diagnosis.md names each one in its equations)."""

    alpha: float = 0.05
    """Family-wise error rate of the screening: Holm's step-down over the hidden-effect candidates, and the level of
    the engine-map test on its own. On a trip with nothing hidden, any recommendation needs a screening rejection
    first, so the probability of recommending anything is at most alpha (asymptotically, as the score tests)."""

    min_effect_percent: float = 1.0
    """[%] Share of the simulation error a significant candidate's least-squares fit must explain to be built:
    smaller effects are detectable with many samples but not worth an input."""

    min_share_beyond_inputs: float = 0.1
    """[1] Share of a bus signal's variance a static quadratic map of engine speed and torque must leave
    (ident.effects.share_beyond_inputs) for its generic forms to be built: below it (a variance inflation factor
    above 10, as for identifiability) speed and torque determine the signal, and what it explains is the engine's
    own fuelling at its operating point, not a hidden effect."""

    max_builds: int = 3
    """Candidates built per round of forward selection (the screened ones that explain the largest share of
    the simulation error): each build is one refit per fold, the diagnosis's cost. When none passes, the pairs of
    those with stated physics are built too (ident.diagnosis.selection)."""

    block_s: float = 30.0
    """[s] Length of the scoring blocks: the held-out simulation error is summed per block, and the blocks are the
    pairs whose spread gives the margin."""

    chunk_s: float = 120.0
    """[s] Length of the stretches a fold leaves out on data of one trip (a whole number of scoring blocks, longer so
    that the stretches fitted on between them are long beside the model's start-up)."""

    folds: int = 4
    """Folds on data of one trip: fold k leaves out every chunk whose index is k modulo `folds` (interleaved, so each
    fit sees every part of the trip). With several trips each trip is a fold instead."""

    trip_break_s: float = 600.0
    """[s] A break of the log at least this long starts another trip (another file, another day)."""

    margin_se: float = 2.0
    """k of the yardstick: the mean of the per-block paired improvements (MSE without − MSE with), or their trimmed
    mean (`trim`), must exceed k standard errors of it (their long-run spread over the blocks, Newey–West: what the
    fits and the noise move, neighbouring blocks correlated)."""

    trim: float = 0.2
    """[1] Share of the block improvements left out at each end of the yardstick's trimmed mean (Yuen's; 0.2 as Wilcox
    recommends). An effect on most blocks whose spread one or two transient blocks decide (a cold start) passes on
    it; one that acts in a few blocks (a regeneration) on the plain mean."""

    min_drop_percent: float = 1.0
    """[%] Relative floor of the yardstick: the pooled held-out RMS simulation error must fall by at least this much
    (a real but negligible improvement is not worth an input)."""

    min_fuel_percent: float = 0.7
    """[%] Floor of the yardstick in fuel: the RMS of the fuel a candidate's model explains beyond the base on
    held-out data, √(RMSE_without² − RMSE_with²), must be at least this share of the mean fuel there. On trips with
    nothing hidden an engine model close to its noise floor still leaves a little structured error at overrun and
    gear-shift transients, which a flexible candidate takes up significantly: mostly 0.1–0.5 % of the fuel on the
    training draws, against at least 1 % for the effects found at half their stated magnitudes
    (docs/explanation/diagnosis.md)."""

    refit_max_iter: int = 20
    """Levenberg–Marquardt iterations of each refit (warm-started from the base model: few suffice)."""

    max_rounds: int = 6
    """Rounds of forward selection at most (one effect accepted per round)."""

    def to_json(self) -> dict:
        return asdict(self)
