"""The diagnosis as the engineer reads it, rendered once from the typed decisions (ident.diagnosis.candidate): each
candidate's explanation, the verdict, and the JSON `fuelid diagnose --json` prints (which the CLI text and the report
lay out)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.candidate import MAP_EFFECT, Candidate, EngineMap, MapStatus, Status
from fuelid.ident.diagnosis.settings import Settings
from fuelid.ident.diagnosis.size import EffectSize
from fuelid.ident.modelrun import ModelRun

ADD = "`fuelid identify --effects-from DIAGNOSIS.json` adds what is recommended"


def _gain(c: Candidate | EngineMap) -> str:
    h = c.held_out
    said = {"paired gain {:.1f} standard errors": h.gain_in_se,  # the largest of the yardstick's statistics decides
            "trimmed mean paired gain {:.1f} standard errors": h.trimmed_in_se,
            "paired gain {:.1f} standard errors beyond a placebo's (its signals shifted by half the data)":
                h.beyond_null_in_se if math.isfinite(h.beyond_null_in_se) else -math.inf}
    words, t = max(said.items(), key=lambda kv: kv[1])
    return f"held-out RMS error {h.rmse_without:.3g} → {h.rmse_with:.3g} ({-h.drop_percent:+.1f} %, " \
           f"{words.format(t)} over {h.n_blocks} blocks, {h.fuel_percent:.2g} % of the fuel)"


def _pair_text(c: Candidate) -> str:
    """What a candidate accepted together with another is said to be (its held-out gain is beyond the other's
    model)."""
    return f"with {c.together_with} beside it (neither passes alone; together, each lowers the held-out error beyond " \
           "the model with the other)"


def _alternatives_text(c: Candidate) -> str:
    """What is said of a recommended candidate's alternatives (ident.diagnosis.selection): '' without any."""
    if not c.alternatives:
        return ""
    return f"; these data do not tell it apart from {', '.join(c.alternatives)}: neither model simulates held-out " \
           "blocks better than the other beyond the margin"


def signals_text(effect) -> str:
    """An effect's bus signals as the engineer reads them: DBC names with their SPNs."""
    spn = {s: fx.spn_of(s) for s in effect.signals}
    return ", ".join(f"{s} (SPN {spn[s]})" if spn[s] is not None else s for s in effect.signals)


def size_text(z: EffectSize) -> str:
    """An effect's size in a model built with it (ident.diagnosis.size) in words, with its units."""
    said = {
        "state": lambda: f"{z.value:+.3g} {z.unit} while on" + (f" ({z.percent:+.1f} %)" * math.isfinite(z.percent)),
        "scales_fuel": lambda: f"the fuel scaled by {z.percent:+.3g} % per {z.x_unit}",
        "torque": lambda: f"fuel burnt for {z.value:.3g} {z.value_unit} of torque the bus does not report",
        "additive": lambda: f"{z.value:+.3g} {z.value_unit}",
        "shift": lambda: f"the fuel signal lags by {z.value:.2f} s",
    }[z.form]()
    return f"{said}, RMS fuel contribution {z.rms:.3g} {z.unit}"


def _template(c: Candidate) -> str | None:
    """An engineer-defined effect's explanation template (ident.effectfile) filled with its size, once recommended."""
    z, template = c.size, c.definition.template
    if template is None or z is None or not c.recommended:
        return None
    return template.format(signals=signals_text(c.definition), size=z.value, percent=z.percent, rms=z.rms,
                           unit=z.unit, x_unit=z.x_unit)


def explanation(c: Candidate) -> str:
    """What the diagnosis says of one candidate: its status and the evidence that decided it; once recommended, its
    size (an engineer-defined effect's own sentence when it has one)."""
    s = c.screening
    p = "" if s is None else f"p = {s.p_value:.2g} (Holm {s.p_holm:.2g}), explains {s.explains_percent:.1f} % of " \
                             "the simulation error"
    size = "" if c.size is None else f"; {_template(c) or size_text(c.size)}"
    return {
        Status.RECOMMENDED: lambda: "recommended" + f", {_pair_text(c)}" * bool(c.together_with)
                                    + f": {_gain(c)}{size}{_alternatives_text(c)}",
        Status.NAMED_NOT_RECOMMENDED: lambda: f"named, not recommended: {c.reason.value}" + (
            f" ({_gain(c)}{size})" if c.held_out is not None else "") + f"; {p}",
        Status.EXPLAINED_BY: lambda: f"explained by {c.explained_by}: significant before it was added, not after",
        Status.NOT_SIGNIFICANT: lambda: f"not significant: {p}",
        Status.TOO_SMALL: lambda: f"too small: {p}",
        Status.NOT_TESTABLE: lambda: "not testable: its bus signals are not in the data, or the model's own "
                                     "columns span it",
        Status.ALREADY_IN_MODEL: lambda: "already in the model" + (
            ": the engine model's map cuts the injection (no fuel at and below zero torque)"
            if c.explained_by == MAP_EFFECT else ""),
    }[c.status]()


def map_sentence(m: EngineMap) -> str:
    """What the diagnosis says of the engine's own map (MapStatus)."""
    return {
        MapStatus.IN_MODEL: "the engine's map is part of the model",
        MapStatus.ADVISED: "the engine's fuel map is curved and the linear model misses it: identify the engine "
                           f"model (`fuelid identify --effect {MAP_EFFECT}`; `--effects-from` adds it) — "
                           + (_gain(m) if m.held_out else ""),
        MapStatus.NOT_NEEDED: "the engine model does not lower the held-out error beyond the margin: the linear "
                              "model is enough here",
        MapStatus.NOT_TESTABLE: "the engine map could not be tested on these data",
    }[m.status]


def verdict(candidates: list[Candidate], m: EngineMap, settings: Settings) -> str:
    """The verdict: the engine map when advised, the recommended effects, and those named but not recommended."""
    rec = [c for c in candidates if c.status is Status.RECOMMENDED]
    named = [c for c in candidates if c.status is Status.NAMED_NOT_RECOMMENDED]
    parts = [map_sentence(m)] if m.status is MapStatus.ADVISED else []
    if rec:
        parts.append("missing effect" + "s" * (len(rec) > 1) + " recommended: "
                     + "; ".join(f"add {c.spec or c.effect} (" + f"{_pair_text(c)}: " * bool(c.together_with)
                                 + f"{_gain(c)}{_alternatives_text(c)})" for c in rec) + f" — {ADD}")
    parts += [f"{c.effect} is named by the screening but not recommended: {c.reason.value}" for c in named]
    if not rec and m.status is not MapStatus.ADVISED:
        parts.append(f"no missing effect recommended: none lowers the held-out simulation error by more than "
                     f"{settings.margin_se:g} standard errors, {settings.min_drop_percent:g} % "
                     f"and {settings.min_fuel_percent:g} % of the fuel "
                     f"(screening: Holm, family-wise α = {settings.alpha:g})")
    return ". ".join(parts) + "."


def candidate_json(c: Candidate) -> dict:
    """One candidate as `fuelid diagnose --json` lists it (`id`, `effect`, `recommended`, `status`, … flat; the
    evidence under `screening` and `held_out`)."""
    e, s, h = c.definition, c.screening, c.held_out
    return {"id": c.effect, "effect": c.effect, "spec": c.spec or c.effect, "name": e.name, "form": e.form,
            "signals": list(e.signals), "spns": list(e.spns), "physics": e.physics,
            "status": c.status.value, "reason": c.reason and c.reason.name.lower(), "explained_by": c.explained_by,
            "recommended": c.recommended, "together_with": c.together_with, "alternatives": list(c.alternatives),
            "significant": c.named,
            "testable": s is not None, "round": c.round,
            "statistic": s and s.statistic, "df": s.df if s else 0, "p_value": s and s.p_value,
            "p_holm": s and s.p_holm, "estimated_drop_percent": s and s.explains_percent,
            "rmse_drop_percent": h and h.drop_percent, "size": c.size and c.size.to_json(),
            "screening": s and s.to_json(), "held_out": h and h.to_json(), "explanation": explanation(c)}


STATUS_ORDER = list(Status)


@dataclass
class Diagnosis:
    """The whole diagnosis (ident.diagnosis.pipeline.diagnose): candidates with their statuses (recommended ones
    first, in the order accepted), the engine map, and the model run it read (for the report, never serialised)."""

    model: dict
    data: dict
    compare: dict
    held_out: dict | None
    where_it_fails: dict
    candidates: list[Candidate]
    engine_map: EngineMap
    settings: Settings
    samples: int
    run: ModelRun = field(repr=False)

    @property
    def recommended(self) -> list[Candidate]:
        return [c for c in self.candidates if c.recommended]

    @property
    def verdict(self) -> str:
        return verdict(self.candidates, self.engine_map, self.settings)

    def to_json(self) -> dict:
        m = self.engine_map
        tested = sum(c.screening is not None for c in self.candidates)
        return {"model": self.model, "data": self.data, "compare": self.compare, "held_out": self.held_out,
                "where_it_fails": self.where_it_fails,
                "test": {"method": "screening by two score tests per candidate (prediction and simulation errors, "
                                   "Newey-West robust) with Holm over the family; a candidate is recommended when "
                                   "the model refitted with it lowers the held-out simulation error (blocks or "
                                   "trips left out of the fit) by more than the margin; forward selection",
                         "alpha": self.settings.alpha, "candidates_tested": tested, "samples": self.samples,
                         "settings": self.settings.to_json()},
                "engine_map": {"effect": MAP_EFFECT, "status": m.status.value, "explanation": map_sentence(m),
                               "screening": m.screening and m.screening.to_json(),
                               "held_out": m.held_out and m.held_out.to_json()},
                "missing_effects": [c.effect for c in self.recommended],
                "candidates": [candidate_json(c) for c in self.candidates], "verdict": self.verdict}
