"""A candidate effect of the diagnosis as a typed record: what its tests found (`Evidence`) and what the diagnosis
says of it (`Candidate`, serialised by `to_json` as `fuelid diagnose --json` lists it)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fuelid.ident import effects as fx

JSON_FIELDS = ("effect", "spec", "name", "form", "signals", "spns", "statistic", "df", "p_value", "log10_p",
               "testable", "tests", "estimated_drop_percent", "size", "explanation", "physics", "p_holm",
               "test_significant", "significant", "recommended", "role", "rmse_drop_percent", "verification",
               "conditional", "refit", "explained_by", "alternatives")
UNTESTED_FIELDS = ("effect", "name", "form", "signals", "spns", "testable", "statistic", "df", "p_value",
                   "significant", "test_significant", "estimated_drop_percent", "explanation", "rmse_drop_percent",
                   "verification", "conditional", "explained_by")


@dataclass
class Evidence:
    """What an entry kind's test of an effect found (ident.diagnosis.entries): reg its regressors on the dataset
    grid, x their lagged columns in the fuel domain stacked like Run.r, w = A x (x in the domain of w), tests
    {name: ScoreTest}, left the fraction of the simulation error left after fitting them, coef the coefficients
    the explanation starts from, ref the reference model of a fuel-signal delay (ident.diagnosis.delay.Reference)
    or None."""

    reg: fx.Regressors
    x: np.ndarray
    w: np.ndarray
    tests: dict
    left: float
    coef: np.ndarray
    ref: object = None


@dataclass
class Candidate:
    """One candidate effect (ident.diagnosis.diagnose's docstring lists the fields). `tests` is None when its bus
    signals are not in the data (then it serialises only the fields an untested candidate has); definition,
    entry, reg, x, w (x in the domain of w, A x), X (its verified columns) and ref are the working data of the
    diagnosis, never serialised."""

    effect: str
    name: str
    form: str
    signals: list
    spns: list
    physics: str
    explanation: str
    spec: str | None = None
    statistic: float | None = None
    df: int = 0
    p_value: float | None = None
    log10_p: float = 0.0
    testable: bool = False
    tests: dict | None = None
    estimated_drop_percent: float | None = None
    size: dict | None = None
    p_holm: float | None = None
    test_significant: bool = False
    significant: bool = False
    recommended: bool = False
    rmse_drop_percent: float | None = None
    verification: dict | None = None
    conditional: dict | None = None
    refit: dict | None = None  # forward selection's PEM refit with it: RMS simulation error without/with, verified
    explained_by: str | None = None
    alternatives: list = field(default_factory=list)  # rivals these data cannot tell it from (selection, 5)
    role: str | None = None  # what a named candidate is: ENGINE_MAP (the engine's own curvature) or MISSING_EFFECT
    definition: fx.Effect | None = field(default=None, repr=False)
    entry: object = field(default=None, repr=False)
    reg: fx.Regressors | None = field(default=None, repr=False)
    x: np.ndarray | None = field(default=None, repr=False)
    w: np.ndarray | None = field(default=None, repr=False)
    X: np.ndarray | None = field(default=None, repr=False)
    ref: object = field(default=None, repr=False)

    def to_json(self) -> dict:
        """The candidate as `fuelid diagnose --json` lists it."""
        return {k: getattr(self, k) for k in (JSON_FIELDS if self.tests is not None else UNTESTED_FIELDS)}


def confirmed_effects(candidates: list[dict]) -> list[str]:
    """The effects a diagnosis (its JSON `candidates`) recommends adding: named as missing and verified on
    held-out data, and on held-out trips when it had several (`recommended`; a result without that field
    recommends none), in the order found, as `fuelid identify --effect` and identify_model take them (a fuel
    delay with the shift found: fuel_delay=0.36)."""
    return [c.get("spec", c["effect"]) for c in candidates if c.get("recommended") is True]


ENGINE_MAP = "engine map"  # the role of the engine's own static curvature: a property of the engine (verdict, 0)
MISSING_EFFECT = "missing effect"  # the role of a hidden effect the forward selection named
